//! The training loop: Chamfer (+ optional energy distance) on the exits of
//! hit rays, BCE on the mask of all rays, Adam, per-epoch held-out
//! evaluation, CSV log, checkpoints and resume.
//!
//! Everything random (batches, the k-subsets of exits, the decoder's r, the
//! initial weights) comes from `SampleRng` streams keyed by (seed, step), not
//! from Burn's generator: a run is then reproducible on CPU backends, and a
//! resumed run draws exactly what the uninterrupted run would have drawn.

use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use burn::config::Config;
use burn::module::Module;
use burn::optim::{AdamConfig, GradientsParams, ModuleOptimizer};
use burn::tensor::{Device, Tensor, TensorData};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
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

/// File names inside a model directory.
pub mod files {
    pub const MODEL_CONFIG: &str = "model_config.json";
    pub const TRAIN_CONFIG: &str = "train_config.json";
    pub const META: &str = "meta.json";
    pub const LOG: &str = "log.csv";
    pub const CHECKPOINT: &str = "checkpoint";
    pub const CHECKPOINT_TMP: &str = "checkpoint.tmp";
    pub const CHECKPOINT_OLD: &str = "checkpoint.old";
    pub const WEIGHTS: &str = "model.bpk";
    pub const OPTIMIZER: &str = "optim.bpk";
    pub const STATE: &str = "state.json";
}

/// Command-line options of `nppp train`. Hyperparameters left unset take the
/// defaults of [`TrainConfig`] on a fresh run, and the saved values on
/// `--resume` (giving a different value then is an error, except for the
/// budget, the learning rate and the backend).
#[derive(clap::Args, Clone, Debug)]
pub struct TrainOptions {
    /// Training data written by `nppp gen`.
    #[arg(long)]
    pub data: PathBuf,
    /// Model directory to create (configs, checkpoint, log.csv).
    #[arg(long)]
    pub out: PathBuf,
    /// Burn backend.
    #[arg(long, value_enum, default_value_t = BackendKind::default())]
    pub backend: BackendKind,
    /// Length of the run in optimizer steps (default 24000: about 12 minutes
    /// on 2 cores); the learning-rate schedule follows it.
    #[arg(long, conflicts_with = "epochs")]
    pub steps: Option<u64>,
    /// Length of the run in epochs (one epoch = one pass over the training
    /// hit rays), instead of --steps.
    #[arg(long)]
    pub epochs: Option<usize>,
    /// Stop once this many steps are done in total, as if interrupted: the
    /// schedule still follows the run's length, and --resume continues it.
    #[arg(long)]
    pub stop_after: Option<u64>,
    /// Training-time budget of this invocation in minutes (0 = none). Once
    /// 300 steps are timed, a run that would not fit is shortened so that it
    /// still ends with its learning-rate decay (the run length then depends
    /// on the machine's speed; use 0 for bit-reproducible runs). If the
    /// budget is spent anyway, training evaluates, checkpoints and stops.
    #[arg(long, default_value_t = 60.0)]
    pub minutes: f64,
    /// Continue the checkpoint in --out.
    #[arg(long, conflicts_with = "overwrite")]
    pub resume: bool,
    /// Start afresh even if --out holds a checkpoint (it is deleted once the
    /// data has been read and checked).
    #[arg(long)]
    pub overwrite: bool,
    /// Input rays per step (hits, for the Chamfer term).
    #[arg(long)]
    pub batch: Option<usize>,
    /// Exits per ray per step (a random subset of the file's k).
    #[arg(long)]
    pub k: Option<usize>,
    /// Rays (hits and misses) per step for the mask term.
    #[arg(long)]
    pub mask_batch: Option<usize>,
    /// Adam learning rate.
    #[arg(long)]
    pub lr: Option<f64>,
    /// Weight of the energy-distance term added to Chamfer (0 = Chamfer only;
    /// default 1).
    #[arg(long)]
    pub energy_weight: Option<f32>,
    /// Seed of every random choice of the run.
    #[arg(long)]
    pub seed: Option<u64>,
    /// Every n-th ray of the file is held out for evaluation.
    #[arg(long)]
    pub holdout_every: Option<usize>,
    /// Steps per epoch (default: one pass over the training hit rays).
    #[arg(long)]
    pub steps_per_epoch: Option<usize>,
    /// Held-out hit rays scored at the end of every epoch.
    #[arg(long)]
    pub eval_rays: Option<usize>,
    /// Latent size (z); the baked grid stores this many channels.
    #[arg(long)]
    pub latent_dim: Option<usize>,
    /// Encoder hidden width.
    #[arg(long)]
    pub encoder_width: Option<usize>,
    /// Decoder hidden width.
    #[arg(long)]
    pub decoder_width: Option<usize>,
    /// Mask network hidden width.
    #[arg(long)]
    pub mask_width: Option<usize>,
    /// No progress bar.
    #[arg(long)]
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
        Ok(())
    }
}

/// What identifies the data a checkpoint was trained on.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DataFingerprint {
    pub rays: usize,
    pub hits: usize,
    pub k: usize,
    pub mesh_hash: u64,
    pub material_hash: u64,
}

/// Progress saved with every checkpoint (`checkpoint/state.json`).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct TrainState {
    pub version: u32,
    /// Optimizer steps done.
    pub step: u64,
    pub steps_per_epoch: usize,
    /// Training time over all invocations.
    pub elapsed_s: f64,
    /// Running sums of this epoch's training losses (total, chamfer, energy,
    /// bce) and their count, so a resumed epoch logs the same average.
    pub epoch_sums: [f64; 4],
    pub epoch_count: u64,
    pub data: DataFingerprint,
    pub last_metrics: Option<HeldoutMetrics>,
    /// The run's length after fitting it into a `--minutes` budget (None:
    /// the configured length): the learning-rate schedule follows it, so a
    /// time-limited run still ends with its decay phase.
    #[serde(default)]
    pub schedule_steps: Option<u64>,
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

/// A training failure that callers may want to tell apart.
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    #[error(
        "training diverged: the loss became non-finite ({value}) at step {step}; stopped without \
         saving. The last good checkpoint (step {last_good}) is kept in {dir}; resume it with \
         --resume and a lower --lr"
    )]
    NonFinite {
        step: u64,
        value: f32,
        last_good: u64,
        dir: PathBuf,
    },
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
    let cfg = resolve_config(opts)?;
    let (info, rays) = load_dataset(&opts.data, opts.quiet)?;
    let data = TrainingData::build(rays, info.k as usize, cfg.holdout_every)
        .with_context(|| format!("preparing {}", opts.data.display()))?;
    train_on(opts, cfg, info, data)
}

/// Trains on data already in memory (the tests and tools use this with
/// synthetic rays; `info` names the object as a data file header would).
pub fn train_with_data(
    opts: &TrainOptions,
    info: DatasetInfo,
    data: TrainingData,
) -> Result<TrainReport> {
    let cfg = resolve_config(opts)?;
    train_on(opts, cfg, info, data)
}

fn checkpoint_dir(out: &Path) -> Option<PathBuf> {
    [files::CHECKPOINT, files::CHECKPOINT_OLD]
        .iter()
        .map(|n| out.join(n))
        .find(|d| d.join(files::STATE).is_file())
}

/// The run's configuration: the saved one on resume (checked against the
/// command line), else defaults overridden by the command line.
fn resolve_config(opts: &TrainOptions) -> Result<TrainConfig> {
    let saved_path = opts.out.join(files::TRAIN_CONFIG);
    let mut cfg = if opts.resume {
        if checkpoint_dir(&opts.out).is_none() {
            bail!(
                "--resume: {} holds no checkpoint to resume",
                opts.out.display()
            );
        }
        let cfg = TrainConfig::load(&saved_path).map_err(|e| {
            anyhow::anyhow!("--resume: cannot read {}: {e:?}", saved_path.display())
        })?;
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
    Ok(cfg)
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

/// Runs `f`, turning a panic inside Burn (it panics on some malformed files)
/// into an error.
fn no_panic<T>(what: &str, f: impl FnOnce() -> Result<T>) -> Result<T> {
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)) {
        Ok(r) => r,
        Err(p) => {
            let msg = p
                .downcast_ref::<String>()
                .cloned()
                .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
                .unwrap_or_default();
            bail!("{what}: the file is corrupt or from another model ({msg})")
        }
    }
}

/// Loads the weights of a model directory's checkpoint onto `device`.
pub fn load_weights(ckpt: &Path, cfg: &ModelConfig, device: &Device) -> Result<NpppModel> {
    let path = ckpt.join(files::WEIGHTS);
    if !path.is_file() {
        bail!("{} is missing", path.display());
    }
    let fresh = NpppModel::init(cfg, 0, device)?;
    no_panic(&format!("loading {}", path.display()), || {
        fresh
            .try_load_file(&path)
            .map_err(|e| anyhow::anyhow!("loading {}: {e:?}", path.display()))
    })
}

fn read_state(ckpt: &Path) -> Result<TrainState> {
    let p = ckpt.join(files::STATE);
    let s = fs::read_to_string(&p).with_context(|| format!("reading {}", p.display()))?;
    let st: TrainState =
        serde_json::from_str(&s).with_context(|| format!("{} is corrupt", p.display()))?;
    if st.version != 1 {
        bail!("{}: unsupported state version {}", p.display(), st.version);
    }
    Ok(st)
}

fn save_checkpoint(
    out: &Path,
    cfg: &TrainConfig,
    model: &NpppModel,
    optim: &ModuleOptimizer,
    state: &TrainState,
) -> Result<()> {
    // The config is saved with each checkpoint, not at start: a learning
    // rate given to a run that then diverged must not outlive that run.
    cfg.save(out.join(files::TRAIN_CONFIG))
        .with_context(|| format!("writing {}", files::TRAIN_CONFIG))?;
    let tmp = out.join(files::CHECKPOINT_TMP);
    let cur = out.join(files::CHECKPOINT);
    let old = out.join(files::CHECKPOINT_OLD);
    if tmp.exists() {
        fs::remove_dir_all(&tmp).with_context(|| format!("removing {}", tmp.display()))?;
    }
    fs::create_dir_all(&tmp).with_context(|| format!("creating {}", tmp.display()))?;
    model
        .clone()
        .save_file(tmp.join(files::WEIGHTS))
        .map_err(|e| anyhow::anyhow!("saving weights: {e:?}"))?;
    optim
        .save(tmp.join(files::OPTIMIZER))
        .map_err(|e| anyhow::anyhow!("saving optimizer state: {e:?}"))?;
    fs::write(tmp.join(files::STATE), serde_json::to_string_pretty(state)?)?;
    // Swap: there is always one complete checkpoint on disk (`checkpoint` or,
    // for the instant between the renames, `checkpoint.old`).
    if old.exists() {
        fs::remove_dir_all(&old)?;
    }
    if cur.exists() {
        fs::rename(&cur, &old)?;
    }
    fs::rename(&tmp, &cur)?;
    if old.exists() {
        fs::remove_dir_all(&old)?;
    }
    Ok(())
}

fn write_json_atomic(path: &Path, text: &str) -> Result<()> {
    let tmp = path.with_extension("json.tmp");
    fs::write(&tmp, text).with_context(|| format!("writing {}", tmp.display()))?;
    fs::rename(&tmp, path).with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}

/// Keeps only the log rows at or before `step` (rows written after the
/// checkpoint we resume from describe a future that is about to be redone).
fn prune_log(path: &Path, step: u64) -> Result<()> {
    let Ok(text) = fs::read_to_string(path) else {
        return Ok(());
    };
    let mut out = String::new();
    for (i, line) in text.lines().enumerate() {
        let keep = i == 0
            || line
                .split(',')
                .nth(1)
                .and_then(|s| s.parse::<u64>().ok())
                .is_some_and(|s| s <= step);
        if keep {
            out.push_str(line);
            out.push('\n');
        }
    }
    fs::write(path, out)?;
    Ok(())
}

fn append_log(path: &Path, row: &str) -> Result<()> {
    let new = !path.exists();
    let mut f = fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)
        .with_context(|| format!("opening {}", path.display()))?;
    if new {
        writeln!(f, "{LOG_HEADER}")?;
    }
    writeln!(f, "{row}")?;
    Ok(())
}

fn train_on(
    opts: &TrainOptions,
    cfg: TrainConfig,
    info: DatasetInfo,
    data: TrainingData,
) -> Result<TrainReport> {
    let out = &opts.out;
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
    fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;

    // Start fresh or resume.
    let (mut model, mut optim, mut state) = if opts.resume {
        let ckpt = checkpoint_dir(out).context("no checkpoint")?;
        let state = read_state(&ckpt)?;
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
        let model = load_weights(&ckpt, &cfg.model, &ad)?;
        let opath = ckpt.join(files::OPTIMIZER);
        let optim = no_panic(&format!("loading {}", opath.display()), || {
            make_optimizer(&cfg)
                .load(&opath)
                .map_err(|e| anyhow::anyhow!("loading {}: {e:?}", opath.display()))
        })?;
        prune_log(&out.join(files::LOG), state.step)?;
        (model, optim, state)
    } else {
        for d in [
            files::CHECKPOINT,
            files::CHECKPOINT_OLD,
            files::CHECKPOINT_TMP,
        ] {
            let d = out.join(d);
            if d.exists() {
                fs::remove_dir_all(&d).with_context(|| format!("removing {}", d.display()))?;
            }
        }
        let meta = ModelMeta::new(info.clone(), data.transform.clone(), opts.data.clone());
        write_json_atomic(
            &out.join(files::META),
            &serde_json::to_string_pretty(&meta)?,
        )?;
        cfg.model
            .save(out.join(files::MODEL_CONFIG))
            .with_context(|| format!("writing {}", files::MODEL_CONFIG))?;
        let _ = fs::remove_file(out.join(files::LOG));
        let model = NpppModel::init(&cfg.model, cfg.seed, &ad)?;
        let state = TrainState {
            version: 1,
            step: 0,
            steps_per_epoch: spe,
            elapsed_s: 0.0,
            epoch_sums: [0.0; 4],
            epoch_count: 0,
            data: fp,
            last_metrics: None,
            schedule_steps: None,
        };
        (model, make_optimizer(&cfg), state)
    };

    if let Some(s) = state.schedule_steps {
        total_steps = total_steps.min(s);
        stop_at = stop_at.min(total_steps);
    }
    let start_step = state.step;
    let pb = if opts.quiet {
        ProgressBar::hidden()
    } else {
        let pb = ProgressBar::with_draw_target(Some(stop_at), ProgressDrawTarget::stderr());
        pb.set_style(
            ProgressStyle::with_template(
                "train {bar:30} {pos}/{len} steps ({per_sec}, eta {eta}) {msg}",
            )
            .expect("static template"),
        );
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
    let log_path = out.join(files::LOG);

    let evaluate_model = |model: &NpppModel| -> Result<HeldoutMetrics> {
        let mut est = BurnEstimator::new(
            model,
            data.transform.clone(),
            info.max_internal_bounces,
            cfg.model.noise_dim,
        )?;
        evaluate(&mut est, &data.heldout, data.k, &data.transform, &eval_opts)
    };

    while state.step < stop_at {
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
                let last_good = checkpoint_dir(out)
                    .and_then(|c| read_state(&c).ok())
                    .map_or(0, |s| s.step);
                return Err(TrainError::NonFinite {
                    step: state.step + 1,
                    value,
                    last_good,
                    dir: out.clone(),
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
        if epoch_end || last || over_time {
            state.elapsed_s = base_elapsed + t0.elapsed().as_secs_f64();
            let metrics = evaluate_model(&model)?;
            if !(metrics.chamfer.is_finite() && metrics.mask_bce.is_finite()) {
                pb.abandon();
                let last_good = checkpoint_dir(out)
                    .and_then(|c| read_state(&c).ok())
                    .map_or(0, |s| s.step);
                return Err(TrainError::NonFinite {
                    step: state.step,
                    value: metrics.chamfer as f32,
                    last_good,
                    dir: out.clone(),
                }
                .into());
            }
            let c = state.epoch_count.max(1) as f64;
            let avg: Vec<f64> = state.epoch_sums.iter().map(|s| s / c).collect();
            let sps = t0.elapsed().as_secs_f64() / (state.step - start_step).max(1) as f64;
            let row = format!(
                "{:.4},{},{:.2},{:e},{:.6},{:.6},{:.6},{:.6},{:.6},{:.6},{:.6},{:.5},{:.5},{:.5},{:.5},{:.5},{:.5},{:.5},{:.5}",
                state.step as f64 / spe as f64,
                state.step,
                state.elapsed_s,
                lr,
                avg[0],
                avg[1],
                avg[2],
                avg[3],
                metrics.chamfer,
                metrics.energy,
                metrics.mask_bce,
                metrics.mask_accuracy,
                metrics.throughput_error,
                metrics.throughput_bias,
                metrics.throughput_noise_floor,
                metrics.throughput_rms_error,
                metrics.radiance_error,
                metrics.radiance_bias,
                sps
            );
            state.last_metrics = Some(metrics);
            if epoch_end {
                state.epoch_sums = [0.0; 4];
                state.epoch_count = 0;
            }
            save_checkpoint(out, &cfg, &model, &optim, &state)?;
            last_ckpt = Instant::now();
            append_log(&log_path, &row)?;
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
            if over_time && !last {
                stopped_by_time = true;
                break;
            }
        } else if last_ckpt.elapsed().as_secs_f64() > CHECKPOINT_EVERY_S {
            state.elapsed_s = base_elapsed + t0.elapsed().as_secs_f64();
            save_checkpoint(out, &cfg, &model, &optim, &state)?;
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

/// A trained model loaded back from its directory, for baking and evaluation.
pub struct LoadedModel {
    pub dir: PathBuf,
    pub model_config: ModelConfig,
    pub train_config: TrainConfig,
    pub meta: ModelMeta,
    pub model: NpppModel,
    pub state: TrainState,
}

/// Loads the latest checkpoint of a model directory (no autodiff) onto `device`.
pub fn load_model_dir(dir: &Path, device: &Device) -> Result<LoadedModel> {
    if !dir.is_dir() {
        bail!("model directory {} does not exist", dir.display());
    }
    let mc = dir.join(files::MODEL_CONFIG);
    let model_config = ModelConfig::load(&mc)
        .map_err(|e| anyhow::anyhow!("cannot read {}: {e:?}", mc.display()))?;
    model_config.validate()?;
    let tc = dir.join(files::TRAIN_CONFIG);
    let train_config = TrainConfig::load(&tc)
        .map_err(|e| anyhow::anyhow!("cannot read {}: {e:?}", tc.display()))?;
    let mp = dir.join(files::META);
    let meta: ModelMeta = serde_json::from_str(
        &fs::read_to_string(&mp).with_context(|| format!("reading {}", mp.display()))?,
    )
    .with_context(|| format!("{} is corrupt", mp.display()))?;
    if meta.format != ModelMeta::FORMAT || meta.version != 1 {
        bail!(
            "{}: not an nppp model directory (format {:?} version {})",
            mp.display(),
            meta.format,
            meta.version
        );
    }
    if meta.input_features != INPUT_FEATURES {
        bail!(
            "{}: the model was trained on {} input features, this build computes {}",
            mp.display(),
            meta.input_features,
            INPUT_FEATURES
        );
    }
    let ckpt = checkpoint_dir(dir)
        .with_context(|| format!("{} holds no checkpoint (train first)", dir.display()))?;
    let state = read_state(&ckpt)?;
    let device = device.clone().without_autodiff();
    let model = load_weights(&ckpt, &model_config, &device)?;
    Ok(LoadedModel {
        dir: dir.to_path_buf(),
        model_config,
        train_config,
        meta,
        model,
        state,
    })
}
