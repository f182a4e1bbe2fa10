//! The training loop: Chamfer (+ optional energy distance) on the exits of
//! hit rays, BCE on the mask of all rays, Adam, per-epoch held-out
//! evaluation, CSV log, checkpoints and resume.
//!
//! Everything random (batches, the k-subsets of exits, the decoder's r, the
//! initial weights) comes from `SampleRng` streams keyed by (seed, step), not
//! from Burn's generator: a run is then reproducible on CPU backends, and a
//! resumed run draws exactly what the uninterrupted run would have drawn.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use burn::config::Config;
use burn::optim::{AdamConfig, GradientsParams, ModuleOptimizer};
use burn::tensor::{Device, Tensor, TensorData};
use indicatif::{ProgressBar, ProgressDrawTarget};
use nppp_estimator::EXIT_FEATURES;
use nppp_geom::SampleRng;
use serde::{Deserialize, Serialize};

use crate::backend::BackendKind;
use crate::data::TrainingData;
use crate::eval::{BurnEstimator, EvalOptions, HeldoutMetrics, evaluate};
use crate::features::INPUT_FEATURES;
use crate::io::{DatasetInfo, ModelMeta, load_dataset};
use crate::loss::{
    bce_with_logits, chamfer_from_dists, energy_distance_trainable, pairwise_sq_dists,
};
use crate::model::{ModelConfig, NpppModel};
use crate::model_dir::{
    Checkpoint, CheckpointContent, DataFingerprint, STATE_VERSION, TrainState, check_fresh_out,
    checkpoint_dir, load_optimizer, load_weights, lock_model_dir, open_checkpoint, refresh_copies,
    save_checkpoint,
};

pub use crate::model_dir::files;

/// What `nppp train` was asked for (the CLI's flags, `nppp-cli`'s `TrainArgs`,
/// map onto this one to one). Hyperparameters left unset take the
/// defaults of [`TrainConfig`] on a fresh run, and the saved values on
/// `--resume` (giving a different value then is an error, except for the
/// budget, the learning rate and the backend).
#[derive(Clone, Debug)]
pub struct TrainOptions {
    /// Training data written by `nppp gen`.
    pub data: PathBuf,
    /// Model directory to create (configs, checkpoint, log.csv).
    pub out: PathBuf,
    /// Burn backend.
    pub backend: BackendKind,
    /// Length of the run in optimizer steps (default 24000: about 12 minutes
    /// on 2 cores); the learning-rate schedule follows it.
    pub steps: Option<u64>,
    /// Length of the run in epochs (one epoch = one pass over the training
    /// hit rays), instead of --steps.
    pub epochs: Option<usize>,
    /// Stop once this many steps are done in total, as if interrupted: the
    /// schedule still follows the run's length, and --resume continues it.
    pub stop_after: Option<u64>,
    /// Training-time budget of this invocation in minutes (0 = none). Once
    /// 300 steps are timed, a run that would not fit is shortened so that it
    /// still ends with its learning-rate decay (the run length then depends
    /// on the machine's speed; use 0 for bit-reproducible runs). If the
    /// budget is spent anyway, training evaluates, checkpoints and stops.
    pub minutes: f64,
    /// Continue the checkpoint in --out.
    pub resume: bool,
    /// Start afresh even if --out holds a checkpoint (it is deleted once the
    /// data has been read and checked).
    pub overwrite: bool,
    /// Input rays per step (hits, for the Chamfer term).
    pub batch: Option<usize>,
    /// Exits per ray per step (a random subset of the file's k).
    pub k: Option<usize>,
    /// Rays (hits and misses) per step for the mask term.
    pub mask_batch: Option<usize>,
    /// Adam learning rate.
    pub lr: Option<f64>,
    /// Weight of the energy-distance term added to Chamfer (0 = Chamfer only;
    /// default 1).
    pub energy_weight: Option<f32>,
    /// Seed of every random choice of the run.
    pub seed: Option<u64>,
    /// Every n-th ray of the file is held out for evaluation.
    pub holdout_every: Option<usize>,
    /// Steps per epoch (default: one pass over the training hit rays).
    pub steps_per_epoch: Option<usize>,
    /// Held-out hit rays scored at the end of every epoch.
    pub eval_rays: Option<usize>,
    /// Latent size (z); the baked grid stores this many channels.
    pub latent_dim: Option<usize>,
    /// Encoder hidden width.
    pub encoder_width: Option<usize>,
    /// Decoder hidden width.
    pub decoder_width: Option<usize>,
    /// Mask network hidden width.
    pub mask_width: Option<usize>,
    /// Write a row of training losses (averaged since the previous row),
    /// learning rate and time per step to log.csv every this many steps
    /// (0: only at evaluations).
    pub log_every: u64,
    /// Also score the held-out rays (and checkpoint) every this many steps,
    /// besides every epoch's end (0: only at epoch ends).
    pub eval_every: u64,
    /// No progress bar.
    pub quiet: bool,
}

impl TrainOptions {
    /// Options with every hyperparameter at its default.
    pub fn new(data: impl Into<PathBuf>, out: impl Into<PathBuf>) -> Self {
        Self {
            data: data.into(),
            out: out.into(),
            backend: BackendKind::default(),
            epochs: None,
            steps: None,
            stop_after: None,
            minutes: 60.0,
            resume: false,
            overwrite: false,
            batch: None,
            k: None,
            mask_batch: None,
            lr: None,
            energy_weight: None,
            seed: None,
            holdout_every: None,
            steps_per_epoch: None,
            eval_rays: None,
            latent_dim: None,
            encoder_width: None,
            decoder_width: None,
            mask_width: None,
            log_every: 100,
            eval_every: 2000,
            quiet: false,
        }
    }
}

/// Everything that defines a training run, saved as `train_config.json`.
#[derive(Config, Debug, PartialEq)]
pub struct TrainConfig {
    pub model: ModelConfig,
    #[config(default = 64)]
    pub batch: usize,
    #[config(default = 64)]
    pub k: usize,
    /// Rays per step for the mask term (they are cheap: one logit each).
    #[config(default = 1024)]
    pub mask_batch: usize,
    /// Adam (1e-3, 0.9, 0.999) as in the thesis; epsilon 1e-8 (Burn's
    /// default is 1e-5, which damps small gradients).
    #[config(default = 1e-3)]
    pub lr: f64,
    /// The rate stays at `lr` until this fraction of the run's steps, then
    /// decays (half cosine) to `lr * lr_final`: at a constant rate the
    /// held-out brightness bias swings by a few percent from epoch to epoch,
    /// and the run should end on steady weights. 1 = no decay.
    #[config(default = 0.7)]
    pub lr_decay_from: f64,
    #[config(default = 0.05)]
    pub lr_final: f64,
    #[config(default = 0.9)]
    pub beta_1: f32,
    #[config(default = 0.999)]
    pub beta_2: f32,
    #[config(default = 1e-8)]
    pub epsilon: f32,
    /// Weight of the energy distance next to Chamfer. Chamfer matches
    /// supports, not densities: on the knot, Chamfer alone left the held-out
    /// mean throughput 1.5% too bright (per-ray RMS error 3.9%); with the
    /// energy term at weight 1: +0.9% and 3.0%, for 18% more time per step.
    #[config(default = 1.0)]
    pub energy_weight: f32,
    #[config(default = 1.0)]
    pub mask_weight: f32,
    /// Per-parameter gradient-norm clip (0 = off): a safety net against a
    /// rare batch of far outliers, not a regularizer.
    #[config(default = 10.0)]
    pub grad_clip_norm: f32,
    #[config(default = 1)]
    pub seed: u64,
    #[config(default = 20)]
    pub holdout_every: usize,
    /// 0 = one pass over the training hit rays.
    #[config(default = 0)]
    pub steps_per_epoch: usize,
    /// Length of the run in steps, unless `epochs` is set.
    #[config(default = 24000)]
    pub steps: u64,
    /// Length of the run in epochs (0 = use `steps`).
    #[config(default = 0)]
    pub epochs: usize,
    /// Held-out hit rays whose exits are scored at each epoch's end.
    #[config(default = 512)]
    pub eval_rays: usize,
}

impl TrainConfig {
    /// The learning rate of step `step` (0-based) of a run of `total` steps.
    pub fn lr_at(&self, step: u64, total: u64) -> f64 {
        let start = self.lr_decay_from * total as f64;
        let s = step as f64;
        if total == 0 || s < start || self.lr_decay_from >= 1.0 {
            return self.lr;
        }
        let t = ((s - start) / (total as f64 - start).max(1.0)).clamp(0.0, 1.0);
        let f =
            self.lr_final + (1.0 - self.lr_final) * 0.5 * (1.0 + (std::f64::consts::PI * t).cos());
        self.lr * f
    }

    fn validate(&self) -> Result<()> {
        self.model.validate()?;
        let pos = [
            ("batch", self.batch),
            ("k", self.k),
            ("mask_batch", self.mask_batch),
        ];
        for (name, v) in pos {
            if v == 0 {
                bail!("{name} must be at least 1");
            }
        }
        if !(self.lr.is_finite() && self.lr > 0.0) {
            bail!("learning rate {} must be positive", self.lr);
        }
        if !((0.0..=1.0).contains(&self.lr_decay_from) && (0.0..=1.0).contains(&self.lr_final)) {
            bail!("lr_decay_from and lr_final must be in [0, 1]");
        }
        if !(self.energy_weight.is_finite() && self.energy_weight >= 0.0) {
            bail!("energy weight {} must be >= 0", self.energy_weight);
        }
        if self.holdout_every < 2 {
            bail!("holdout_every must be at least 2");
        }
        self.check_step_memory()
    }

    /// Bytes one step holds for the exit terms (pairwise distances of the
    /// b x k generated and real exits, decoder activations) and for the mask
    /// term: the forward values kept for the backward pass, their gradients
    /// and temporaries (x3), in f32. An estimate from the shapes, meant to
    /// refuse flags that cannot fit, not to predict the peak exactly.
    pub fn step_memory_bytes(&self) -> (u64, u64) {
        let m = &self.model;
        let w = |x: usize| x as u64;
        let (b, k, bm) = (w(self.batch), w(self.k), w(self.mask_batch));
        let bk = b.saturating_mul(k);
        let per_exit = w(m.decoder_width)
            .saturating_mul(w(m.decoder_layers) + 1)
            .saturating_add(w(EXIT_FEATURES + m.noise_dim + m.latent_dim));
        let exits = bk
            .saturating_mul(k.saturating_mul(6))
            .saturating_add(bk.saturating_mul(per_exit))
            .saturating_add(b.saturating_mul(
                w(m.encoder_width).saturating_mul(w(m.encoder_layers) + 1) + w(INPUT_FEATURES),
            ));
        let mask = bm.saturating_mul(
            w(m.mask_width)
                .saturating_mul(w(m.mask_layers) + 1)
                .saturating_add(w(INPUT_FEATURES)),
        );
        let bytes = |elems: u64| elems.saturating_mul(4 * 3);
        (bytes(exits), bytes(mask))
    }

    /// Refuses a batch shape whose step would not fit in half the memory
    /// available (16 GiB assumed where it cannot be read): a clear error
    /// instead of an abort on allocation.
    fn check_step_memory(&self) -> Result<()> {
        let budget = nppp_files::available_memory().unwrap_or(16 << 30) / 2;
        let (exits, mask) = self.step_memory_bytes();
        let fmt = nppp_files::format_bytes;
        if exits > budget {
            bail!(
                "--batch {} with --k {}: one training step would hold about {} (pairwise \
                 distances of {} x {} x {} exits and the decoder's activations), more than half \
                 of the {} of memory available; the defaults are --batch 64 --k 64",
                self.batch,
                self.k,
                fmt(exits),
                self.batch,
                self.k,
                self.k,
                fmt(2 * budget)
            );
        }
        if mask > budget {
            bail!(
                "--mask-batch {}: one training step would hold about {} for the mask term, more \
                 than half of the {} of memory available; the default is 1024",
                self.mask_batch,
                fmt(mask),
                fmt(2 * budget)
            );
        }
        Ok(())
    }
}

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

/// Set by [`request_stop`] (the CLI's Ctrl-C / SIGTERM handler): the
/// training loop saves a checkpoint after the current step and returns
/// [`TrainError::Interrupted`].
static STOP_REQUESTED: AtomicBool = AtomicBool::new(false);
/// Whether a training loop is running (and so will act on a stop request);
/// outside it, an interrupt may end the process at once.
static IN_TRAINING_LOOP: AtomicBool = AtomicBool::new(false);

/// Asks the running training loop to checkpoint and stop.
pub fn request_stop() {
    STOP_REQUESTED.store(true, Ordering::SeqCst);
}

/// Whether a stop was requested.
pub fn stop_requested() -> bool {
    STOP_REQUESTED.load(Ordering::SeqCst)
}

/// Whether a training loop is running (it acts on [`request_stop`]).
pub fn in_training_loop() -> bool {
    IN_TRAINING_LOOP.load(Ordering::SeqCst)
}

/// Marks the training loop as running while alive.
struct LoopGuard;

impl LoopGuard {
    fn enter() -> Self {
        IN_TRAINING_LOOP.store(true, Ordering::SeqCst);
        Self
    }
}

impl Drop for LoopGuard {
    fn drop(&mut self) {
        IN_TRAINING_LOOP.store(false, Ordering::SeqCst);
    }
}

// Stream ids of the per-step random choices.
const STREAM_PERM: u64 = 0x9E41;
const STREAM_BATCH: u64 = 0xBA7C;
const STREAM_NOISE: u64 = 0x7015;
const STREAM_MASK: u64 = 0x3A5C;

/// Steps timed before a `--minutes` budget shortens the schedule.
const CALIBRATION_STEPS: u64 = 300;
/// Share of the measured pace the budget plans for: evaluations,
/// checkpoints and a busy machine take the rest.
const TIME_SAFETY: f64 = 0.85;

/// A checkpoint is also written this often (seconds) within long epochs, so
/// an interrupted run loses little.
const CHECKPOINT_EVERY_S: f64 = 300.0;

const LOG_HEADER: &str = "epoch,step,elapsed_s,lr,train_loss,train_chamfer,train_energy,train_bce,\
heldout_chamfer,heldout_energy,heldout_bce,mask_accuracy,throughput_error,throughput_bias,\
throughput_noise_floor,throughput_rms_error,radiance_error,radiance_bias,seconds_per_step";

/// Trains on the data file named in `opts` (see [`TrainOptions`]).
pub fn train(opts: &TrainOptions) -> Result<TrainReport> {
    let (cfg, ckpt) = resolve_config(opts)?;
    let (info, rays) = load_dataset(&opts.data, opts.quiet)?;
    let data = TrainingData::build(rays, info.k as usize, cfg.holdout_every)
        .with_context(|| format!("preparing {}", opts.data.display()))?;
    train_on(opts, cfg, ckpt, info, data)
}

/// Trains on data already in memory (the tests and tools use this with
/// synthetic rays; `info` names the object as a data file header would).
pub fn train_with_data(
    opts: &TrainOptions,
    info: DatasetInfo,
    data: TrainingData,
) -> Result<TrainReport> {
    let (cfg, ckpt) = resolve_config(opts)?;
    train_on(opts, cfg, ckpt, info, data)
}

/// The run's configuration: the saved one on resume (checked against the
/// command line), else defaults overridden by the command line. On resume,
/// the checked checkpoint comes with it.
fn resolve_config(opts: &TrainOptions) -> Result<(TrainConfig, Option<Checkpoint>)> {
    let mut ckpt = None;
    let mut cfg = if opts.resume {
        if !opts.out.is_dir() {
            bail!(
                "--resume: {} is not a model directory (no such folder)",
                opts.out.display()
            );
        }
        let c = open_checkpoint(&opts.out)
            .context("--resume")?
            .with_context(|| {
                format!(
                    "--resume: {} holds no checkpoint to resume (a run saves its first one at \
                     the end of its first epoch, after {} s, or when stopped)",
                    opts.out.display(),
                    CHECKPOINT_EVERY_S
                )
            })?;
        let cfg = c.train_config.clone();
        ckpt = Some(c);
        let clash = |name: &str, given: Option<String>, saved: String| -> Result<()> {
            match given {
                Some(g) if g != saved => bail!(
                    "--resume: --{name} {g} differs from the checkpoint's {saved}; a resumed run \
                     keeps its configuration (train into a new --out to change it)"
                ),
                _ => Ok(()),
            }
        };
        fn s<T: ToString>(x: Option<T>) -> Option<String> {
            x.map(|v| v.to_string())
        }
        clash("batch", s(opts.batch), cfg.batch.to_string())?;
        clash("k", s(opts.k), cfg.k.to_string())?;
        clash("mask-batch", s(opts.mask_batch), cfg.mask_batch.to_string())?;
        clash(
            "energy-weight",
            s(opts.energy_weight),
            cfg.energy_weight.to_string(),
        )?;
        clash("seed", s(opts.seed), cfg.seed.to_string())?;
        clash(
            "holdout-every",
            s(opts.holdout_every),
            cfg.holdout_every.to_string(),
        )?;
        clash(
            "steps-per-epoch",
            s(opts.steps_per_epoch),
            cfg.steps_per_epoch.to_string(),
        )?;
        clash(
            "latent-dim",
            s(opts.latent_dim),
            cfg.model.latent_dim.to_string(),
        )?;
        clash(
            "encoder-width",
            s(opts.encoder_width),
            cfg.model.encoder_width.to_string(),
        )?;
        clash(
            "decoder-width",
            s(opts.decoder_width),
            cfg.model.decoder_width.to_string(),
        )?;
        clash(
            "mask-width",
            s(opts.mask_width),
            cfg.model.mask_width.to_string(),
        )?;
        cfg
    } else {
        check_fresh_out(&opts.out)?;
        if checkpoint_dir(&opts.out).is_some() && !opts.overwrite {
            bail!(
                "{} already holds a checkpoint; pass --resume to continue it, --overwrite to \
                 start afresh, or choose another --out",
                opts.out.display()
            );
        }
        let mut model = ModelConfig::new();
        if let Some(v) = opts.latent_dim {
            model.latent_dim = v;
        }
        if let Some(v) = opts.encoder_width {
            model.encoder_width = v;
        }
        if let Some(v) = opts.decoder_width {
            model.decoder_width = v;
        }
        if let Some(v) = opts.mask_width {
            model.mask_width = v;
        }
        let mut cfg = TrainConfig::new(model);
        if let Some(v) = opts.batch {
            cfg.batch = v;
        }
        if let Some(v) = opts.k {
            cfg.k = v;
        }
        if let Some(v) = opts.mask_batch {
            cfg.mask_batch = v;
        }
        if let Some(v) = opts.energy_weight {
            cfg.energy_weight = v;
        }
        if let Some(v) = opts.seed {
            cfg.seed = v;
        }
        if let Some(v) = opts.holdout_every {
            cfg.holdout_every = v;
        }
        if let Some(v) = opts.steps_per_epoch {
            cfg.steps_per_epoch = v;
        }
        cfg
    };
    // The length, the learning rate and the evaluation may change between
    // invocations (a longer run stretches the decay phase accordingly).
    if let Some(v) = opts.epochs {
        cfg.epochs = v;
    }
    if let Some(v) = opts.steps {
        cfg.steps = v;
        cfg.epochs = 0;
    }
    if let Some(v) = opts.lr {
        cfg.lr = v;
    }
    if let Some(v) = opts.eval_rays {
        cfg.eval_rays = v;
    }
    if !(opts.minutes.is_finite() && opts.minutes >= 0.0) {
        bail!("--minutes {} must be >= 0", opts.minutes);
    }
    cfg.validate()?;
    Ok((cfg, ckpt))
}

fn fingerprint(info: &DatasetInfo, data: &TrainingData) -> DataFingerprint {
    DataFingerprint {
        rays: data.train.len() + data.heldout.len(),
        hits: data.train.hits() + data.heldout.hits(),
        k: data.k,
        mesh_hash: info.mesh_hash,
        material_hash: info.material_hash,
    }
}

/// One step's input, assembled on the CPU.
struct Batch {
    features: Vec<f32>,
    real: Vec<f32>,
    noise: Vec<f32>,
    mask_features: Vec<f32>,
    mask_labels: Vec<f32>,
    b: usize,
    k: usize,
    bm: usize,
}

/// The permutation of the training hit rays for one epoch.
fn epoch_permutation(seed: u64, epoch: u64, n: usize) -> Vec<u32> {
    let mut rng = SampleRng::new(seed, epoch, STREAM_PERM);
    let mut p: Vec<u32> = (0..n as u32).collect();
    for i in (1..n).rev() {
        let j = (rng.next_u64() % (i as u64 + 1)) as usize;
        p.swap(i, j);
    }
    p
}

fn make_batch(
    cfg: &TrainConfig,
    data: &TrainingData,
    perm: &[u32],
    step: u64,
    spe: usize,
) -> Batch {
    let tr = &data.train;
    let n_hit = tr.hits();
    let b = cfg.batch;
    let kf = data.k;
    let k = cfg.k.min(kf);
    let nd = cfg.model.noise_dim;
    let in_epoch = (step % spe as u64) as usize;
    let mut rng = SampleRng::new(cfg.seed, step, STREAM_BATCH);
    let mut features = Vec::with_capacity(b * INPUT_FEATURES);
    let mut real = Vec::with_capacity(b * k * EXIT_FEATURES);
    let mut idx: Vec<u32> = (0..kf as u32).collect();
    for j in 0..b {
        let h = perm[(in_epoch * b + j) % n_hit] as usize;
        let ray = tr.hit_index[h];
        features.extend_from_slice(&tr.features[ray * INPUT_FEATURES..(ray + 1) * INPUT_FEATURES]);
        let exits = &tr.exits[h * kf * EXIT_FEATURES..(h + 1) * kf * EXIT_FEATURES];
        if k == kf {
            real.extend_from_slice(exits);
        } else {
            // Partial Fisher-Yates: k distinct exits of the file's kf.
            for i in 0..k {
                let r = i + (rng.next_u64() % (kf - i) as u64) as usize;
                idx.swap(i, r);
                let e = idx[i] as usize;
                real.extend_from_slice(&exits[e * EXIT_FEATURES..(e + 1) * EXIT_FEATURES]);
            }
        }
    }
    let mut nrng = SampleRng::new(cfg.seed, step, STREAM_NOISE);
    let noise: Vec<f32> = (0..b * k * nd).map(|_| nrng.normal()).collect();
    let mut mrng = SampleRng::new(cfg.seed, step, STREAM_MASK);
    let bm = cfg.mask_batch;
    let mut mask_features = Vec::with_capacity(bm * INPUT_FEATURES);
    let mut mask_labels = Vec::with_capacity(bm);
    for _ in 0..bm {
        let i = (mrng.next_u64() % tr.len() as u64) as usize;
        mask_features.extend_from_slice(&tr.features[i * INPUT_FEATURES..(i + 1) * INPUT_FEATURES]);
        mask_labels.push(tr.hit[i] as u8 as f32);
    }
    Batch {
        features,
        real,
        noise,
        mask_features,
        mask_labels,
        b,
        k,
        bm,
    }
}

/// Loss values of one step: total, chamfer, energy, bce.
type StepLosses = [f32; 4];

fn train_step(
    model: NpppModel,
    optim: &mut ModuleOptimizer,
    cfg: &TrainConfig,
    lr: f64,
    batch: Batch,
    device: &Device,
) -> std::result::Result<(NpppModel, StepLosses), (NpppModel, f32)> {
    let Batch {
        features,
        real,
        noise,
        mask_features,
        mask_labels,
        b,
        k,
        bm,
    } = batch;
    let nd = cfg.model.noise_dim;
    let feats = Tensor::<2>::from_data(TensorData::new(features, [b, INPUT_FEATURES]), device);
    let real = Tensor::<3>::from_data(TensorData::new(real, [b, k, EXIT_FEATURES]), device);
    let noise = Tensor::<2>::from_data(TensorData::new(noise, [b * k, nd]), device);
    let generated = model.generate(feats, noise, k);
    let d = pairwise_sq_dists(generated.clone(), real.clone());
    let chamfer = chamfer_from_dists(d.clone());
    let energy = if cfg.energy_weight > 0.0 {
        energy_distance_trainable(d, generated)
    } else {
        Tensor::<1>::zeros([1], device)
    };
    let mf = Tensor::<2>::from_data(TensorData::new(mask_features, [bm, INPUT_FEATURES]), device);
    let ml = Tensor::<1>::from_data(TensorData::new(mask_labels, [bm]), device);
    let bce = bce_with_logits(model.mask_logits(mf), ml);
    let loss = chamfer.clone()
        + energy.clone().mul_scalar(cfg.energy_weight)
        + bce.clone().mul_scalar(cfg.mask_weight);
    // One read-back per step: the values for the log and the finiteness check.
    let values = Tensor::cat(
        vec![
            loss.clone().detach(),
            chamfer.detach(),
            energy.detach(),
            bce.detach(),
        ],
        0,
    )
    .into_data()
    .try_into_vec::<f32>()
    .unwrap_or_else(|_| vec![f32::NAN; 4]);
    let v: StepLosses = [values[0], values[1], values[2], values[3]];
    if !v.iter().all(|x| x.is_finite()) {
        return Err((model, v[0]));
    }
    let grads = GradientsParams::from_grads(loss.backward(), &model);
    let model = optim.step(lr, model, grads);
    Ok((model, v))
}

fn make_optimizer(cfg: &TrainConfig) -> ModuleOptimizer {
    let mut a = AdamConfig::new()
        .with_beta_1(cfg.beta_1)
        .with_beta_2(cfg.beta_2)
        .with_epsilon(cfg.epsilon);
    if cfg.grad_clip_norm > 0.0 {
        a = a.with_grad_clipping(Some(burn::grad_clipping::GradientClippingConfig::Norm(
            cfg.grad_clip_norm,
        )));
    }
    a.init()
}

/// One row of log.csv (see `LOG_HEADER`); the held-out columns are empty
/// on rows without an evaluation.
fn log_row(
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
fn append_live_row(path: &Path, row: &str) {
    use std::io::Write;
    if let Ok(mut f) = std::fs::OpenOptions::new().append(true).open(path) {
        let _ = writeln!(f, "{row}");
    }
}

fn train_on(
    opts: &TrainOptions,
    cfg: TrainConfig,
    ckpt: Option<Checkpoint>,
    info: DatasetInfo,
    data: TrainingData,
) -> Result<TrainReport> {
    let out = &opts.out;
    let mut cfg = cfg;
    // The exits per ray a step uses can only be as many as the file holds;
    // the saved config says what actually runs.
    if cfg.k > data.k {
        if !opts.quiet {
            eprintln!(
                "note: {} holds {} exits per ray, so each step uses k = {} (not {}); \
                 train_config.json records {}",
                opts.data.display(),
                data.k,
                data.k,
                cfg.k,
                data.k
            );
        }
        cfg.k = data.k;
    }
    if data.heldout.is_empty() {
        bail!(
            "no held-out rays: the data has {} rays and every {}th is held out",
            data.train.len(),
            cfg.holdout_every
        );
    }
    let device = opts.backend.device()?;
    let ad = device.clone().autodiff();
    let n_hit = data.train.hits();
    let spe = if cfg.steps_per_epoch > 0 {
        cfg.steps_per_epoch
    } else {
        n_hit.div_ceil(cfg.batch)
    };
    // The schedule's length, and where this invocation stops.
    let total_steps = if cfg.epochs > 0 {
        (cfg.epochs * spe) as u64
    } else {
        cfg.steps
    };
    let mut total_steps = total_steps;
    let mut stop_at = opts.stop_after.map_or(total_steps, |s| s.min(total_steps));
    let fp = fingerprint(&info, &data);
    let _lock = lock_model_dir(out)?;

    // Start fresh or resume. A fresh run writes nothing into `out` until
    // its first checkpoint: a model already there (--overwrite) stays whole
    // until then, whatever happens to this run.
    let resumed_from = ckpt.as_ref().map(|c| c.state.step);
    let (mut model, mut optim, mut state, meta, mut log) = if let Some(ckpt) = ckpt {
        let state = ckpt.state.clone();
        if state.data != fp {
            bail!(
                "--resume: the checkpoint was trained on other data ({:?}) than {} ({:?})",
                state.data,
                opts.data.display(),
                fp
            );
        }
        if state.steps_per_epoch != spe {
            bail!(
                "--resume: steps per epoch changed ({} -> {spe})",
                state.steps_per_epoch
            );
        }
        let model = load_weights(&ckpt, &ad)?;
        let optim = load_optimizer(&ckpt, make_optimizer(&cfg))?;
        (model, optim, state, ckpt.meta, ckpt.log)
    } else {
        let meta = ModelMeta::new(info.clone(), data.transform.clone(), opts.data.clone());
        let model = NpppModel::init(&cfg.model, cfg.seed, &ad)?;
        let state = TrainState {
            version: STATE_VERSION,
            step: 0,
            steps_per_epoch: spe,
            elapsed_s: 0.0,
            epoch_sums: [0.0; 4],
            epoch_count: 0,
            data: fp,
            last_metrics: None,
            schedule_steps: None,
            files: Vec::new(),
        };
        (
            model,
            make_optimizer(&cfg),
            state,
            meta,
            format!("{LOG_HEADER}\n"),
        )
    };
    // The step of the newest checkpoint of *this* run (resumed from, or
    // saved since): what a divergence message may point to.
    let mut last_saved = resumed_from;
    if resumed_from.is_some() {
        let content = CheckpointContent {
            train_config: &cfg,
            meta: &meta,
            model: &model,
            optim: &optim,
            log: &log,
        };
        refresh_copies(out, &content)?;
    }

    if let Some(s) = state.schedule_steps {
        total_steps = total_steps.min(s);
        stop_at = stop_at.min(total_steps);
    }
    let start_step = state.step;
    let pb = if opts.quiet {
        ProgressBar::hidden()
    } else {
        let pb = ProgressBar::with_draw_target(Some(stop_at), ProgressDrawTarget::stderr());
        pb.set_style(nppp_files::progress_style(
            "train {bar:30} {pos}/{len} steps ({rate}, eta {eta}) {msg}",
            "steps",
        ));
        pb.set_position(start_step);
        pb
    };
    let t0 = Instant::now();
    let base_elapsed = state.elapsed_s;
    let mut last_ckpt = Instant::now();
    let mut perm_epoch = u64::MAX;
    let mut perm = Vec::new();
    let mut stopped_by_time = false;
    let mut step_time = 0.0f64;
    let eval_opts = EvalOptions {
        max_hit_rays: cfg.eval_rays,
        ..EvalOptions::default()
    };
    let save = |model: &NpppModel, optim: &ModuleOptimizer, state: &TrainState, log: &str| {
        let content = CheckpointContent {
            train_config: &cfg,
            meta: &meta,
            model,
            optim,
            log,
        };
        save_checkpoint(out, &content, state)
    };

    let evaluate_model = |model: &NpppModel| -> Result<HeldoutMetrics> {
        let mut est =
            BurnEstimator::new(model, data.transform.clone(), &info, cfg.model.noise_dim)?;
        evaluate(&mut est, &data.heldout, data.k, &data.transform, &eval_opts)
    };

    let mut last_row_at = Instant::now();
    let mut last_row_step = start_step;
    let _in_loop = LoopGuard::enter();
    while state.step < stop_at {
        if stop_requested() {
            pb.abandon();
            if state.step > start_step {
                state.elapsed_s = base_elapsed + t0.elapsed().as_secs_f64();
                save(&model, &optim, &state, &log)?;
            }
            return Err(TrainError::Interrupted {
                step: state.step,
                dir: out.clone(),
                data: opts.data.clone(),
                saved: last_saved.is_some() || state.step > start_step,
            }
            .into());
        }
        let epoch = state.step / spe as u64;
        if epoch != perm_epoch {
            perm = epoch_permutation(cfg.seed, epoch, n_hit);
            perm_epoch = epoch;
        }
        let ts = Instant::now();
        let batch = make_batch(&cfg, &data, &perm, state.step, spe);
        // Fit the schedule into the time budget once the pace is known, and
        // again after each evaluation (which the first estimate misses).
        let timed = state.step - start_step;
        if opts.minutes > 0.0
            && timed > 0
            && (timed == CALIBRATION_STEPS || state.step.is_multiple_of(spe as u64))
        {
            let per_step = t0.elapsed().as_secs_f64() / timed as f64;
            let left = opts.minutes * 60.0 - t0.elapsed().as_secs_f64();
            let fits = state.step + (TIME_SAFETY * left / per_step).max(0.0) as u64;
            if fits < total_steps {
                let line = format!(
                    "--minutes {}: {total_steps} steps do not fit at {:.1} ms/step; the run \
                     is shortened to {fits} steps (its learning-rate decay included)",
                    opts.minutes,
                    per_step * 1e3
                );
                if pb.is_hidden() {
                    if !opts.quiet {
                        eprintln!("{line}");
                    }
                } else {
                    pb.println(line);
                }
                total_steps = fits;
                stop_at = stop_at.min(fits);
                state.schedule_steps = Some(fits);
                pb.set_length(stop_at);
            }
        }
        let lr = cfg.lr_at(state.step, total_steps);
        let stepped = train_step(model, &mut optim, &cfg, lr, batch, &ad);
        step_time += ts.elapsed().as_secs_f64();
        let (m, v) = match stepped {
            Ok(x) => x,
            Err((_, value)) => {
                pb.abandon();
                return Err(TrainError::NonFinite {
                    step: state.step + 1,
                    value,
                    last_good: last_saved,
                    dir: out.clone(),
                    kept_previous: last_saved.is_none() && checkpoint_dir(out).is_some(),
                }
                .into());
            }
        };
        model = m;
        state.step += 1;
        for (s, x) in state.epoch_sums.iter_mut().zip(v) {
            *s += x as f64;
        }
        state.epoch_count += 1;
        pb.set_position(state.step);
        if state.step % 10 == 0 {
            pb.set_message(format!("loss {:.4}", v[0]));
        }
        let epoch_end = state.step % spe as u64 == 0;
        let last = state.step >= stop_at;
        let over_time = opts.minutes > 0.0 && t0.elapsed().as_secs_f64() > opts.minutes * 60.0;
        let evaluate_now = epoch_end
            || last
            || over_time
            || (opts.eval_every > 0 && state.step.is_multiple_of(opts.eval_every));
        let log_now = opts.log_every > 0 && state.step.is_multiple_of(opts.log_every);
        if evaluate_now || log_now {
            state.elapsed_s = base_elapsed + t0.elapsed().as_secs_f64();
            let metrics = if evaluate_now {
                let m = evaluate_model(&model)?;
                if !(m.chamfer.is_finite() && m.mask_bce.is_finite()) {
                    pb.abandon();
                    return Err(TrainError::NonFinite {
                        step: state.step,
                        value: m.chamfer as f32,
                        last_good: last_saved,
                        dir: out.clone(),
                        kept_previous: last_saved.is_none() && checkpoint_dir(out).is_some(),
                    }
                    .into());
                }
                Some(m)
            } else {
                None
            };
            let c = state.epoch_count.max(1) as f64;
            let avg: Vec<f64> = state.epoch_sums.iter().map(|s| s / c).collect();
            let window = (state.step - last_row_step).max(1) as f64;
            let sps = last_row_at.elapsed().as_secs_f64() / window;
            let row = log_row(
                state.step as f64 / spe as f64,
                state.step,
                state.elapsed_s,
                lr,
                &avg,
                metrics.as_ref(),
                sps,
            );
            state.epoch_sums = [0.0; 4];
            state.epoch_count = 0;
            last_row_at = Instant::now();
            last_row_step = state.step;
            log.push_str(&row);
            log.push('\n');
            if let Some(metrics) = metrics {
                state.last_metrics = Some(metrics);
                save(&model, &optim, &state, &log)?;
                last_saved = Some(state.step);
                last_ckpt = Instant::now();
                let line = format!(
                    "epoch {:.2}: train {:.4}  held-out chamfer {:.4}  mask acc {:.2}%  throughput err {:.2}% (rms {:.2}%, bias {:+.2}%, floor {:.2}%)",
                    state.step as f64 / spe as f64,
                    avg[0],
                    metrics.chamfer,
                    100.0 * metrics.mask_accuracy,
                    100.0 * metrics.throughput_error,
                    100.0 * metrics.throughput_rms_error,
                    100.0 * metrics.throughput_bias,
                    100.0 * metrics.throughput_noise_floor,
                );
                // A hidden bar (no terminal, or --quiet) prints nothing: then the
                // epoch lines go to stderr directly unless --quiet.
                if !pb.is_hidden() {
                    pb.println(line);
                } else if !opts.quiet {
                    eprintln!("{line}");
                }
            } else if last_saved.is_some() {
                // The folder is this run's: show the row at once (the
                // checkpoint's own log gets it at the next checkpoint).
                append_live_row(&out.join(files::LOG), &row);
            }
            if over_time && !last {
                stopped_by_time = true;
                break;
            }
        } else if last_ckpt.elapsed().as_secs_f64() > CHECKPOINT_EVERY_S {
            state.elapsed_s = base_elapsed + t0.elapsed().as_secs_f64();
            save(&model, &optim, &state, &log)?;
            last_saved = Some(state.step);
            last_ckpt = Instant::now();
        }
    }
    pb.finish_and_clear();
    let run = state.step - start_step;
    Ok(TrainReport {
        model_dir: out.clone(),
        backend: opts.backend,
        steps: state.step,
        steps_this_run: run,
        epochs_completed: state.step as f64 / spe as f64,
        elapsed_s: state.elapsed_s,
        seconds_per_step: t0.elapsed().as_secs_f64() / run.max(1) as f64,
        step_seconds: step_time / run.max(1) as f64,
        stopped_by_time,
        schedule_steps: total_steps,
        metrics: state.last_metrics,
    })
}
