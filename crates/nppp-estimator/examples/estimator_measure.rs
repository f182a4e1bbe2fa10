//! Quick measurements quoted in FORMAT.md: grid lookup and sampler speed on
//! one core, and training-data bytes per exit.
//!
//! `cargo run --release -p nppp-estimator --example estimator_measure`

use nppp_estimator::dataset::{DatasetHeader, DatasetWriter, RayRecord, WriterOptions};
use nppp_estimator::{
    BakedEstimator, Dense, EXIT_FEATURES, EstimatorMeta, EstimatorSampler, Exit, ExitBatch, ExitTransform, QuantizedGrid,
};
use nppp_geom::{BoundingSphere, SampleRng, SpherePair, Vec3};
use std::hint::black_box;
use std::time::Instant;

fn random_pairs(n: usize, rng: &mut SampleRng) -> Vec<SpherePair> {
    (0..n).map(|_| SpherePair([rng.uniform(), rng.uniform(), rng.uniform(), rng.uniform()])).collect()
}

fn grid_speed() {
    let mut rng = SampleRng::from_seed(1);
    let res = 32u32;
    let n = nppp_estimator::node_count(res);
    let values: Vec<f32> = (0..n * 16).map(|_| rng.normal()).collect();
    let pairs = random_pairs(1 << 20, &mut rng);
    for bits in [8u8, 4, 2] {
        let g = QuantizedGrid::from_f32(res, 16, &values, bits).unwrap();
        let mut out = [0.0f32; 16];
        let mut acc = 0.0f32;
        let t = Instant::now();
        let reps = 4;
        for _ in 0..reps {
            for p in &pairs {
                g.interpolate(black_box(p), &mut out);
                acc += out[3];
            }
        }
        let dt = t.elapsed().as_secs_f64();
        black_box(acc);
        println!(
            "latent 32^4 x 16 @ {bits} bit ({:.1} MiB): {:.2} M lookups/s ({:.0} ns each)",
            g.data.len() as f64 / (1 << 20) as f64,
            (reps * pairs.len()) as f64 / dt / 1e6,
            dt * 1e9 / (reps * pairs.len()) as f64
        );
    }
    // Coherent rays (a random walk in the 4D space, like neighbouring pixels):
    // what the cache sees when a tile's rays hit one object.
    let mut walk = [0.5f32; 4];
    let coherent: Vec<SpherePair> = (0..1 << 20)
        .map(|_| {
            for x in &mut walk {
                *x = (*x + (rng.uniform() - 0.5) * 0.004).rem_euclid(1.0);
            }
            SpherePair(walk)
        })
        .collect();
    for bits in [8u8, 4, 2] {
        let g = QuantizedGrid::from_f32(res, 16, &values, bits).unwrap();
        let mut out = [0.0f32; 16];
        let mut acc = 0.0f32;
        let t = Instant::now();
        for p in &coherent {
            g.interpolate(black_box(p), &mut out);
            acc += out[3];
        }
        let dt = t.elapsed().as_secs_f64();
        black_box(acc);
        println!(
            "latent 32^4 x 16 @ {bits} bit, coherent rays: {:.2} M lookups/s ({:.0} ns each)",
            coherent.len() as f64 / dt / 1e6,
            dt * 1e9 / coherent.len() as f64
        );
    }
    let mask = QuantizedGrid::from_f32(res, 1, &values[..n], 8).unwrap();
    let mut out = [0.0f32; 1];
    let t = Instant::now();
    let mut acc = 0.0;
    for p in &pairs {
        mask.interpolate(black_box(p), &mut out);
        acc += out[0];
    }
    black_box(acc);
    let dt = t.elapsed().as_secs_f64();
    println!("mask 32^4 x 1 @ 8 bit: {:.2} M lookups/s", pairs.len() as f64 / dt / 1e6);

    // Whole sample: latent lookup + a 32 -> 64 -> 64 -> 13 decoder + decode.
    let mut dense = |i: usize, o: usize| Dense {
        inputs: i,
        outputs: o,
        weight: (0..i * o).map(|_| rng.normal() * 0.2).collect(),
        bias: (0..o).map(|_| rng.normal() * 0.1).collect(),
    };
    let decoder = nppp_estimator::Mlp { layers: vec![dense(32, 64), dense(64, 64), dense(64, EXIT_FEATURES)] };
    let meta = EstimatorMeta {
        mesh_name: "m".into(),
        mesh_hash: 0,
        material_name: "x".into(),
        material_hash: 0,
        sphere: BoundingSphere { center: Vec3::ZERO, radius: 1.0 },
        latent_dim: 16,
        noise_dim: 16,
        max_internal_bounces: 64,
        notes: String::new(),
    };
    let est = BakedEstimator::from_f32_grids(meta, res, &values, res, &values[..n], 8, decoder, ExitTransform::default()).unwrap();
    let s = EstimatorSampler::new(est);
    let mut rep = Default::default();
    let r: Vec<f32> = (0..16 * 4096).map(|_| rng.normal()).collect();
    let mut batch = ExitBatch::default();
    let t = Instant::now();
    let mut n_s = 0;
    for chunk in pairs.chunks(4096).take(64) {
        let fill = |k: usize, z: &mut [f32], noise: &mut [f32]| {
            s.latent(&chunk[k], z);
            noise.copy_from_slice(&r[k * 16..(k + 1) * 16]);
        };
        black_box(s.sample_batch(&mut batch, chunk.len(), fill, &mut rep).exits);
        n_s += chunk.len();
    }
    let dt = t.elapsed().as_secs_f64();
    let rows = 1 << 16;
    let inputs: Vec<f32> = (0..rows * 32).map(|_| rng.normal()).collect();
    let mut y = vec![0.0f32; rows * EXIT_FEATURES];
    let t = Instant::now();
    s.baked().decoder.forward_batch(&inputs, &mut y);
    let d_ref = t.elapsed().as_secs_f64();
    let t = Instant::now();
    s.cpu_decoder().forward(&inputs, &mut y);
    let d_fast = t.elapsed().as_secs_f64();
    black_box(&y);
    println!(
        "decoder only: Mlp::forward_batch {:.2} M rows/s, CpuDecoder::forward {:.2} M rows/s",
        rows as f64 / d_ref / 1e6,
        rows as f64 / d_fast / 1e6
    );
    println!(
        "sample (32->64->64->13 decoder): {:.2} M samples/s, {}",
        n_s as f64 / dt / 1e6,
        s.baked().describe().lines().last().unwrap_or("")
    );
}

fn synthetic(rng: &mut SampleRng, k: u32, hit_rate: f32) -> RayRecord {
    let pair = SpherePair([rng.uniform(), rng.uniform(), rng.uniform(), rng.uniform()]);
    if rng.uniform() >= hit_rate {
        return RayRecord { pair, hit: false, exits: vec![], vertices: vec![] };
    }
    let exits = (0..k)
        .map(|_| {
            let position = nppp_geom::sampling::uniform_sphere(rng.uniform2());
            let mut direction = nppp_geom::sampling::uniform_sphere(rng.uniform2());
            if direction.dot(position) < 0.0 {
                direction = -direction;
            }
            let mut b = 1u32;
            while rng.uniform() < 0.5 && b < 64 {
                b += 1;
            }
            let absorbed = rng.uniform() < 0.1;
            let bi = b as i32;
            let throughput = if absorbed { Vec3::ZERO } else { Vec3::new(0.8f32.powi(bi), 0.6f32.powi(bi), 0.4f32.powi(bi)) };
            Exit { position, direction, throughput, radiance: Vec3::ZERO, bounces: b }
        })
        .collect();
    RayRecord { pair, hit: true, exits, vertices: vec![] }
}

fn dataset_size() {
    let dir = std::env::temp_dir().join(format!("nppp-measure-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let (k, rays, hit_rate) = (512u32, 2000usize, 0.4f32);
    for (label, compress) in [("raw", false), ("deflate", true)] {
        let header = DatasetHeader {
            mesh_name: "m".into(),
            mesh_hash: 0,
            material_name: "diffuse".into(),
            material_hash: 0,
            material_json: "{}".into(),
            sphere: BoundingSphere { center: Vec3::ZERO, radius: 1.0 },
            k,
            seed: 7,
            max_internal_bounces: 64,
            shard: None,
            vertices: false,
        };
        let path = dir.join(format!("{label}.nppd"));
        let mut rng = SampleRng::from_seed(3);
        let mut w = DatasetWriter::create_with(&path, header, WriterOptions { compress, ..Default::default() }).unwrap();
        let t = Instant::now();
        for _ in 0..rays {
            w.write(&synthetic(&mut rng, k, hit_rate)).unwrap();
        }
        let s = w.finish().unwrap();
        let wt = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let mut r = nppp_estimator::DatasetReader::open(&path).unwrap();
        let mut n = 0usize;
        while let Some(c) = r.next_chunk() {
            n += c.unwrap().len();
        }
        let rt = t.elapsed().as_secs_f64();
        assert_eq!(n, rays);
        let per_exit = s.file_bytes as f64 / s.exits as f64;
        let projected = per_exit * 200_000.0 * 0.4 * 512.0;
        println!(
            "{label}: {} rays, {} exits, {} bytes = {per_exit:.2} B/exit (raw payload {:.2} B/exit); write {:.2} M exits/s, read {:.2} M exits/s; 200k rays x k=512 at 40% hits: {:.0} MiB",
            s.rays,
            s.exits,
            s.file_bytes,
            s.raw_bytes as f64 / s.exits as f64,
            s.exits as f64 / wt / 1e6,
            s.exits as f64 / rt / 1e6,
            projected / (1 << 20) as f64
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}

fn main() {
    grid_speed();
    dataset_size();
}
