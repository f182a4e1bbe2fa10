//! `nppp`: the command-line tool. Each subcommand is one stage of the
//! pipeline (gen, train, bake, render, bench) or a utility (info, mesh).

mod bench_cmd;
mod gen_cmd;
mod mesh_cmd;
mod render_cmd;

use anyhow::Result;
use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "nppp",
    version,
    about = "Path tracing with neural probabilistic path prediction"
)]
struct Cli {
    /// Worker threads (default: all cores).
    #[arg(long, global = true)]
    threads: Option<usize>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Render a scene to an EXR (and optionally a PNG preview).
    Render(render_cmd::RenderArgs),
    /// Generate estimator training data: path-trace one object alone.
    Gen(gen_cmd::GenArgs),
    /// Train an estimator (Burn) on data from `nppp gen`.
    Train(nppp_nn::TrainOptions),
    /// Bake a trained model into a quantized `.nppp` estimator.
    Bake(nppp_nn::BakeOptions),
    /// Write a scene's mesh (e.g. a procedural object) as an OBJ.
    Mesh(mesh_cmd::MeshArgs),
    /// Time against error: PT at M = 1..5 and PT + NPPP at P = 0..3 against a
    /// cached high-spp reference; writes a Markdown table, CSV and plots.
    Bench(bench_cmd::BenchArgs),
    /// Print what a `.nppp` estimator holds and its memory.
    Info {
        /// The `.nppp` file.
        file: std::path::PathBuf,
    },
}

fn main() {
    let cli = Cli::parse();
    if let Err(e) = run(cli) {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

fn run(cli: Cli) -> Result<()> {
    if let Some(t) = cli.threads {
        anyhow::ensure!(t >= 1, "--threads must be at least 1");
        rayon::ThreadPoolBuilder::new()
            .num_threads(t)
            .build_global()?;
    }
    match cli.command {
        Command::Render(a) => render_cmd::run(&a),
        Command::Gen(a) => gen_cmd::run(&a),
        Command::Bench(a) => bench_cmd::run(&a),
        Command::Train(o) => {
            let r = nppp_nn::train(&o)?;
            eprintln!("{r:#?}");
            Ok(())
        }
        Command::Bake(o) => {
            let r = nppp_nn::bake(&o)?;
            eprintln!("{r:#?}");
            Ok(())
        }
        Command::Mesh(a) => mesh_cmd::run(&a),
        Command::Info { file } => {
            let b = nppp_estimator::BakedEstimator::load(&file)?;
            println!("{}", b.describe());
            Ok(())
        }
    }
}
