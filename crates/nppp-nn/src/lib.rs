//! The neural estimator in Burn: encoder, decoder and mask network (and,
//! for objects that take light samples, the vertex head that returns a
//! skipped vertex for next-event estimation), their training (Chamfer +
//! energy distance + mask BCE, Adam), the model
//! directory with its checksummed checkpoints (`model_dir`), baking to
//! `.nppp`, and the decoder as a Burn backend of the estimator interface
//! (`decoder::BurnDecoder`, an `nppp_estimator::ExitDecoder` that
//! `nppp render --decoder burn-*` attaches).
//!
//! The renderer never links this crate's training stack: it reads the baked
//! file through `nppp-estimator`. This crate is what `nppp train` and
//! `nppp bake` call; see the README for the model directory layout and the
//! measured numbers behind the defaults.

pub mod backend;
pub mod bake;
pub mod data;
pub mod decoder;
pub mod eval;
pub mod features;
pub mod io;
pub mod loss;
pub mod model;
pub mod model_dir;
pub mod synthetic;
pub mod train;

pub use backend::BackendKind;
pub use bake::{BakeOptions, BakeReport, bake, bake_sweep};
pub use data::{DataSplit, RaySample, TrainingData};
pub use eval::{BurnEstimator, EvalOptions, ExitSource, HeldoutMetrics, evaluate};
pub use features::{INPUT_FEATURES, ray_features};
pub use io::{DatasetInfo, ModelMeta, load_dataset, load_dataset_where, synthetic_header};
pub use model::{MlpNet, ModelConfig, NpppModel};
pub use model_dir::{LoadedModel, load_model_dir};
pub use train::{
    TrainConfig, TrainError, TrainOptions, TrainReport, in_training_loop, request_stop,
    stop_requested, train, train_with_data,
};
