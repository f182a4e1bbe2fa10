//! What a training run hands back: the [`TrainReport`] that `nppp train`
//! prints, and the [`TrainError`] failures callers tell apart (divergence,
//! interruption) with their messages.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::backend::BackendKind;
use crate::eval::HeldoutMetrics;

/// Result of a training run.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct TrainReport {
    pub model_dir: PathBuf,
    pub backend: BackendKind,
    /// Steps done in total (all invocations).
    pub steps: u64,
    /// Steps done by this invocation.
    pub steps_this_run: u64,
    pub epochs_completed: f64,
    pub elapsed_s: f64,
    /// Mean wall time of one optimizer step in this invocation, everything
    /// included (batch assembly, evaluation, checkpoints).
    pub seconds_per_step: f64,
    /// Mean time of the step alone: batch assembly, forward, backward, Adam.
    pub step_seconds: f64,
    pub stopped_by_time: bool,
    /// The run's scheduled length (shortened to fit `--minutes` if needed).
    pub schedule_steps: u64,
    pub metrics: Option<HeldoutMetrics>,
}

/// The summary `nppp train` prints: a few aligned lines with units, the
/// held-out numbers that matter and where the files went.
impl std::fmt::Display for TrainReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let dir = self.model_dir.display();
        writeln!(f, "{dir}")?;
        writeln!(
            f,
            "  steps       {} of {} ({} in this run, {:.2} epochs){}",
            self.steps,
            self.schedule_steps,
            self.steps_this_run,
            self.epochs_completed,
            if self.stopped_by_time {
                "; stopped by --minutes"
            } else {
                ""
            }
        )?;
        writeln!(
            f,
            "  time        {:.1} min in all; {:.1} ms per step in this run ({:.1} ms for the step \
             itself), {} backend",
            self.elapsed_s / 60.0,
            1e3 * self.seconds_per_step,
            1e3 * self.step_seconds,
            self.backend
        )?;
        if let Some(m) = &self.metrics {
            writeln!(
                f,
                "  held-out    {} rays ({} hits): chamfer {:.4}, energy {:.4}, mask accuracy {:.2}%",
                m.rays,
                m.hit_rays,
                m.chamfer,
                m.energy,
                100.0 * m.mask_accuracy
            )?;
            writeln!(
                f,
                "  throughput  mean error per ray {:.2}% (RMS {:.2}%, bias {:+.2}%, noise floor {:.2}%)",
                100.0 * m.throughput_error,
                100.0 * m.throughput_rms_error,
                100.0 * m.throughput_bias,
                100.0 * m.throughput_noise_floor
            )?;
            if let Some(v) = &m.vertex {
                writeln!(
                    f,
                    "  vertex head chamfer {:.4}; light-sample throughput error per ray {:.2}% (bias \
                     {:+.2}%); {:.4} sphere radii from the nearest real vertex",
                    v.chamfer,
                    100.0 * v.throughput_error,
                    100.0 * v.throughput_bias,
                    v.position_error
                )?;
            }
        }
        writeln!(
            f,
            "  files       {dir}/checkpoint/ (weights, configs, state), {dir}/log.csv"
        )?;
        if self.steps < self.schedule_steps {
            write!(
                f,
                "  next        continue with `nppp train --resume --data DATA.nppd --out {dir}`"
            )
        } else {
            write!(
                f,
                "  next        `nppp bake --model {dir} --out models/NAME.nppp`"
            )
        }
    }
}

/// A training failure that callers may want to tell apart.
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    #[error("{}", non_finite_message(*step, *value, *last_good, dir, *kept_previous))]
    NonFinite {
        step: u64,
        value: f32,
        /// The newest checkpoint of this run (resumed from or saved since),
        /// if there is one: what `--resume` continues.
        last_good: Option<u64>,
        dir: PathBuf,
        /// A fresh run (`--overwrite`) left an older model in `dir` untouched.
        kept_previous: bool,
    },
    #[error("{}", interrupted_message(*step, dir, data, *saved))]
    Interrupted {
        step: u64,
        dir: PathBuf,
        data: PathBuf,
        /// Whether a checkpoint of `step` is in `dir` (none when a fresh
        /// run is stopped before its first step).
        saved: bool,
    },
}

fn interrupted_message(step: u64, dir: &Path, data: &Path, saved: bool) -> String {
    if saved {
        format!(
            "interrupted: a checkpoint of step {step} is saved in {}; continue with \
             `nppp train --resume --data {} --out {}`",
            dir.display(),
            data.display(),
            dir.display()
        )
    } else {
        "interrupted before the first training step; nothing was saved".to_string()
    }
}

fn non_finite_message(
    step: u64,
    value: f32,
    last_good: Option<u64>,
    dir: &Path,
    kept_previous: bool,
) -> String {
    let head = format!("training diverged: the loss became non-finite ({value}) at step {step}");
    match last_good {
        Some(n) => format!(
            "{head}; stopped without saving. The last good checkpoint (step {n}) is kept in {}; \
             resume it with --resume and a lower --lr",
            dir.display()
        ),
        None if kept_previous => format!(
            "{head}, before this run saved any checkpoint; nothing was saved, and the model that \
             was in {} before --overwrite is untouched. Start again with a lower --lr",
            dir.display()
        ),
        None => format!(
            "{head}, before this run saved any checkpoint; nothing was saved. Start again with \
             a lower --lr"
        ),
    }
}
