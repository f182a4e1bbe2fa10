//! The training log, log.csv: its columns, one row per log or evaluation
//! point, and the live copy beside the checkpoint.

use std::path::Path;

use crate::eval::HeldoutMetrics;

pub(super) const LOG_HEADER: &str = "epoch,step,elapsed_s,lr,train_loss,train_chamfer,train_energy,train_bce,\
heldout_chamfer,heldout_energy,heldout_bce,mask_accuracy,throughput_error,throughput_bias,\
throughput_noise_floor,throughput_rms_error,radiance_error,radiance_bias,seconds_per_step";

/// One row of log.csv (see `LOG_HEADER`); the held-out columns are empty
/// on rows without an evaluation.
pub(super) fn log_row(
    epoch: f64,
    step: u64,
    elapsed_s: f64,
    lr: f64,
    train: &[f64],
    heldout: Option<&HeldoutMetrics>,
    seconds_per_step: f64,
) -> String {
    let held = match heldout {
        Some(m) => format!(
            "{:.6},{:.6},{:.6},{:.5},{:.5},{:.5},{:.5},{:.5},{:.5},{:.5}",
            m.chamfer,
            m.energy,
            m.mask_bce,
            m.mask_accuracy,
            m.throughput_error,
            m.throughput_bias,
            m.throughput_noise_floor,
            m.throughput_rms_error,
            m.radiance_error,
            m.radiance_bias
        ),
        None => ",,,,,,,,,".to_string(),
    };
    format!(
        "{epoch:.4},{step},{elapsed_s:.2},{lr:.4e},{:.6},{:.6},{:.6},{:.6},{held},{seconds_per_step:.5}",
        train[0], train[1], train[2], train[3]
    )
}

/// Appends a row to the log.csv beside the checkpoint (a copy for people
/// watching the run; best effort: the checkpoint holds the real log).
pub(super) fn append_live_row(path: &Path, row: &str) {
    use std::io::Write;
    if let Ok(mut f) = std::fs::OpenOptions::new().append(true).open(path) {
        let _ = writeln!(f, "{row}");
    }
}
