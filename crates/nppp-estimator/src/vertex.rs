//! One vertex of the path an estimator skips, picked for next-event
//! estimation (issue 18), and the invertible map between it and the vertex
//! head's feature vector.
//!
//! Light that reaches an opaque object directly is found by a light sample
//! at each of its vertices; a skipped path has none, and its light is found
//! only when the exit ray happens to hit a lamp. The estimator therefore
//! also returns one vertex of the skipped path, picked with probability
//! proportional to the luminance of its throughput, with that throughput
//! divided by the probability of the pick. One light sample there estimates
//! the direct light of every skipped vertex at once, unbiased over picks.
//!
//! The vertex is a marginal sample: the vertex head has learned the
//! distribution of picked vertices alone, not jointly with the exit. That is
//! enough for the light sample's expectation (a sum over vertices), whatever
//! noise drives the head (the renderer reuses the exit's:
//! `EstimatorSampler::sample_vertices_from_exit_noise`); it rules out MIS
//! against the exit's emitter hit, so the renderer counts the light at
//! skipped vertices by light sampling alone (see `nppp-render`'s
//! `EntryNee::PickedVertex`).

use crate::exit::{fit_mean_std, safe_normalize, standardize};
use glam::Vec3;
use serde::{Deserialize, Serialize};

/// Features of an encoded vertex: position 3, normal 3, direction towards
/// the previous vertex 3, weighted throughput 3, internal bounce index 1.
pub const VERTEX_FEATURES: usize = 13;

/// The most weighted throughput per channel a decoded vertex keeps: the sum
/// of a path's throughputs over its vertices, each at most 1, over the
/// vertices a surface walk makes in practice. A network that asks for more
/// is broken, and would brighten the image without bound.
pub const VERTEX_THROUGHPUT_BOUND: f32 = 16.0;

/// A skipped path's vertex picked for a light sample, in the unit sphere's
/// frame (the same frame as [`crate::Exit`]).
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct PickedVertex {
    /// Inside the unit sphere (on the object's surface).
    pub position: Vec3,
    /// Unit shading normal on the mesh's outward side.
    pub normal: Vec3,
    /// Unit, towards the previous vertex (or the entry point).
    pub wo: Vec3,
    /// Throughput from the entry up to this vertex, before it scatters,
    /// divided by the probability of picking it; zero when the path had no
    /// vertex a light sample may be taken at.
    pub beta: Vec3,
    /// Internal bounces before this vertex (0: the first hit); a renderer
    /// with fewer bounces left than this takes no light sample.
    pub index: u32,
}

/// Per-feature standardization of the encoded vertex; throughput and index
/// are compressed with ln(1 + x) first, as [`crate::ExitTransform`] does.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct VertexTransform {
    pub mean: [f32; VERTEX_FEATURES],
    pub std: [f32; VERTEX_FEATURES],
}

impl Default for VertexTransform {
    fn default() -> Self {
        Self { mean: [0.0; VERTEX_FEATURES], std: [1.0; VERTEX_FEATURES] }
    }
}

impl VertexTransform {
    /// Raw (unstandardized) features of a vertex.
    pub fn raw_features(v: &PickedVertex) -> [f32; VERTEX_FEATURES] {
        let l = |x: f32| x.max(0.0).ln_1p();
        [
            v.position.x,
            v.position.y,
            v.position.z,
            v.normal.x,
            v.normal.y,
            v.normal.z,
            v.wo.x,
            v.wo.y,
            v.wo.z,
            l(v.beta.x),
            l(v.beta.y),
            l(v.beta.z),
            l(v.index as f32),
        ]
    }

    /// Fits mean and std over a set of vertices (std floored at 1e-3).
    pub fn fit<'a>(vertices: impl IntoIterator<Item = &'a PickedVertex>) -> Self {
        let (mean, std) = fit_mean_std(vertices.into_iter().map(Self::raw_features));
        Self { mean, std }
    }

    pub fn encode(&self, v: &PickedVertex) -> [f32; VERTEX_FEATURES] {
        standardize(Self::raw_features(v), &self.mean, &self.std)
    }

    /// Inverts `encode` and repairs what a network may get wrong: a position
    /// outside the unit sphere is pulled onto it, unnormalized or degenerate
    /// vectors are normalized (a degenerate one zeroes the throughput: no
    /// light sample rather than one in a made-up frame), throughput is kept
    /// in [0, [`VERTEX_THROUGHPUT_BOUND`]] and the index in [0, `max_bounces`].
    /// Returns the vertex and whether anything was repaired.
    pub fn decode(&self, f: &[f32; VERTEX_FEATURES], max_bounces: u32) -> (PickedVertex, bool) {
        let mut raw = [0.0f32; VERTEX_FEATURES];
        for i in 0..VERTEX_FEATURES {
            raw[i] = f[i] * self.std[i] + self.mean[i];
        }
        let mut repaired = false;
        let mut position = Vec3::new(raw[0], raw[1], raw[2]);
        if !position.is_finite() {
            repaired = true;
            position = Vec3::ZERO;
        } else if position.length_squared() > 1.0 {
            // Every vertex of the object lies inside its sphere (by a 1%
            // margin): one outside is the network's error, counted.
            repaired = true;
            position = position.normalize_or_zero();
        }
        let normal = safe_normalize(Vec3::new(raw[3], raw[4], raw[5]));
        let wo = safe_normalize(Vec3::new(raw[6], raw[7], raw[8]));
        let unlog = |y: f32, repaired: &mut bool| -> f32 {
            if !y.is_finite() {
                *repaired = true;
                return 0.0;
            }
            (y.min(80.0).exp() - 1.0).max(0.0)
        };
        let mut beta = Vec3::new(unlog(raw[9], &mut repaired), unlog(raw[10], &mut repaired), unlog(raw[11], &mut repaired));
        if beta.max_element() > VERTEX_THROUGHPUT_BOUND {
            repaired = true;
            beta = beta.min(Vec3::splat(VERTEX_THROUGHPUT_BOUND));
        }
        let index = unlog(raw[12], &mut repaired).round().clamp(0.0, max_bounces as f32) as u32;
        let (normal, wo) = match (normal, wo) {
            (Some(n), Some(w)) => (n, w),
            _ => {
                repaired = true;
                beta = Vec3::ZERO;
                (Vec3::Z, Vec3::Z)
            }
        };
        (PickedVertex { position, normal, wo, beta, index }, repaired)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn unit(v: [f32; 3]) -> Vec3 {
        Vec3::from(v).try_normalize().unwrap_or(Vec3::Z)
    }

    /// A position the network put outside the unit sphere is pulled onto it
    /// and counted as a repair (a forged head's far vertices changed the
    /// image with no word).
    #[test]
    fn a_vertex_outside_the_sphere_is_repaired_and_counted() {
        let v = PickedVertex { position: Vec3::new(0.3, 0.0, 0.0), normal: Vec3::Z, wo: Vec3::Z, beta: Vec3::ONE, index: 1 };
        let t = VertexTransform::fit([v, PickedVertex { index: 3, ..v }].iter());
        let far = PickedVertex { position: Vec3::new(3.0, 0.0, 0.0), ..v };
        let (d, repaired) = t.decode(&t.encode(&far), 10);
        assert!(repaired);
        assert!((d.position - Vec3::X).length() < 1e-5, "{:?}", d.position);
        assert!(!t.decode(&t.encode(&v), 10).1);
    }

    proptest! {
        /// decode(encode(v)) = v for every vertex a walk can record.
        #[test]
        fn encode_then_decode_returns_the_vertex(
            p in prop::array::uniform3(-0.57f32..0.57),
            n in prop::array::uniform3(-1.0f32..1.0),
            w in prop::array::uniform3(-1.0f32..1.0),
            b in prop::array::uniform3(0.0f32..8.0),
            index in 0u32..200,
        ) {
            let v = PickedVertex { position: Vec3::from(p), normal: unit(n), wo: unit(w), beta: Vec3::from(b), index };
            let t = VertexTransform::fit([v, PickedVertex { index: 3, ..v }].iter());
            let (d, repaired) = t.decode(&t.encode(&v), 1000);
            prop_assert!(!repaired);
            prop_assert!((d.position - v.position).length() < 1e-4);
            prop_assert!((d.normal - v.normal).length() < 1e-4);
            prop_assert!((d.wo - v.wo).length() < 1e-4);
            prop_assert!((d.beta - v.beta).abs().max_element() < 1e-3 * (1.0 + v.beta.max_element()));
            prop_assert_eq!(d.index, v.index);
        }

        /// Whatever a network outputs, the decoded vertex is usable: inside
        /// the sphere, unit vectors, finite bounded throughput.
        #[test]
        fn any_output_decodes_to_a_usable_vertex(f in prop::array::uniform13(prop::num::f32::ANY)) {
            let (v, _) = VertexTransform::default().decode(&f, 64);
            prop_assert!(v.position.is_finite() && v.position.length() <= 1.0 + 1e-5);
            prop_assert!((v.normal.length() - 1.0).abs() < 1e-4);
            prop_assert!((v.wo.length() - 1.0).abs() < 1e-4);
            prop_assert!(v.beta.is_finite() && v.beta.min_element() >= 0.0);
            prop_assert!(v.beta.max_element() <= VERTEX_THROUGHPUT_BOUND);
            prop_assert!(v.index <= 64);
        }
    }
}
