//! Burn losses against brute-force references, and the decoder export.

use burn::tensor::{Device, Tensor, TensorData};
use nppp_estimator::EXIT_FEATURES;
use nppp_geom::SampleRng;
use nppp_nn::loss::{self, reference};
use nppp_nn::{ModelConfig, NpppModel};

#[allow(deprecated)]
fn dev() -> Device {
    Device::ndarray()
}

fn randn(n: usize, rng: &mut SampleRng) -> Vec<f32> {
    (0..n).map(|_| rng.normal()).collect()
}

fn t3(v: Vec<f32>, s: [usize; 3]) -> Tensor<3> {
    Tensor::from_data(TensorData::new(v, s), &dev())
}

fn scalar(t: Tensor<1>) -> f64 {
    t.into_data().try_into_vec::<f32>().unwrap()[0] as f64
}

#[test]
fn chamfer_matches_brute_force() {
    let mut rng = SampleRng::from_seed(1);
    let (b, n, m, d) = (3, 7, 5, EXIT_FEATURES);
    let a = randn(b * n * d, &mut rng);
    let c: Vec<f32> = randn(b * m * d, &mut rng)
        .iter()
        .map(|x| 2.0 * x + 0.5)
        .collect();
    let got = scalar(loss::chamfer(
        t3(a.clone(), [b, n, d]),
        t3(c.clone(), [b, m, d]),
    ));
    let want: f64 = (0..b)
        .map(|i| {
            reference::chamfer(
                &a[i * n * d..(i + 1) * n * d],
                &c[i * m * d..(i + 1) * m * d],
                d,
            )
        })
        .sum::<f64>()
        / b as f64;
    assert!((got - want).abs() < 1e-4 * want.max(1.0), "{got} vs {want}");
    // Identical sets: zero (up to the expansion's rounding).
    let same = scalar(loss::chamfer(t3(a.clone(), [b, n, d]), t3(a, [b, n, d])));
    assert!(same.abs() < 1e-4, "{same}");
}

#[test]
fn energy_distance_matches_brute_force() {
    let mut rng = SampleRng::from_seed(2);
    let (b, n, d) = (2, 9, EXIT_FEATURES);
    let a = randn(b * n * d, &mut rng);
    let c: Vec<f32> = randn(b * n * d, &mut rng)
        .iter()
        .map(|x| 0.5 * x + 1.0)
        .collect();
    let (ta, tc) = (t3(a.clone(), [b, n, d]), t3(c.clone(), [b, n, d]));
    let dxy = loss::pairwise_sq_dists(ta.clone(), tc.clone());
    let got = scalar(loss::energy_distance(dxy, ta, tc));
    let want: f64 = (0..b)
        .map(|i| {
            let s = i * n * d..(i + 1) * n * d;
            reference::energy_distance(&a[s.clone()], &c[s], d)
        })
        .sum::<f64>()
        / b as f64;
    assert!(
        (got - want).abs() < 1e-3 * want.abs().max(1.0),
        "{got} vs {want}"
    );
    assert!(want > 0.1);
}

#[test]
fn bce_matches_brute_force_and_is_stable() {
    let logits = vec![-30.0f32, -3.0, -0.5, 0.0, 0.7, 4.0, 25.0, 1.5];
    let labels = vec![0.0f32, 1.0, 0.0, 1.0, 1.0, 0.0, 1.0, 1.0];
    let t = |v: Vec<f32>| Tensor::<1>::from_data(TensorData::new(v.clone(), [v.len()]), &dev());
    let got = scalar(loss::bce_with_logits(t(logits.clone()), t(labels.clone())));
    let want = reference::bce(&logits, &labels);
    assert!((got - want).abs() < 1e-5 * want.max(1.0), "{got} vs {want}");
    // Logits far beyond what exp() survives in f32: still finite and right.
    let got = scalar(loss::bce_with_logits(
        t(vec![200.0, -200.0]),
        t(vec![0.0, 1.0]),
    ));
    assert!((got - 200.0).abs() < 1e-3, "{got}");
}

#[test]
fn exported_decoder_matches_burn() {
    let cfg = ModelConfig::new();
    let model = NpppModel::init(&cfg, 7, &dev()).unwrap();
    let mlp = model.export_decoder().unwrap();
    assert_eq!(mlp.inputs(), cfg.latent_dim + cfg.noise_dim);
    assert_eq!(mlp.outputs(), EXIT_FEATURES);
    let rows = 257;
    let mut rng = SampleRng::from_seed(3);
    let x: Vec<f32> = randn(rows * mlp.inputs(), &mut rng)
        .iter()
        .map(|v| 3.0 * v)
        .collect();
    let burn_out = model
        .decoder
        .forward(Tensor::from_data(
            TensorData::new(x.clone(), [rows, mlp.inputs()]),
            &dev(),
        ))
        .into_data()
        .try_into_vec::<f32>()
        .unwrap();
    let mut out = vec![0.0; rows * EXIT_FEATURES];
    mlp.forward_batch(&x, &mut out);
    let worst = burn_out
        .iter()
        .zip(&out)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(worst < 1e-5, "max |burn - mlp| = {worst}");
    assert!(
        out.iter().any(|v| v.abs() > 0.1),
        "outputs should not be trivial"
    );
}
