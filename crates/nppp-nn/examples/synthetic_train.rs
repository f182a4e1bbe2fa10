//! Trains on an analytic object (no data file needed), to measure step
//! times per backend and compare loss settings:
//!
//! ```text
//! cargo run -p nppp-nn --release --example synthetic_train -- \
//!     --object diffuse --rays 20000 --file-k 64 --out /tmp/m --backend flex --epochs 3
//! ```

use clap::Parser;
use nppp_nn::synthetic::SyntheticObject;
use nppp_nn::{TrainOptions, TrainingData, synthetic_header, train_with_data};

#[derive(Parser)]
struct Args {
    /// mirror | diffuse
    #[arg(long, default_value = "diffuse")]
    object: String,
    #[arg(long, default_value_t = 20_000)]
    rays: usize,
    /// Exits per hit ray in the synthetic "file".
    #[arg(long, default_value_t = 64)]
    file_k: usize,
    #[arg(long, default_value_t = 1)]
    data_seed: u64,
    #[command(flatten)]
    train: TrainOptions,
}

fn main() -> anyhow::Result<()> {
    let a = Args::parse();
    let obj = match a.object.as_str() {
        "mirror" => SyntheticObject::Mirror { radius: 0.6 },
        "diffuse" => SyntheticObject::AbsorbingDiffuse { radius: 0.6 },
        o => anyhow::bail!("unknown object {o}"),
    };
    let rays = obj.rays(a.rays, a.file_k, a.data_seed);
    let every = a.train.holdout_every.unwrap_or(20);
    let data = TrainingData::build(rays, a.file_k, every)?;
    let rep = train_with_data(&a.train, synthetic_header(&a.object, a.file_k), data)?;
    println!("{}", serde_json::to_string_pretty(&rep)?);
    Ok(())
}
