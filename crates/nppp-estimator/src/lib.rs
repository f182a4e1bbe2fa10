//! The estimator's data and runtime, free of any training stack: the exit
//! sample and its learning transform, the picked vertex for next-event
//! estimation and its transform, the training-data file and its shards, the baked
//! `.nppp` file (quantized 4D latent and mask grids plus decoder weights), and
//! the estimator interface every caller uses: [`EstimatorSampler`] (mask,
//! answered from its sign table where that knows, latent lookup, one
//! batched decode path) over an [`ExitDecoder`] backend
//! (plain Rust here; nppp-nn implements it for Burn).

pub mod baked;
pub mod dataset;
pub mod decoder;
pub mod dense_kernel;
pub mod exit;
pub mod grid;
pub mod mask_sign;
pub mod mlp;
pub mod quant;
pub mod recipe;
pub mod sampler;
pub mod shard;
pub mod vertex;

/// Relative margin of an estimator's bounding sphere around its mesh
/// (`BoundingSphere::around`): no vertex may lie on the sphere itself, or
/// input rays would start inside the surface. Data generation and the
/// renderer must use the same sphere, so this has one home.
pub const SPHERE_MARGIN: f32 = 0.01;

pub use baked::{BakedEstimator, EstimatorFileError, EstimatorMeta, VertexHead};
pub use dataset::{DatasetError, DatasetHeader, DatasetReader, DatasetSummary, DatasetWriter, RayRecord, WriterOptions};
pub use decoder::{CpuDecoder, ExitDecoder};
pub use dense_kernel::KernelIsa;
pub use exit::{
    DecodeRepairs, EXIT_FEATURES, EXIT_THROUGHPUT_BOUND, EXIT_THROUGHPUT_BOUND_MEDIUM, Exit, ExitBounds, ExitTransform,
    exit_throughput_bound,
};
pub use grid::{Corners, QuantizedGrid, node_coords, node_count};
pub use mlp::{Dense, Mlp};
pub use quant::{QuantError, dequantize, quantize};
pub use sampler::{DecodedBatch, EstimatorSampler, ExitBatch};
pub use vertex::{PickedVertex, VERTEX_FEATURES, VERTEX_THROUGHPUT_BOUND, VertexTransform};
