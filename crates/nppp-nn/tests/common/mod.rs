//! Shared by the integration tests: a training configuration small enough
//! for seconds-long runs on two cores.

use nppp_nn::{BackendKind, TrainOptions};
use std::path::Path;

/// A small, fast configuration on NdArray, writing to `out`.
pub fn small_opts(out: &Path) -> TrainOptions {
    let mut o = TrainOptions::new("synthetic", out);
    o.backend = BackendKind::Ndarray;
    o.quiet = true;
    o.batch = Some(16);
    o.k = Some(8);
    o.mask_batch = Some(64);
    o.encoder_width = Some(64);
    o.decoder_width = Some(32);
    o.eval_rays = Some(32);
    o.steps_per_epoch = Some(25);
    o.seed = Some(5);
    o.minutes = 0.0;
    o
}
