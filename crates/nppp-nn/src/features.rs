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

/// Fourier frequencies (octaves) per angle: a plain ReLU MLP is biased
/// towards smooth functions, and these let it resolve sharp features (mask
/// boundaries of thin parts, caustics). Integer frequencies keep v periodic.
/// Nothing finer than 8 cycles: a 32^4 grid could not hold it anyway.
pub const FOURIER_FREQS: [f32; 4] = [1.0, 2.0, 4.0, 8.0];

/// Features per point: a = 2u - 1 (= cos theta), the point on the sphere
/// (x, y), then sin/cos of v and of a at each of `FOURIER_FREQS`.
const PER_POINT: usize = 3 + 4 * FOURIER_FREQS.len();

/// Length of the feature vector: both points, plus the chord vector (3),
/// the chord's half length (1) and the line's Plucker moment (3), which
/// carry the ray's direction and position directly instead of making the
/// network derive them.
pub const INPUT_FEATURES: usize = 2 * PER_POINT + 7;

fn point_features(u: f32, v: f32, out: &mut [f32]) -> [f32; 3] {
    let a = (2.0 * u - 1.0).clamp(-1.0, 1.0);
    let s = (1.0 - a * a).max(0.0).sqrt();
    let (sv, cv) = (TAU * v).sin_cos();
    let p = [s * cv, s * sv, a];
    out[0] = a;
    out[1] = p[0];
    out[2] = p[1];
    let mut o = 3;
    for f in FOURIER_FREQS {
        let (s1, c1) = (TAU * f * v).sin_cos();
        let (s2, c2) = (PI * f * a).sin_cos();
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
    // Moment of the line through p1 and p2 (|p1 x p2| <= 1).
    out[o + 4] = p1[1] * p2[2] - p1[2] * p2[1];
    out[o + 5] = p1[2] * p2[0] - p1[0] * p2[2];
    out[o + 6] = p1[0] * p2[1] - p1[1] * p2[0];
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
        let a = SpherePair([0.3, 0.99999, 0.7, 0.4]);
        let b = SpherePair([0.3, 0.00001, 0.7, 0.4]);
        let fa = ray_features(&[a]);
        let fb = ray_features(&[b]);
        assert_eq!(fa.len(), INPUT_FEATURES);
        for (x, y) in fa.iter().zip(&fb) {
            assert!(x.abs() <= 1.0 + 1e-6 && y.abs() <= 1.0 + 1e-6);
            assert!((x - y).abs() < 0.01, "{x} vs {y}");
        }
    }
}
