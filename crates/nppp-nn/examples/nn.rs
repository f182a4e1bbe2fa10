//! The measurements behind the crate README that `nppp` has no command for:
//! bake sweeps and training on analytic objects. (`nppp train` and `nppp
//! bake` are the real commands; this example takes only the flags these
//! measurements vary and leaves every other option at its default.)
//!
//! ```text
//! cargo run -p nppp-nn --release --example nn -- sweep --model models/knot
//! cargo run -p nppp-nn --release --example nn -- synthetic --object diffuse --out /tmp/m
//! ```

use clap::{Parser, Subcommand};
use nppp_nn::synthetic::SyntheticObject;
use nppp_nn::{BackendKind, BakeOptions, TrainOptions, TrainingData, synthetic_header};
use std::path::PathBuf;

#[derive(Parser)]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Baked-vs-unbaked accuracy at several grid sizes and bit depths.
    Sweep {
        /// Model directory written by `nppp train`.
        #[arg(long)]
        model: PathBuf,
        #[arg(long, value_delimiter = ',', default_value = "16,32,64")]
        res: Vec<u32>,
        #[arg(long, value_delimiter = ',', default_value = "8,4,2")]
        bit_depths: Vec<u8>,
        /// Held-out hit rays scored per row.
        #[arg(long, default_value_t = 512)]
        eval_rays: usize,
        /// Use Burn's NdArray backend instead of Flex.
        #[arg(long)]
        ndarray: bool,
    },
    /// Train on an analytic object.
    Synthetic {
        /// mirror | diffuse
        #[arg(long, default_value = "diffuse")]
        object: String,
        #[arg(long, default_value_t = 20_000)]
        rays: usize,
        #[arg(long, default_value_t = 64)]
        file_k: usize,
        #[arg(long, default_value_t = 1)]
        data_seed: u64,
        /// Model directory to create.
        #[arg(long)]
        out: PathBuf,
        #[arg(long)]
        steps: Option<u64>,
        #[arg(long)]
        seed: Option<u64>,
        /// Training-time budget in minutes (0 = none).
        #[arg(long, default_value_t = 0.0)]
        minutes: f64,
        #[arg(long)]
        overwrite: bool,
        #[arg(long)]
        quiet: bool,
    },
}

fn main() -> anyhow::Result<()> {
    match Cli::parse().cmd {
        Cmd::Sweep {
            model,
            res,
            bit_depths,
            eval_rays,
            ndarray,
        } => {
            let mut bake = BakeOptions::new(model, "unused.nppp");
            bake.eval_rays = eval_rays;
            if ndarray {
                bake.backend = BackendKind::Ndarray;
            }
            let rows = nppp_nn::bake_sweep(&bake, &res, &bit_depths)?;
            println!("{}", serde_json::to_string_pretty(&rows)?);
            println!("{}", nppp_nn::bake::sweep_table(&rows));
        }
        Cmd::Synthetic {
            object,
            rays,
            file_k,
            data_seed,
            out,
            steps,
            seed,
            minutes,
            overwrite,
            quiet,
        } => {
            let obj = match object.as_str() {
                "mirror" => SyntheticObject::Mirror { radius: 0.6 },
                "diffuse" => SyntheticObject::AbsorbingDiffuse { radius: 0.6 },
                o => anyhow::bail!("unknown object {o}"),
            };
            let mut train = TrainOptions::new("synthetic", out);
            train.steps = steps;
            train.seed = seed;
            train.minutes = minutes;
            train.overwrite = overwrite;
            train.quiet = quiet;
            let rays = obj.rays(rays, file_k, data_seed);
            let data = TrainingData::build(rays, file_k, train.holdout_every.unwrap_or(20))?;
            let rep = nppp_nn::train_with_data(&train, synthetic_header(&object, file_k), data)?;
            println!("{}", serde_json::to_string_pretty(&rep)?);
        }
    }
    Ok(())
}
