//! The run's configuration: what `nppp train` was asked for
//! ([`TrainOptions`]), what defines a run ([`TrainConfig`], saved as
//! `train_config.json`), how the two meet on a fresh run or a resume
//! (`resolve_config`, which also opens and checks the checkpoint), and the
//! fingerprint of the data a checkpoint is checked against.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use burn::config::Config;
use nppp_estimator::EXIT_FEATURES;

use super::CHECKPOINT_EVERY_S;
use crate::backend::BackendKind;
use crate::data::TrainingData;
use crate::features::INPUT_FEATURES;
use crate::io::DatasetInfo;
use crate::model::ModelConfig;
use crate::model_dir::{
    Checkpoint, DataFingerprint, check_checkpoint_folders, check_fresh_out, checkpoint_dir,
    checkpoint_read_lock, incomplete_checkpoint, no_checkpoint_message, open_checkpoint,
};

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
    /// Standard normals per decoder row (r): each renderer entry draws this
    /// many per decoder.
    pub noise_dim: Option<usize>,
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
            noise_dim: None,
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
    /// Weight of the vertex head's term (its Chamfer plus `energy_weight`
    /// times its energy distance) when the model has the head.
    #[config(default = 1.0)]
    pub vertex_weight: f32,
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
        self.check_values()?;
        self.check_step_memory()
    }

    /// Refuses values no run can use, naming the key (as in
    /// `train_config.json`; the flag beside it where there is one): a
    /// checkpoint's file is checked with this when it is opened.
    pub fn check_values(&self) -> Result<()> {
        self.model.validate()?;
        let pos = [
            ("batch (--batch)", self.batch),
            ("k (--k)", self.k),
            ("mask_batch (--mask-batch)", self.mask_batch),
        ];
        for (name, v) in pos {
            if v == 0 {
                bail!("{name} = 0 must be at least 1");
            }
        }
        if !(self.lr.is_finite() && self.lr > 0.0) {
            bail!("lr (--lr) = {} must be a number > 0", self.lr);
        }
        for (name, v) in [
            ("lr_decay_from", self.lr_decay_from),
            ("lr_final", self.lr_final),
        ] {
            if !(0.0..=1.0).contains(&v) {
                bail!("{name} = {v} must be in [0, 1]");
            }
        }
        if !(self.energy_weight.is_finite() && self.energy_weight >= 0.0) {
            bail!(
                "energy_weight (--energy-weight) = {} must be a number >= 0",
                self.energy_weight
            );
        }
        if !(self.vertex_weight.is_finite() && self.vertex_weight >= 0.0) {
            bail!(
                "vertex_weight = {} must be a number >= 0",
                self.vertex_weight
            );
        }
        if self.holdout_every < 2 {
            bail!(
                "holdout_every (--holdout-every) = {} must be at least 2",
                self.holdout_every
            );
        }
        // Reached only through an edited file (the flags are checked by
        // clap): each was accepted and trained to nonsense, or "diverged"
        // with the advice to lower --lr.
        for (name, v) in [("beta_1", self.beta_1), ("beta_2", self.beta_2)] {
            if !(0.0..1.0).contains(&v) {
                bail!("{name} = {v} must be in [0, 1) (Adam's decay rate)");
            }
        }
        if !(self.epsilon.is_finite() && self.epsilon > 0.0) {
            bail!("epsilon = {} must be a number > 0", self.epsilon);
        }
        for (name, v) in [
            ("mask_weight", self.mask_weight),
            ("grad_clip_norm", self.grad_clip_norm),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                bail!("{name} = {v} must be a number >= 0");
            }
        }
        if self.eval_rays == 0 {
            bail!("eval_rays (--eval-rays) = 0 must be at least 1");
        }
        Ok(())
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
        // The vertex head doubles the per-exit terms.
        let heads = if m.vertex_head { 2 } else { 1 };
        let (k, per_exit) = (k.saturating_mul(heads), per_exit.saturating_mul(heads));
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

/// The hyperparameters a run keeps for its whole length, once each:
/// `(flag, TrainOptions field, TrainConfig field)`, applied by `$apply`. A
/// fresh run takes the given ones; `--resume` refuses a given one that
/// differs from the checkpoint's.
macro_rules! kept_hyperparameters {
    ($apply:ident) => {
        $apply!("batch", batch, batch);
        $apply!("k", k, k);
        $apply!("mask-batch", mask_batch, mask_batch);
        $apply!("energy-weight", energy_weight, energy_weight);
        $apply!("seed", seed, seed);
        $apply!("holdout-every", holdout_every, holdout_every);
        $apply!("steps-per-epoch", steps_per_epoch, steps_per_epoch);
        $apply!("latent-dim", latent_dim, model.latent_dim);
        $apply!("noise-dim", noise_dim, model.noise_dim);
        $apply!("encoder-width", encoder_width, model.encoder_width);
        $apply!("decoder-width", decoder_width, model.decoder_width);
        $apply!("mask-width", mask_width, model.mask_width);
    };
}

/// The run's configuration: the saved one on resume (checked against the
/// command line), else defaults overridden by the command line. On resume,
/// the checked checkpoint comes with it.
pub(super) fn resolve_config(opts: &TrainOptions) -> Result<(TrainConfig, Option<Checkpoint>)> {
    // meta.json records where the data is (bake reads its held-out rays
    // from there), and JSON holds only UTF-8: such a path failed at the
    // first checkpoint with "path contains invalid UTF-8 characters",
    // naming no file.
    let data_path = std::path::absolute(&opts.data).unwrap_or_else(|_| opts.data.clone());
    if data_path.to_str().is_none() {
        bail!(
            "--data {}: the path is not valid UTF-8 text, and the model records where its \
             training data is (meta.json, for bake); rename the file or the folder that \
             holds it",
            data_path.display()
        );
    }
    let mut ckpt = None;
    let mut cfg = if opts.resume {
        if !opts.out.is_dir() {
            bail!(
                "--resume: {} is not a model directory (no such folder)",
                opts.out.display()
            );
        }
        // Another run may be swapping a checkpoint in (this one has not
        // taken the folder yet): read one whole.
        let _lock = checkpoint_read_lock(&opts.out).context("--resume")?;
        let c = open_checkpoint(&opts.out)
            .context("--resume")?
            .with_context(|| {
                let none = format!(
                    "holds no checkpoint to resume (a run saves its first one at the end of its \
                     first epoch, after {CHECKPOINT_EVERY_S} s, or when stopped)"
                );
                format!("--resume: {}", no_checkpoint_message(&opts.out, &none))
            })?;
        check_checkpoint_folders(&opts.out).context("--resume")?;
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
        macro_rules! check_kept {
            ($flag:literal, $opt:ident, $($field:ident).+) => {
                clash($flag, opts.$opt.map(|v| v.to_string()), cfg.$($field).+.to_string())?;
            };
        }
        kept_hyperparameters!(check_kept);
        cfg
    } else {
        check_fresh_target(opts)?;
        let mut cfg = TrainConfig::new(ModelConfig::new());
        macro_rules! set_given {
            ($flag:literal, $opt:ident, $($field:ident).+) => {
                if let Some(v) = opts.$opt {
                    cfg.$($field).+ = v;
                }
            };
        }
        kept_hyperparameters!(set_given);
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
        bail!(
            "--minutes {}: give a finite number of minutes >= 0 (0 = no budget)",
            opts.minutes
        );
    }
    cfg.validate()?;
    Ok((cfg, ckpt))
}

/// Whether a fresh run may train into `--out`: a folder of its own files
/// (or none) without a checkpoint, unless `--overwrite`. Checked when the
/// run starts and again once it holds the folder's lock: a run that
/// finished in the folder in between was replaced without `--overwrite`.
pub(super) fn check_fresh_target(opts: &TrainOptions) -> Result<()> {
    check_fresh_out(&opts.out)?;
    check_checkpoint_folders(&opts.out)?;
    if checkpoint_dir(&opts.out).is_some() && !opts.overwrite {
        bail!(
            "{} already holds a checkpoint; pass --resume to continue it, --overwrite to \
             start afresh, or choose another --out",
            opts.out.display()
        );
    }
    if let Some(d) = incomplete_checkpoint(&opts.out)
        && !opts.overwrite
    {
        bail!(
            "{} holds files but no {} (an incomplete or damaged checkpoint, whose weights \
             may still be wanted); pass --overwrite to start afresh (they are replaced once \
             the new run's first checkpoint is in place), or choose another --out",
            d.display(),
            crate::model_dir::files::STATE
        );
    }
    Ok(())
}

pub(super) fn fingerprint(info: &DatasetInfo, data: &TrainingData) -> DataFingerprint {
    DataFingerprint {
        rays: data.train.len() + data.heldout.len(),
        hits: data.train.hits() + data.heldout.hits(),
        k: data.k,
        mesh_hash: info.mesh_hash,
        material_hash: info.material_hash,
    }
}
