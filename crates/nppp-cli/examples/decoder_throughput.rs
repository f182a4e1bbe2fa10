//! Decoder throughput by batch size, per backend: when does a GPU decoder
//! pay? (BENCHMARKS.md, "The decoder on a GPU".)
//!
//! Runs an estimator file's decoder on random rows (the decoder's cost does
//! not depend on the values) with the plain-Rust CPU decoder and each Burn
//! backend asked for, from one thread and from `--threads` threads at once
//! (a render calls the decoder from every worker, each with its own
//! wavefront's entries). Rows per second include everything a render pays:
//! for Burn, the copy into a tensor, the upload, the launch and the readback.
//!
//! ```text
//! cargo run --release -p nppp-cli --example decoder_throughput -- models/cornell-glass.nppp
//! cargo run --release -p nppp-cli --features wgpu --example decoder_throughput -- \
//!     models/cornell-glass.nppp --backends cpu,flex,wgpu --threads 16
//! ```

use anyhow::{Context, Result, bail};
use nppp_estimator::{BakedEstimator, CpuDecoder, ExitDecoder};
use nppp_geom::SampleRng;
use nppp_nn::BackendKind;
use nppp_nn::decoder::BurnDecoder;
use std::time::{Duration, Instant};

/// Batch sizes measured. A render's wavefront step hands the decoder about
/// a hundred entries per call (cornell-glass at P = 0: 111 on average, as
/// `nppp render` reports); the larger sizes show where a GPU would pay.
const BATCHES: [usize; 7] = [64, 256, 1024, 4096, 16384, 65536, 262144];
/// Each measurement repeats its batch for at least this long.
const MIN_TIME: Duration = Duration::from_millis(300);

struct Args {
    file: String,
    backends: Vec<String>,
    threads: usize,
}

fn parse_args() -> Result<Args> {
    let mut it = std::env::args().skip(1);
    let mut file = None;
    let mut backends = vec!["cpu".to_string(), "flex".to_string()];
    let mut threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    while let Some(a) = it.next() {
        match a.as_str() {
            "--backends" => {
                let v = it
                    .next()
                    .context("--backends needs a list, e.g. cpu,flex,wgpu")?;
                backends = v.split(',').map(str::to_string).collect();
            }
            "--threads" => {
                let v = it.next().context("--threads needs a number")?;
                threads = v
                    .parse()
                    .with_context(|| format!("--threads {v}: not a number"))?;
                if threads == 0 {
                    bail!("--threads 0: at least one");
                }
            }
            _ if a.starts_with("--") => bail!("unknown flag {a} (--backends, --threads)"),
            _ => file = Some(a),
        }
    }
    Ok(Args {
        file: file.context(
            "usage: decoder_throughput FILE.nppp [--backends cpu,flex,ndarray,wgpu] [--threads N]",
        )?,
        backends,
        threads,
    })
}

/// Rows per second of `decoder` on batches of `rows`, each of `threads`
/// threads running its own batches at the same time.
fn rows_per_second(
    decoder: &dyn ExitDecoder,
    inputs: usize,
    outputs: usize,
    rows: usize,
    threads: usize,
) -> Result<f64> {
    let mut rng = SampleRng::from_seed(7);
    let input: Vec<f32> = (0..rows * inputs).map(|_| rng.normal()).collect();
    // One call first: a GPU backend compiles its kernels and allocates here.
    let mut warm = vec![0.0f32; rows * outputs];
    decoder
        .decode(&input, rows, &mut warm)
        .map_err(anyhow::Error::msg)?;
    let start = Instant::now();
    let done: Result<Vec<usize>> = std::thread::scope(|s| {
        let handles: Vec<_> = (0..threads)
            .map(|_| {
                let input = &input;
                s.spawn(move || -> Result<usize> {
                    let mut out = vec![0.0f32; rows * outputs];
                    let mut n = 0usize;
                    while start.elapsed() < MIN_TIME {
                        decoder
                            .decode(input, rows, &mut out)
                            .map_err(anyhow::Error::msg)?;
                        n += rows;
                    }
                    Ok(n)
                })
            })
            .collect();
        handles
            .into_iter()
            .map(|h| h.join().expect("decoder thread panicked"))
            .collect()
    });
    let total: usize = done?.iter().sum();
    Ok(total as f64 / start.elapsed().as_secs_f64())
}

fn main() -> Result<()> {
    // As `nppp render` does: the matrix products run on the calling thread.
    // SAFETY: first thing in `main`, before any thread exists.
    unsafe { nppp_nn::backend::single_threaded_gemm() };
    let args = parse_args()?;
    let baked = BakedEstimator::load(std::path::Path::new(&args.file))
        .with_context(|| args.file.clone())?;
    let mlp = &baked.decoder;
    let (inputs, outputs) = (mlp.inputs(), mlp.outputs());
    let widths: Vec<String> = mlp.layers.iter().map(|l| l.outputs.to_string()).collect();
    println!(
        "{}: decoder {inputs} -> {} ({} layers)",
        args.file,
        widths.join(" -> "),
        mlp.layers.len()
    );
    let mut decoders: Vec<(String, Box<dyn ExitDecoder>)> = Vec::new();
    for b in &args.backends {
        let d: Box<dyn ExitDecoder> = match b.as_str() {
            "cpu" => Box::new(CpuDecoder::new(mlp)),
            "flex" => Box::new(BurnDecoder::new(mlp, BackendKind::Flex)?),
            "ndarray" => Box::new(BurnDecoder::new(mlp, BackendKind::Ndarray)?),
            "wgpu" => Box::new(BurnDecoder::new(mlp, BackendKind::Wgpu)?),
            other => bail!("--backends: unknown backend {other} (cpu, flex, ndarray, wgpu)"),
        };
        decoders.push((b.clone(), d));
    }
    let mut thread_counts = vec![1];
    if args.threads > 1 {
        thread_counts.push(args.threads);
    }
    println!("M rows/s (each thread its own batches; threads = {thread_counts:?})");
    print!("{:>8}", "batch");
    for (name, _) in &decoders {
        for t in &thread_counts {
            print!(" {:>14}", format!("{name} x{t}"));
        }
    }
    println!();
    for rows in BATCHES {
        print!("{rows:>8}");
        for (_, d) in &decoders {
            for &t in &thread_counts {
                let r = rows_per_second(d.as_ref(), inputs, outputs, rows, t)?;
                print!(" {:>14.3}", r / 1e6);
            }
        }
        println!();
    }
    Ok(())
}
