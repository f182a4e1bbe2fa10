//! A stand-in for `nppp train` / `nppp bake` while developing this crate,
//! plus the measurements behind the README (synthetic objects, bake sweeps):
//!
//! ```text
//! cargo run -p nppp-nn --release --example nn -- train --data knot.npppdata --out models/knot
//! cargo run -p nppp-nn --release --example nn -- bake --model models/knot --out knot.nppp
//! cargo run -p nppp-nn --release --example nn -- sweep --model models/knot --out unused
//! cargo run -p nppp-nn --release --example nn -- synthetic --object diffuse --data x --out /tmp/m
//! ```

use clap::{Parser, Subcommand};
use nppp_nn::synthetic::SyntheticObject;
use nppp_nn::{BakeOptions, TrainOptions, TrainingData, synthetic_header};

#[derive(Parser)]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    Train(TrainOptions),
    Bake(BakeOptions),
    /// Baked-vs-unbaked accuracy at several grid sizes and bit depths.
    Sweep {
        #[command(flatten)]
        bake: BakeOptions,
        #[arg(long, value_delimiter = ',', default_value = "16,32,64")]
        res: Vec<u32>,
        #[arg(long, value_delimiter = ',', default_value = "8,4,2")]
        bit_depths: Vec<u8>,
    },
    /// Train on an analytic object (`--data` is ignored).
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
        #[command(flatten)]
        train: TrainOptions,
    },
}

fn main() -> anyhow::Result<()> {
    match Cli::parse().cmd {
        Cmd::Train(o) => println!("{}", serde_json::to_string_pretty(&nppp_nn::train(&o)?)?),
        Cmd::Bake(o) => println!("{}", serde_json::to_string_pretty(&nppp_nn::bake(&o)?)?),
        Cmd::Sweep {
            bake,
            res,
            bit_depths,
        } => {
            let rows = nppp_nn::bake_sweep(&bake, &res, &bit_depths)?;
            println!("{}", serde_json::to_string_pretty(&rows)?);
            println!("{}", nppp_nn::bake::sweep_table(&rows));
        }
        Cmd::Synthetic {
            object,
            rays,
            file_k,
            data_seed,
            train,
        } => {
            let obj = match object.as_str() {
                "mirror" => SyntheticObject::Mirror { radius: 0.6 },
                "diffuse" => SyntheticObject::AbsorbingDiffuse { radius: 0.6 },
                o => anyhow::bail!("unknown object {o}"),
            };
            let rays = obj.rays(rays, file_k, data_seed);
            let data = TrainingData::build(rays, file_k, train.holdout_every.unwrap_or(20))?;
            let rep = nppp_nn::train_with_data(&train, synthetic_header(&object, file_k), data)?;
            println!("{}", serde_json::to_string_pretty(&rep)?);
        }
    }
    Ok(())
}
