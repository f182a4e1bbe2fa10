//! `nppp`: the command-line tool. Each subcommand is one stage of the
//! pipeline (gen, train, bake, render, bench) or a utility (info, mesh).

mod bench;
mod bench_cmd;
mod gen_cmd;
mod merge_cmd;
mod mesh_cmd;
mod plot;
mod render_cmd;
mod train_cmd;

use anyhow::Result;
use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "nppp",
    version,
    about = "Path tracing with neural probabilistic path prediction"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

/// A count flag's value, as a clap value parser: a whole number of at least
/// 1, so that a 0 is a usage error naming the flag (status 2), as every
/// other malformed flag is.
pub(crate) fn at_least_one<T>(s: &str) -> Result<T, String>
where
    T: std::str::FromStr + PartialOrd + From<u8>,
{
    let v: T = s.parse().map_err(|_| {
        if s.trim().parse::<u128>().is_ok() {
            format!("{s} is too large")
        } else {
            format!("\"{s}\" is not a whole number")
        }
    })?;
    if v >= T::from(1) {
        Ok(v)
    } else {
        Err("must be at least 1".into())
    }
}

/// The most `--threads` per available core.
const MAX_THREADS_PER_CORE: usize = 64;

/// `--threads`, on the subcommands whose work runs on the thread pool.
#[derive(clap::Args)]
struct Threads {
    /// Worker threads (default: all cores).
    #[arg(long, value_parser = at_least_one::<usize>)]
    threads: Option<usize>,
}

#[derive(Subcommand)]
enum Command {
    /// Render a scene to an EXR (and optionally a PNG preview).
    Render {
        #[command(flatten)]
        args: render_cmd::RenderArgs,
        #[command(flatten)]
        threads: Threads,
    },
    /// Generate estimator training data: path-trace one object alone.
    Gen {
        #[command(flatten)]
        args: gen_cmd::GenArgs,
        #[command(flatten)]
        threads: Threads,
    },
    /// Train an estimator (Burn) on data from `nppp gen`.
    Train {
        #[command(flatten)]
        args: train_cmd::TrainArgs,
        #[command(flatten)]
        threads: Threads,
    },
    /// Bake a trained model into a quantized `.nppp` estimator.
    Bake {
        #[command(flatten)]
        args: train_cmd::BakeArgs,
        #[command(flatten)]
        threads: Threads,
    },
    /// Merge shards (`render --shard`, `gen --shard`) into the file one run
    /// would have written: render parts into an EXR, data parts into an .nppd.
    Merge(merge_cmd::MergeArgs),
    /// Write a scene's mesh (e.g. a procedural object) as an OBJ.
    Mesh(mesh_cmd::MeshArgs),
    /// Time against error: PT at M = 1..5 and PT + NPPP at P = 0..3 against a
    /// cached high-spp reference; writes a Markdown table, CSV and plots.
    Bench {
        #[command(flatten)]
        args: bench_cmd::BenchArgs,
        #[command(flatten)]
        threads: Threads,
    },
    /// Draw the training curves of a model directory's log.csv (SVG or PNG).
    PlotLog(plot::PlotLogArgs),
    /// Print what a `.nppp` estimator holds and its memory.
    Info {
        /// The `.nppp` file.
        file: std::path::PathBuf,
    },
}

fn main() {
    let cli = Cli::parse();
    if matches!(cli.command, Command::Render { .. } | Command::Bench { .. }) {
        // SAFETY: first thing in `main` after parsing the flags, before any
        // thread exists. Training and baking are left as they were.
        unsafe { nppp_nn::backend::single_threaded_gemm() };
    }
    // SAFETY: as above, no thread exists yet.
    unsafe { pin_pool_size(cli.command.threads()) };
    if let Err(e) = run(cli) {
        nppp_files::note!("error: {e:#}");
        // Output folders this run made and left empty (it failed before
        // writing into them).
        nppp_files::remove_new_empty_dirs();
        std::process::exit(1);
    }
}

/// Whether `p` ends in `.ext` (any case): outputs are checked by name before
/// any work, so a slip of the flags cannot write one format under another's name.
fn has_extension(p: &std::path::Path, ext: &str) -> bool {
    p.extension()
        .is_some_and(|e| e.to_string_lossy().eq_ignore_ascii_case(ext))
}

/// `--out` of a command that writes training data (gen, merge of data
/// parts): an existing file is kept unless `overwrite`, since it can be
/// hours of tracing.
fn keep_existing_data(out: &std::path::Path, overwrite: bool, command: &str) -> Result<()> {
    anyhow::ensure!(
        overwrite || !out.exists(),
        "--out {}: exists; training data can be hours of tracing, so {command} keeps it: pass \
         --overwrite to replace it, or name another file",
        out.display()
    );
    Ok(())
}

/// The most threads a pool may have ([`MAX_THREADS_PER_CORE`] per core),
/// and the cores.
fn most_threads() -> (usize, usize) {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    (MAX_THREADS_PER_CORE * cores.max(1), cores)
}

/// Every thread pool the process makes without a size takes it from
/// `RAYON_NUM_THREADS`: the global one without `--threads`, and the pools
/// that exr builds for each image it compresses or reads. The variable is
/// set to `--threads` where given (so that it bounds those too), and capped
/// at [`most_threads`] otherwise (5000 made an 8x8 render take 42 s, with
/// `--threads 2` 18 s, in exr's pools).
///
/// # Safety
/// Must run before any thread exists (it sets an environment variable).
unsafe fn pin_pool_size(threads: Option<&Threads>) {
    const VAR: &str = "RAYON_NUM_THREADS";
    const OLD_VAR: &str = "RAYON_RS_NUM_CPUS";
    let (most, cores) = most_threads();
    let size = match threads.and_then(|t| t.threads) {
        // Larger: refused by Threads::install before any work.
        Some(t) => (t <= most).then_some(t),
        None => {
            // As rayon reads them: its deprecated RAYON_RS_NUM_CPUS counts
            // where RAYON_NUM_THREADS is unset or not a number (3000 made
            // a tiny render take 15 s).
            let read = |var: &str| {
                std::env::var(var)
                    .ok()
                    .and_then(|v| v.trim().parse::<usize>().ok())
            };
            let asked = match read(VAR) {
                Some(n) => Some((VAR, n)),
                None => read(OLD_VAR).map(|n| (OLD_VAR, n)),
            };
            asked.filter(|&(_, n)| n > most).map(|(var, n)| {
                nppp_files::note!(
                    "warning: {var}={n}: using {most} threads ({MAX_THREADS_PER_CORE} per \
                     core; this machine has {cores})"
                );
                most
            })
        }
    };
    if let Some(n) = size {
        // SAFETY: the caller guarantees that no other thread exists.
        unsafe { std::env::set_var(VAR, n.to_string()) };
    }
}

impl Command {
    /// The command's `--threads`, for those that have it.
    fn threads(&self) -> Option<&Threads> {
        match self {
            Command::Render { threads, .. }
            | Command::Gen { threads, .. }
            | Command::Train { threads, .. }
            | Command::Bake { threads, .. }
            | Command::Bench { threads, .. } => Some(threads),
            _ => None,
        }
    }
}

impl Threads {
    /// Sizes the global thread pool (rayon: the renderer, data generation
    /// and Burn's CPU backends all run on it).
    fn install(&self) -> Result<()> {
        if let Some(t) = self.threads {
            // Far more threads than cores only adds scheduling (a typo of
            // 100000 took minutes to start and stop its pool).
            let (most, cores) = most_threads();
            anyhow::ensure!(
                t <= most,
                "--threads {t}: at most {most} ({MAX_THREADS_PER_CORE} per core; this machine has {cores})"
            );
            // rayon's error repeats its cause; said once, with the flag.
            rayon::ThreadPoolBuilder::new()
                .num_threads(t)
                .build_global()
                .map_err(|e| {
                    let why =
                        std::error::Error::source(&e).map_or(e.to_string(), |s| s.to_string());
                    anyhow::anyhow!(
                        "--threads {t}: cannot start {t} worker threads ({why}); ask for fewer, \
                         or raise the process's limits (ulimit -u, ulimit -v)"
                    )
                })?;
        }
        Ok(())
    }
}

/// Ctrl-C or SIGTERM during training: the loop saves a checkpoint after the
/// current step and `nppp train` exits with status 1, saying how to resume.
/// Before the loop (reading data) or at a second signal it exits at once
/// (status 130): every file it writes is replaced atomically, so nothing is
/// left half-written.
fn stop_training_on_interrupt() -> Result<()> {
    ctrlc::set_handler(|| {
        if nppp_nn::in_training_loop() && !nppp_nn::stop_requested() {
            nppp_files::note!(
                "\ninterrupt: saving a checkpoint after this step (again to quit at once)"
            );
            nppp_nn::request_stop();
        } else {
            exit_interrupted();
        }
    })
    .map_err(|e| anyhow::anyhow!("cannot install the interrupt handler: {e}"))
}

/// Removes the temporary files of the writes in progress (their outputs
/// keep their old contents), names the outputs already put in place, and
/// exits with status 130.
fn exit_interrupted() {
    let written = nppp_files::remove_pending_temp_files();
    if written.is_empty() {
        nppp_files::note!("\ninterrupted");
    } else {
        // The last few (a bench writes many files; the latest are what a
        // user looks for).
        let mut names: Vec<String> = written
            .iter()
            .rev()
            .take(3)
            .map(|p| p.display().to_string())
            .collect();
        names.reverse();
        if written.len() > names.len() {
            names.insert(0, format!("{} earlier files", written.len() - names.len()));
        }
        nppp_files::note!(
            "\ninterrupted (already written: {}; any other output keeps its old contents)",
            names.join(", ")
        );
    }
    std::process::exit(130);
}

/// Ctrl-C or SIGTERM in any other command: the files being written keep
/// their old contents (every write is atomic) and their temporary files are
/// removed, then the command exits with status 130.
fn clean_up_on_interrupt() -> Result<()> {
    ctrlc::set_handler(exit_interrupted)
        .map_err(|e| anyhow::anyhow!("cannot install the interrupt handler: {e}"))
}

/// A command's summary on stdout (a closed pipe is the reader's choice, not
/// a failure of the command).
fn print_summary(r: &impl std::fmt::Display) -> Result<()> {
    use std::io::Write;
    // Names and notes come from the file: escaped as notes are.
    match writeln!(
        std::io::stdout(),
        "{}",
        nppp_files::printable(&r.to_string())
    ) {
        Err(e) if e.kind() != std::io::ErrorKind::BrokenPipe => Err(e.into()),
        _ => Ok(()),
    }
}

/// Signals that end a job besides Ctrl-C, SIGTERM and SIGHUP (which
/// `ctrlc` handles): a batch system's soft CPU limit (SIGXCPU), a timer
/// (SIGALRM, SIGVTALRM), a user's SIGUSR1/2 or Ctrl-\ (SIGQUIT, whose core
/// dump is of no use to a user of a release build). Their default action ends
/// the process at once, which left `nppp gen`'s temporary file; the first
/// of them is turned into a SIGTERM, so it ends a command as SIGTERM does,
/// and the rest are ignored: SIGXCPU comes again every CPU-second past the
/// soft limit, and a second SIGTERM would cut short the checkpoint a
/// training run saves at the first (Ctrl-C and SIGTERM still quit at once).
#[cfg(unix)]
fn forward_stop_signals_as_term() {
    static FORWARDED: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);
    extern "C" fn raise_term(_: libc::c_int) {
        if FORWARDED.swap(true, std::sync::atomic::Ordering::SeqCst) {
            return;
        }
        // SAFETY: raise(3) is async-signal-safe, as is a lock-free atomic;
        // `ctrlc`'s SIGTERM handler only posts its semaphore.
        unsafe {
            libc::raise(libc::SIGTERM);
        }
    }
    let handler = raise_term as extern "C" fn(libc::c_int) as libc::sighandler_t;
    for sig in [
        libc::SIGQUIT,
        libc::SIGXCPU,
        libc::SIGALRM,
        libc::SIGVTALRM,
        libc::SIGUSR1,
        libc::SIGUSR2,
    ] {
        // SAFETY: installs a handler that does only the above; nothing
        // else in the program handles these signals.
        unsafe {
            libc::signal(sig, handler);
        }
    }
}

#[cfg(not(unix))]
fn forward_stop_signals_as_term() {}

/// A file-size limit (`ulimit -f`) sends SIGXFSZ to a write past it, whose
/// default action ends the process at once: every command died with the
/// shell's "File size limit exceeded" and left its temporary file. Ignored,
/// the write fails with EFBIG instead, and the command reports it naming
/// the file, and removes what it wrote, as for a full disk.
#[cfg(unix)]
fn fail_writes_past_the_file_size_limit() {
    // SAFETY: sets a signal's disposition to "ignore"; nothing else in the
    // program handles SIGXFSZ.
    unsafe {
        libc::signal(libc::SIGXFSZ, libc::SIG_IGN);
    }
}

#[cfg(not(unix))]
fn fail_writes_past_the_file_size_limit() {}

fn run(cli: Cli) -> Result<()> {
    if !matches!(cli.command, Command::Train { .. }) {
        clean_up_on_interrupt()?;
    }
    forward_stop_signals_as_term();
    fail_writes_past_the_file_size_limit();
    match cli.command {
        Command::Render { args, threads } => {
            threads.install()?;
            render_cmd::run(&args)
        }
        Command::Gen { args, threads } => {
            threads.install()?;
            gen_cmd::run(&args)
        }
        Command::Bench { args, threads } => {
            threads.install()?;
            bench_cmd::run(&args)
        }
        Command::Train { args, threads } => {
            threads.install()?;
            stop_training_on_interrupt()?;
            let r = nppp_nn::train(&args.options())?;
            print_summary(&r)?;
            // The curves beside the log; a machine without a font still
            // has the CSV and `nppp plot-log`.
            match plot::plot_training_log(&r.model_dir, None, false) {
                Ok(files) => {
                    let names: Vec<String> =
                        files.iter().map(|f| f.display().to_string()).collect();
                    print_summary(&format!("  curves      {}", names.join(", ")))
                }
                Err(e) => {
                    nppp_files::note!("note: training curves not drawn: {e:#}");
                    Ok(())
                }
            }
        }
        Command::Bake { args, threads } => {
            threads.install()?;
            let r = nppp_nn::bake(&args.options())?;
            print_summary(&r)
        }
        Command::Mesh(a) => mesh_cmd::run(&a),
        Command::Merge(a) => merge_cmd::run(&a),
        Command::PlotLog(a) => {
            let files = plot::plot_training_log(&a.log, a.out.as_deref(), a.overwrite)?;
            for f in files {
                print_summary(&f.display())?;
            }
            Ok(())
        }
        Command::Info { file } => {
            print_summary(&nppp_estimator::BakedEstimator::describe_file(&file)?)
        }
    }
}
