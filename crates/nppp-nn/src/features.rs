//! The encoder's and mask network's view of an input ray.
//!
//! The raw (u1, v1, u2, v2) coordinates are a poor network input: v wraps
//! around, so v = 0.999 and v = 0.001 are neighbours that a network fed raw v
//! would treat as opposite ends of its input range, and the baked grid would
//! show a seam there. Every feature below is a continuous, periodic function
//! of v and bounded in [-1, 1], so the input is already normalized and the
//! wrap-around is invisible to the network.

use nppp_geom::SpherePair;
use std::f32::consts::{PI, TAU};

/// Fourier frequencies per angle; a few octaves let a plain ReLU MLP
/// resolve sharp features (mask boundaries, caustics) without a huge width.
pub const FOURIER_FREQS: usize = 3;

/// Features per point: a = 2u - 1 (= cos theta), the point on the sphere
/// (x, y), then sin/cos of v and of a at `FOURIER_FREQS` frequencies.
const PER_POINT: usize = 3 + 4 * FOURIER_FREQS;

/// Length of the feature vector: both points, plus the chord vector (3) and
/// the chord's half length (1), which carry the ray's direction and impact
/// parameter directly instead of making the network derive them.
pub const INPUT_FEATURES: usize = 2 * PER_POINT + 4;

fn point_features(u: f32, v: f32, out: &mut [f32]) -> [f32; 3] {
    let a = (2.0 * u - 1.0).clamp(-1.0, 1.0);
    let s = (1.0 - a * a).max(0.0).sqrt();
    let (sv, cv) = (TAU * v).sin_cos();
    let p = [s * cv, s * sv, a];
    out[0] = a;
    out[1] = p[0];
    out[2] = p[1];
    let mut o = 3;
    for f in 1..=FOURIER_FREQS {
        // Integer frequencies keep v periodic; u needs no periodicity.
        let (s1, c1) = (TAU * f as f32 * v).sin_cos();
        let (s2, c2) = (PI * f as f32 * a).sin_cos();
        out[o..o + 4].copy_from_slice(&[s1, c1, s2, c2]);
        o += 4;
    }
    p
}

/// Writes the features of `pair` into `out` (length `INPUT_FEATURES`).
pub fn ray_features_into(pair: &SpherePair, out: &mut [f32]) {
    let [u1, v1, u2, v2] = pair.0;
    let p1 = point_features(u1, v1, &mut out[..PER_POINT]);
    let p2 = point_features(u2, v2, &mut out[PER_POINT..2 * PER_POINT]);
    let d = [p2[0] - p1[0], p2[1] - p1[1], p2[2] - p1[2]];
    let o = 2 * PER_POINT;
    // Chord components are in [-2, 2]: halve them to stay in [-1, 1].
    out[o] = 0.5 * d[0];
    out[o + 1] = 0.5 * d[1];
    out[o + 2] = 0.5 * d[2];
    out[o + 3] = 0.5 * (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
}

/// Features of many rays, row-major `[pairs.len()][INPUT_FEATURES]`.
pub fn ray_features(pairs: &[SpherePair]) -> Vec<f32> {
    let mut out = vec![0.0; pairs.len() * INPUT_FEATURES];
    for (p, o) in pairs.iter().zip(out.chunks_exact_mut(INPUT_FEATURES)) {
        ray_features_into(p, o);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn features_are_bounded_and_continuous_across_the_v_seam() {
        let a = SpherePair([0.3, 0.9999, 0.7, 0.4]);
        let b = SpherePair([0.3, 0.0001, 0.7, 0.4]);
        let fa = ray_features(&[a]);
        let fb = ray_features(&[b]);
        assert_eq!(fa.len(), INPUT_FEATURES);
        for (x, y) in fa.iter().zip(&fb) {
            assert!(x.abs() <= 1.0 + 1e-6 && y.abs() <= 1.0 + 1e-6);
            assert!((x - y).abs() < 0.01, "{x} vs {y}");
        }
    }
}
