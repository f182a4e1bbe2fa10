//! `nppp train` and `nppp bake`: their flags. The training and baking
//! themselves are nppp-nn's (`nppp_nn::train`, `nppp_nn::bake`), which take
//! plain option structs: clap stays in the CLI.

use nppp_nn::{BackendKind, BakeOptions, TrainOptions};
use std::path::PathBuf;

/// A Burn backend, as a flag value.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum BackendArg {
    /// Burn's NdArray CPU backend (deprecated upstream, kept for the tests).
    Ndarray,
    /// Burn's Flex CPU backend (pure Rust); measured faster than NdArray for
    /// this model on 2 cores (see the crate README), hence the default.
    Flex,
    /// Burn's wgpu backend (a GPU through Vulkan/Metal/DX12); needs nppp
    /// built with the `wgpu` cargo feature.
    Wgpu,
}

impl std::fmt::Display for BackendArg {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        BackendKind::from(*self).fmt(f)
    }
}

impl From<BackendArg> for BackendKind {
    fn from(b: BackendArg) -> Self {
        match b {
            BackendArg::Ndarray => BackendKind::Ndarray,
            BackendArg::Flex => BackendKind::Flex,
            BackendArg::Wgpu => BackendKind::Wgpu,
        }
    }
}

fn parse_bits(s: &str) -> std::result::Result<u8, String> {
    match s.trim() {
        "8" => Ok(8),
        "4" => Ok(4),
        "2" => Ok(2),
        _ => Err(format!("{s}: bits must be 8, 4 or 2")),
    }
}

/// Command-line options of `nppp train`. Hyperparameters left unset take the
/// defaults of `nppp_nn::TrainConfig` on a fresh run, and the saved values on
/// `--resume` (giving a different value then is an error, except for the
/// budget, the learning rate and the backend).
#[derive(clap::Args, Clone, Debug)]
pub struct TrainArgs {
    /// Training data written by `nppp gen`.
    #[arg(long)]
    pub data: PathBuf,
    /// Model directory to create (configs, checkpoint, log.csv).
    #[arg(long)]
    pub out: PathBuf,
    /// Burn backend.
    #[arg(long, value_enum, default_value_t = BackendArg::Flex)]
    pub backend: BackendArg,
    /// Length of the run in optimizer steps (default 24000: about 12 minutes
    /// on 2 cores); the learning-rate schedule follows it.
    #[arg(long, conflicts_with = "epochs", value_parser = crate::at_least_one::<u64>)]
    pub steps: Option<u64>,
    /// Length of the run in epochs (one epoch = one pass over the training
    /// hit rays), instead of --steps.
    #[arg(long, value_parser = crate::at_least_one::<usize>)]
    pub epochs: Option<usize>,
    /// Stop once this many steps are done in total, as if interrupted: the
    /// schedule still follows the run's length, and --resume continues it.
    #[arg(long, value_parser = crate::at_least_one::<u64>)]
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
    #[arg(long, value_parser = crate::at_least_one::<usize>)]
    pub batch: Option<usize>,
    /// Exits per ray per step (a random subset of the file's k).
    #[arg(long, value_parser = crate::at_least_one::<usize>)]
    pub k: Option<usize>,
    /// Rays (hits and misses) per step for the mask term.
    #[arg(long, value_parser = crate::at_least_one::<usize>)]
    pub mask_batch: Option<usize>,
    /// Adam learning rate.
    #[arg(long, value_parser = positive_rate)]
    pub lr: Option<f64>,
    /// Weight of the energy-distance term added to Chamfer (0 = Chamfer only;
    /// default 1).
    #[arg(long)]
    pub energy_weight: Option<f32>,
    /// Seed of every random choice of the run.
    #[arg(long)]
    pub seed: Option<u64>,
    /// Every n-th ray of the file is held out for evaluation.
    #[arg(long, value_parser = at_least_two)]
    pub holdout_every: Option<usize>,
    /// Steps per epoch (default: one pass over the training hit rays).
    #[arg(long, value_parser = crate::at_least_one::<usize>)]
    pub steps_per_epoch: Option<usize>,
    /// Held-out hit rays scored at the end of every epoch.
    #[arg(long, value_parser = crate::at_least_one::<usize>)]
    pub eval_rays: Option<usize>,
    /// Latent size (z); the baked grid stores this many channels.
    #[arg(long, value_parser = network_size)]
    pub latent_dim: Option<usize>,
    /// Standard normals per decoder row (r); an entry draws this many per
    /// decoder row in the renderer.
    #[arg(long, value_parser = network_size)]
    pub noise_dim: Option<usize>,
    /// Encoder hidden width.
    #[arg(long, value_parser = network_size)]
    pub encoder_width: Option<usize>,
    /// Decoder hidden width.
    #[arg(long, value_parser = network_size)]
    pub decoder_width: Option<usize>,
    /// Mask network hidden width.
    #[arg(long, value_parser = network_size)]
    pub mask_width: Option<usize>,
    /// Write a row of training losses (averaged since the previous row),
    /// learning rate and time per step to log.csv every this many steps
    /// (0: only at evaluations).
    #[arg(long, default_value_t = 100)]
    pub log_every: u64,
    /// Also score the held-out rays (and checkpoint) every this many steps,
    /// besides every epoch's end (0: only at epoch ends).
    #[arg(long, default_value_t = 2000)]
    pub eval_every: u64,
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
}

/// A whole number in `range`, for a flag clap then names in its message.
fn count_in(s: &str, range: std::ops::RangeInclusive<usize>) -> Result<usize, String> {
    let v: usize = s
        .parse()
        .map_err(|_| format!("\"{s}\" is not a whole number"))?;
    if range.contains(&v) {
        Ok(v)
    } else if *range.end() == usize::MAX {
        Err(format!("must be at least {}", range.start()))
    } else {
        Err(format!(
            "{v} is out of range: {} to {}",
            range.start(),
            range.end()
        ))
    }
}

/// A network size flag: what `ModelConfig::validate` accepts, said with the
/// flag's name (it named the config key) before any data is read.
fn network_size(s: &str) -> Result<usize, String> {
    count_in(s, 1..=nppp_nn::model::MAX_LAYER_SIZE)
}

/// `--holdout-every`: every n-th ray held out, so n = 1 would hold out all.
fn at_least_two(s: &str) -> Result<usize, String> {
    count_in(s, 2..=usize::MAX)
}

/// A baked grid's resolution: a usage error like every other count (it
/// was refused by bake itself, with status 1).
fn grid_resolution(s: &str) -> Result<u32, String> {
    count_in(s, 2..=256).map(|v| v as u32)
}

/// A learning rate: finite and above 0.
fn positive_rate(s: &str) -> Result<f64, String> {
    let v: f64 = s.parse().map_err(|_| format!("\"{s}\" is not a number"))?;
    if v.is_finite() && v > 0.0 {
        Ok(v)
    } else {
        Err(format!("{v} must be a positive finite number"))
    }
}

impl TrainArgs {
    pub fn options(self) -> TrainOptions {
        TrainOptions {
            data: self.data,
            out: self.out,
            backend: self.backend.into(),
            steps: self.steps,
            epochs: self.epochs,
            stop_after: self.stop_after,
            minutes: self.minutes,
            resume: self.resume,
            overwrite: self.overwrite,
            batch: self.batch,
            k: self.k,
            mask_batch: self.mask_batch,
            lr: self.lr,
            energy_weight: self.energy_weight,
            seed: self.seed,
            holdout_every: self.holdout_every,
            steps_per_epoch: self.steps_per_epoch,
            eval_rays: self.eval_rays,
            latent_dim: self.latent_dim,
            noise_dim: self.noise_dim,
            encoder_width: self.encoder_width,
            decoder_width: self.decoder_width,
            mask_width: self.mask_width,
            log_every: self.log_every,
            eval_every: self.eval_every,
            quiet: self.quiet,
        }
    }
}

/// Command-line options of `nppp bake`.
#[derive(clap::Args, Clone, Debug)]
pub struct BakeArgs {
    /// Model directory written by `nppp train`.
    #[arg(long)]
    pub model: PathBuf,
    /// Latent grid resolution S (S^4 nodes x latent_dim channels), 2 to 256.
    #[arg(long, default_value_t = 32, value_parser = grid_resolution)]
    pub latent_grid: u32,
    /// Mask grid resolution (S^4 logits), 2 to 256.
    #[arg(long, default_value_t = 32, value_parser = grid_resolution)]
    pub mask_grid: u32,
    /// Bits per latent value: 8, 4 or 2.
    #[arg(long, default_value_t = 8, value_parser = parse_bits)]
    pub bits: u8,
    /// Bits per mask logit: 8, 4 or 2.
    #[arg(long, default_value_t = 8, value_parser = parse_bits)]
    pub mask_bits: u8,
    /// The `.nppp` file to write.
    #[arg(long)]
    pub out: PathBuf,
    /// Burn backend that evaluates the encoder and mask network.
    #[arg(long, value_enum, default_value_t = BackendArg::Flex)]
    pub backend: BackendArg,
    /// Data file whose held-out rays score the result (default: the
    /// training data recorded in the model directory).
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// Skip the held-out comparison of baked and unbaked estimators.
    #[arg(long)]
    pub no_eval: bool,
    /// Held-out hit rays scored.
    // At least 1: no ray scored would read as a perfect score of 0.
    #[arg(long, default_value_t = 512, value_parser = crate::at_least_one::<usize>)]
    pub eval_rays: usize,
    /// No progress bars.
    #[arg(long)]
    pub quiet: bool,
}

impl BakeArgs {
    pub fn options(self) -> BakeOptions {
        BakeOptions {
            model: self.model,
            latent_grid: self.latent_grid,
            mask_grid: self.mask_grid,
            bits: self.bits,
            mask_bits: self.mask_bits,
            out: self.out,
            backend: self.backend.into(),
            data: self.data,
            no_eval: self.no_eval,
            eval_rays: self.eval_rays,
            quiet: self.quiet,
        }
    }
}
