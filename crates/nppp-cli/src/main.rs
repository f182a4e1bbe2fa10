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
    if matches!(cli.command, Command::Render(_) | Command::Bench(_)) {
        single_threaded_gemm();
    }
    if let Err(e) = run(cli) {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

/// The renderer already runs one wavefront per core, and each wavefront's
/// decoder batch is a `matrixmultiply` product. Burn's ndarray backend turns
/// on that crate's own threading, which would split every batch over extra
/// threads that spin (`sched_yield`) on the cores the renderer is using:
/// 13% of a P = 0 room-skylight render went to yielding, and samples/s rose
/// 1.2x without it (measured on 2 cores). A user's own `MATMUL_NUM_THREADS`
/// is kept. Training and baking are left as they were.
fn single_threaded_gemm() {
    if std::env::var_os("MATMUL_NUM_THREADS").is_none() {
        // SAFETY: called first thing in `main`, before any thread exists, so
        // nothing can read the environment concurrently.
        unsafe { std::env::set_var("MATMUL_NUM_THREADS", "1") };
    }
}

/// Whether `p` ends in `.ext` (any case): outputs are checked by name before
/// any work, so a slip of the flags cannot write one format under another's name.
fn has_extension(p: &std::path::Path, ext: &str) -> bool {
    p.extension()
        .is_some_and(|e| e.to_string_lossy().eq_ignore_ascii_case(ext))
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
            // Not println!: a closed pipe (`nppp info f | head -1`) is the
            // reader's choice, not a crash.
            use std::io::Write;
            match writeln!(std::io::stdout(), "{}", b.describe()) {
                Err(e) if e.kind() != std::io::ErrorKind::BrokenPipe => Err(e.into()),
                _ => Ok(()),
            }
        }
    }
}
