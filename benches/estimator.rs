//! The estimator's hot paths on the committed default estimator
//! (`models/cornell-knot.nppp`): latent and mask grid lookups (quadrilinear
//! and stochastic, incoherent rays; the mask's hit test with and without its
//! sign table), and the decoder at several batch sizes
//! through the estimator interface the renderer calls
//! (`EstimatorSampler::sample_batch`: latent lookup, noise, decoder, inverse
//! transform) and the decoder backends alone (`ExitDecoder::decode`): the
//! plain-Rust CPU decoder and Burn's CPU backends; and the 16 standard
//! normals an entry draws for the decoder's noise (`SampleRng::normal`, a
//! 32-bit ziggurat, against `rand_distr`'s 64-bit one and Box-Muller, which
//! it replaced).

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use nppp_estimator::{
    BakedEstimator, CpuDecoder, DecodeRepairs, EXIT_FEATURES, EstimatorSampler, ExitBatch,
    ExitDecoder, KernelIsa,
};
use nppp_geom::{SampleRng, SpherePair};
use nppp_nn::BackendKind;
use nppp_nn::decoder::BurnDecoder;
use std::path::Path;

fn sampler() -> EstimatorSampler {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../models/cornell-knot.nppp");
    EstimatorSampler::new(BakedEstimator::load(&path).expect("models/cornell-knot.nppp"))
}

fn random_pairs(n: usize) -> Vec<SpherePair> {
    let mut rng = SampleRng::from_seed(3);
    (0..n)
        .map(|_| SpherePair([rng.uniform(), rng.uniform(), rng.uniform(), rng.uniform()]))
        .collect()
}

fn grids(c: &mut Criterion) {
    let s = sampler();
    let pairs = random_pairs(4096);
    let mut g = c.benchmark_group("estimator_grid_lookup");
    g.throughput(Throughput::Elements(pairs.len() as u64));
    g.bench_function("latent_32^4x16_4bit", |b| {
        let mut z = vec![0.0f32; s.latent_dim()];
        b.iter(|| {
            let mut acc = 0.0;
            for p in &pairs {
                s.latent(p, &mut z);
                acc += z[0];
            }
            acc
        })
    });
    // Stochastic filtering: one corner, picked by its weight (the random
    // numbers drawn as the renderer draws them, from a PCG32 stream).
    g.bench_function("latent_32^4x16_4bit_stochastic", |b| {
        let mut z = vec![0.0f32; s.latent_dim()];
        let mut rng = SampleRng::from_seed(5);
        b.iter(|| {
            let mut acc = 0.0;
            for p in &pairs {
                let u = [rng.uniform(), rng.uniform(), rng.uniform(), rng.uniform()];
                s.latent_stochastic(p, u, &mut z);
                acc += z[0];
            }
            acc
        })
    });
    // The hit test as the renderer asks it (the sign table first, see
    // nppp_estimator::mask_sign), and the interpolation alone.
    g.bench_function("mask_64^4_4bit", |b| {
        b.iter(|| pairs.iter().filter(|p| s.hits(p)).count())
    });
    g.bench_function("mask_64^4_4bit_interpolated", |b| {
        b.iter(|| pairs.iter().filter(|p| s.mask_logit(p) > 0.0).count())
    });
    g.finish();
}

/// The decoder backends a render can pick (`--decoder`), on a CPU.
fn backends(s: &EstimatorSampler) -> Vec<Box<dyn ExitDecoder>> {
    let mut list: Vec<Box<dyn ExitDecoder>> = vec![Box::new(CpuDecoder::new(&s.baked().decoder))];
    for backend in [BackendKind::Ndarray, BackendKind::Flex] {
        list.push(Box::new(
            BurnDecoder::new(&s.baked().decoder, backend).expect("burn decoder"),
        ));
    }
    list
}

fn decoder(c: &mut Criterion) {
    let mut s = sampler();
    let n = s.latent_dim() + s.noise_dim();
    let mut rng = SampleRng::from_seed(4);
    let pairs = random_pairs(1024);
    let mut g = c.benchmark_group("estimator_decoder");
    for rows in [1usize, 64, 1024] {
        let input: Vec<f32> = (0..rows * n).map(|_| rng.normal()).collect();
        let mut out = vec![0.0f32; rows * EXIT_FEATURES];
        g.throughput(Throughput::Elements(rows as u64));
        for dec in backends(&s) {
            g.bench_with_input(
                BenchmarkId::new(dec.name().to_string(), rows),
                &rows,
                |b, _| b.iter(|| dec.decode(&input, rows, &mut out).expect("decode")),
            );
        }
    }
    g.finish();
    // The whole batch as the renderer runs it, per backend.
    let mut g = c.benchmark_group("estimator_sample_batch");
    for dec in backends(&s) {
        let name = dec.name().to_string();
        s.set_decoder(dec);
        for rows in [1usize, 64, 1024] {
            g.throughput(Throughput::Elements(rows as u64));
            let mut batch = ExitBatch::default();
            let mut repairs = DecodeRepairs::default();
            let mut noise_rng = SampleRng::from_seed(6);
            g.bench_with_input(BenchmarkId::new(&name, rows), &rows, |b, _| {
                b.iter(|| {
                    let fill = |k: usize, z: &mut [f32], r: &mut [f32]| {
                        s.latent(&pairs[k], z);
                        r.iter_mut().for_each(|x| *x = noise_rng.normal());
                    };
                    s.sample_batch(&mut batch, rows, fill, &mut repairs)
                        .exits
                        .len()
                })
            });
        }
    }
    g.finish();
}

/// Every committed estimator's CPU decoder at the renderer's batch size
/// (about 128 entries per wavefront step on the default scene): what one
/// decoder row costs by the decoder's size, the measurement behind
/// `auto::COST_PER_DECODER_MULTIPLY_ADD`. `NPPP_BENCH_ESTIMATORS` (paths
/// separated by commas) measures other files instead.
fn decoder_sizes(c: &mut Criterion) {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../models");
    let files: Vec<std::path::PathBuf> = match std::env::var("NPPP_BENCH_ESTIMATORS") {
        Ok(list) => list.split(',').map(Into::into).collect(),
        Err(_) => [
            "cornell-knot",
            "cornell-gold",
            "cornell-glass",
            "cornell-jade",
        ]
        .iter()
        .map(|n| root.join(format!("{n}.nppp")))
        .collect(),
    };
    let rows = 128;
    let mut g = c.benchmark_group("estimator_decoder_rows");
    g.throughput(Throughput::Elements(rows as u64));
    for file in files {
        let baked = BakedEstimator::load(&file).expect("estimator file");
        let macs = baked.decoder.multiply_adds();
        let s = EstimatorSampler::new(baked);
        let n = s.latent_dim() + s.noise_dim();
        let mut rng = SampleRng::from_seed(8);
        let input: Vec<f32> = (0..rows * n).map(|_| rng.normal()).collect();
        let mut out = vec![0.0f32; rows * EXIT_FEATURES];
        let name = file
            .file_stem()
            .map_or("?".into(), |s| s.to_string_lossy().into_owned());
        g.bench_function(
            BenchmarkId::new(&name, format!("{macs}_multiply_adds")),
            |b| b.iter(|| s.cpu_decoder().forward(&input, &mut out)),
        );
        // The same product on each instruction set this CPU has (the
        // default above is the widest).
        for isa in KernelIsa::available() {
            let dec = CpuDecoder::with_isa(&s.baked().decoder, isa);
            g.bench_function(
                BenchmarkId::new(
                    format!("{name}_{}", isa.name()),
                    format!("{macs}_multiply_adds"),
                ),
                |b| b.iter(|| dec.forward(&input, &mut out)),
            );
        }
    }
    g.finish();
}

/// Box-Muller as `SampleRng::normal` drew before it used a ziggurat (one
/// of the pair discarded): the bench's other reference.
fn box_muller(rng: &mut SampleRng) -> f32 {
    let u1 = 1.0 - rng.uniform();
    let u2 = rng.uniform();
    (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos()
}

fn noise(c: &mut Criterion) {
    let mut g = c.benchmark_group("noise_16_normals");
    g.throughput(Throughput::Elements(16));
    let mut out = [0.0f32; 16];
    let mut rng = SampleRng::from_seed(7);
    g.bench_function("ziggurat", |b| {
        b.iter(|| {
            out.iter_mut().for_each(|x| *x = rng.normal());
            out[15]
        })
    });
    // The whole row from one 64-bit draw (`SampleRng::fill_normals`), as
    // the renderer draws a decoder row's noise.
    g.bench_function("ziggurat_row", |b| {
        b.iter(|| {
            rng.fill_normals(&mut out);
            out[15]
        })
    });
    // rand_distr's StandardNormal for f32, which SampleRng::normal used
    // before: an f64 ziggurat on a 64-bit draw (two PCG32 steps).
    g.bench_function("rand_distr_f64_ziggurat", |b| {
        use rand::{Rng, SeedableRng};
        let mut pcg = rand_pcg::Pcg32::seed_from_u64(7);
        b.iter(|| {
            out.iter_mut()
                .for_each(|x| *x = pcg.sample::<f32, _>(rand_distr::StandardNormal));
            out[15]
        })
    });
    g.bench_function("box_muller", |b| {
        b.iter(|| {
            out.iter_mut().for_each(|x| *x = box_muller(&mut rng));
            out[15]
        })
    });
    g.finish();
}

criterion_group!(benches, grids, decoder, decoder_sizes, noise);
criterion_main!(benches);
