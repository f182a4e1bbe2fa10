//! The wgpu backend's code path on whatever Vulkan device is present (in CI,
//! Mesa's software rasterizer lavapipe, installed by `.ci/run`). A smoke test
//! of correctness so the path does not rot, never of speed (lavapipe is
//! 13-36x slower than NdArray here, measured). Run it with
//! `cargo test -p nppp-nn --features wgpu --test wgpu` (`make test-wgpu`).
#![cfg(feature = "wgpu")]

mod common;

use std::fs;
use std::path::{Path, PathBuf};

use nppp_estimator::{Dense, Mlp};
use nppp_geom::SampleRng;
use nppp_nn::decoder::BurnDecoder;
use nppp_nn::synthetic::SyntheticObject;
use nppp_nn::train::files;
use nppp_nn::{BackendKind, TrainingData, synthetic_header, train_with_data};

fn tmp(name: &str) -> PathBuf {
    let d = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(format!("nppp-nn-wgpu-{name}"));
    let _ = fs::remove_dir_all(&d);
    d
}

/// The decoder the renderer batches on gives the plain-Rust decoder's
/// outputs on wgpu, as it does on the CPU backends.
#[test]
fn wgpu_decoder_matches_the_cpu_decoder() {
    let mut rng = SampleRng::from_seed(9);
    let widths = [32usize, 64, 64, 64, 13];
    let mlp = Mlp {
        layers: widths
            .windows(2)
            .map(|w| Dense {
                inputs: w[0],
                outputs: w[1],
                weight: (0..w[0] * w[1]).map(|_| rng.normal() * 0.3).collect(),
                bias: (0..w[1]).map(|_| rng.normal() * 0.1).collect(),
            })
            .collect(),
    };
    // Two batch sizes: the first call on a shape compiles kernels.
    for rows in [1usize, 1000] {
        let input: Vec<f32> = (0..rows * 32).map(|_| rng.normal()).collect();
        let mut want = vec![0.0; rows * 13];
        mlp.forward_batch(&input, &mut want);
        let dec = BurnDecoder::new(&mlp, BackendKind::Wgpu).unwrap();
        let mut got = vec![0.0; rows * 13];
        dec.forward(&input, rows, &mut got).unwrap();
        for (a, b) in got.iter().zip(&want) {
            assert!((a - b).abs() <= 1e-4 * (1.0 + b.abs()), "{a} vs {b}");
        }
    }
}

fn epoch_losses(dir: &Path) -> Vec<f64> {
    fs::read_to_string(dir.join(files::LOG))
        .unwrap()
        .lines()
        .skip(1)
        .map(|l| l.split(',').nth(4).unwrap().parse().unwrap())
        .collect()
}

/// Training runs on wgpu with the same code as on the CPU: the same seed
/// gives the same losses as NdArray up to float rounding, and they fall.
#[test]
fn wgpu_training_follows_ndarray() {
    let rays = SyntheticObject::Mirror { radius: 0.6 }.rays(800, 8, 11);
    let data = TrainingData::build(rays, 8, 10).unwrap();
    let info = synthetic_header("mirror", 8);
    let run = |backend: BackendKind| {
        let dir = tmp(&backend.to_string());
        let mut o = common::small_opts(&dir);
        o.backend = backend;
        o.steps_per_epoch = Some(20);
        o.epochs = Some(3);
        let rep = train_with_data(&o, info.clone(), data.clone()).unwrap();
        assert_eq!(rep.steps, 60, "{backend}");
        let m = rep.metrics.unwrap();
        assert!(
            m.chamfer.is_finite() && m.mask_accuracy > 0.5,
            "{backend}: {m:?}"
        );
        epoch_losses(&dir)
    };
    let cpu = run(BackendKind::Ndarray);
    let gpu = run(BackendKind::Wgpu);
    assert!(gpu.iter().all(|l| l.is_finite()), "{gpu:?}");
    assert!(gpu[2] < gpu[0], "wgpu loss does not fall: {gpu:?}");
    // The first epoch starts from identical weights and random numbers.
    let rel = (gpu[0] - cpu[0]).abs() / cpu[0].abs();
    assert!(
        rel < 1e-2,
        "epoch 1 loss: wgpu {} vs ndarray {}",
        gpu[0],
        cpu[0]
    );
}
