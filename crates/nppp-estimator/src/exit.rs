//! One sample of where light goes after entering an object's bounding sphere,
//! and the invertible map between it and the network's feature vector.

use glam::Vec3;
use serde::{Deserialize, Serialize};

/// Number of features of an encoded exit: position 3, direction 3,
/// throughput 3, radiance 3, internal bounce count 1.
pub const EXIT_FEATURES: usize = 13;

/// Where a path left the bounding sphere, all in the unit sphere's frame.
///
/// An absorbed path (or one over the internal bounce cap) is an exit with zero
/// throughput: it must stay in the distribution or the estimator over-brightens.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct Exit {
    /// On the unit sphere.
    pub position: Vec3,
    /// Unit, pointing out of the sphere.
    pub direction: Vec3,
    /// Path throughput accumulated inside (rgb, >= 0).
    pub throughput: Vec3,
    /// Radiance gathered inside, already weighted by the inside throughput
    /// (non-zero only for emissive objects).
    pub radiance: Vec3,
    /// Scattering events made inside; counted against the path's M.
    pub bounces: u32,
}

/// Per-feature standardization of the encoded exit. Throughput, radiance and
/// bounces are compressed with ln(1 + x) before standardization so that rare
/// bright values do not dominate the Chamfer distance; `decode` inverts this
/// exactly and clamps to the physically valid range.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ExitTransform {
    pub mean: [f32; EXIT_FEATURES],
    pub std: [f32; EXIT_FEATURES],
}

/// The first entry of a per-feature standardization (`mean`, `std`) that
/// cannot be used, named by index (`"std[0] = 0"`), or `None`: every mean
/// finite, every std finite and > 0. Shared by the exit and vertex
/// transforms of estimator files and model folders.
pub fn transform_problem(mean: &[f32], std: &[f32]) -> Option<String> {
    if let Some((i, m)) = mean.iter().enumerate().find(|(_, m)| !m.is_finite()) {
        return Some(format!("mean[{i}] = {m} is not a finite number"));
    }
    std.iter().enumerate().find(|(_, s)| !(s.is_finite() && **s > 0.0)).map(|(i, s)| format!("std[{i}] = {s} must be a finite number > 0"))
}

impl Default for ExitTransform {
    fn default() -> Self {
        Self { mean: [0.0; EXIT_FEATURES], std: [1.0; EXIT_FEATURES] }
    }
}

/// The most throughput per channel an exit of a surface object can carry:
/// albedo and reflectance are in [0, 1], and a dielectric is entered and
/// left through the same medium, so no channel returns more than entered.
pub const EXIT_THROUGHPUT_BOUND: f32 = 1.0;

/// The same for a translucent object: spectral MIS divides each channel by
/// the mean of the three channels' pdfs of the walk (at most three times the
/// channel's own estimate, itself at most 1). Clamping its exits at 1 made
/// 28% of cornell-jade's network exits, and the knot, darker.
pub const EXIT_THROUGHPUT_BOUND_MEDIUM: f32 = 3.0;

/// Decoded exit radiance beyond its bound, or below 0, that still counts
/// as rounding, not as a broken decoder (the radiance features' standard
/// deviation is floored at 1e-3, so a decoder trained on zeros stays far
/// within this).
pub const EXIT_RADIANCE_TOLERANCE: f32 = 1e-3;

/// The throughput bound of an object with or without a medium inside.
pub fn exit_throughput_bound(has_medium: bool) -> f32 {
    if has_medium { EXIT_THROUGHPUT_BOUND_MEDIUM } else { EXIT_THROUGHPUT_BOUND }
}

/// The most a decoded exit of one object carries per channel; whoever knows
/// the object's material sets it (the `.nppp` file does not record it).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ExitBounds {
    /// See [`exit_throughput_bound`].
    pub throughput: f32,
    /// Radiance gathered inside: 0 for every object but an emitter, whose
    /// walks end at its surface with its own radiance (at most its largest
    /// channel). A decoder that returns more is broken or forged, and its
    /// e^80 would otherwise reach the image.
    pub radiance: f32,
}

impl ExitBounds {
    /// A non-emitting surface (the default).
    pub const SURFACE: Self = Self { throughput: EXIT_THROUGHPUT_BOUND, radiance: 0.0 };

    /// An object with or without a medium inside that emits `emitted` at most
    /// per channel (0 for anything but an emitter).
    pub fn new(has_medium: bool, emitted: f32) -> Self {
        let radiance = if emitted.is_finite() { emitted.max(0.0) } else { 0.0 };
        Self { throughput: exit_throughput_bound(has_medium), radiance }
    }
}

impl Default for ExitBounds {
    fn default() -> Self {
        Self::SURFACE
    }
}

/// Counts of decoder outputs that had to be repaired; the renderer reports them.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct DecodeRepairs {
    /// Position or direction had near-zero length or a non-finite value.
    pub degenerate: u32,
    /// Direction pointed into the sphere and was reflected to point out.
    pub inward: u32,
    /// Throughput or radiance out of range (negative, non-finite, above the
    /// object's [`ExitBounds`]) and clamped.
    pub clamped: u32,
    /// Picked vertices (the vertex head's) that needed a repair.
    pub vertices: u32,
}

impl ExitTransform {
    /// Raw (unstandardized) features of an exit.
    pub fn raw_features(e: &Exit) -> [f32; EXIT_FEATURES] {
        let l = |x: f32| x.max(0.0).ln_1p();
        [
            e.position.x,
            e.position.y,
            e.position.z,
            e.direction.x,
            e.direction.y,
            e.direction.z,
            l(e.throughput.x),
            l(e.throughput.y),
            l(e.throughput.z),
            l(e.radiance.x),
            l(e.radiance.y),
            l(e.radiance.z),
            l(e.bounces as f32),
        ]
    }

    /// Fits mean and std over a set of exits (std floored so that constant
    /// features such as zero radiance stay finite).
    pub fn fit<'a>(exits: impl IntoIterator<Item = &'a Exit>) -> Self {
        let (mean, std) = fit_mean_std(exits.into_iter().map(Self::raw_features));
        Self { mean, std }
    }

    pub fn encode(&self, e: &Exit) -> [f32; EXIT_FEATURES] {
        standardize(Self::raw_features(e), &self.mean, &self.std)
    }

    /// Inverts `encode`; repairs what a network may get wrong (unnormalized
    /// vectors, inward directions, negative or non-finite values, a
    /// throughput or radiance above `bounds`) and counts it, each kind once
    /// per exit. Values just below 0 are zeroed without a count, as
    /// rounding: throughput down to -1e-6, radiance down to
    /// -`EXIT_RADIANCE_TOLERANCE`, the bounce count down to -0.5.
    pub fn decode(&self, f: &[f32; EXIT_FEATURES], max_bounces: u32, bounds: ExitBounds, repairs: &mut DecodeRepairs) -> Exit {
        let mut raw = [0.0f32; EXIT_FEATURES];
        for i in 0..EXIT_FEATURES {
            raw[i] = f[i] * self.std[i] + self.mean[i];
        }
        // Each repair kind is counted once per exit, so that the renderer's
        // shares of repaired exits stay shares.
        let mut degenerate = false;
        let position = safe_normalize(Vec3::new(raw[0], raw[1], raw[2])).unwrap_or_else(|| {
            degenerate = true;
            Vec3::Z
        });
        let mut direction = safe_normalize(Vec3::new(raw[3], raw[4], raw[5])).unwrap_or_else(|| {
            degenerate = true;
            position
        });
        // An exit must leave the sphere: reflect an inward direction about the
        // tangent plane rather than dropping the sample (that would bias energy).
        let c = direction.dot(position);
        if c < 0.0 {
            if !degenerate {
                repairs.inward += 1;
            }
            direction = (direction - 2.0 * c * position).normalize();
        }
        if degenerate {
            repairs.degenerate += 1;
        }
        let mut clamped = false;
        // `rounding`: how far below 0 a value may decode and still count as
        // the decoder's rounding of a 0 (zeroed, not reported as a repair).
        let mut unlog = |y: f32, rounding: f32| -> f32 {
            if !y.is_finite() {
                clamped = true;
                return 0.0;
            }
            // exp(88) overflows f32; anything that large is a broken network.
            let v = y.min(80.0).exp() - 1.0;
            if v < 0.0 {
                if v < -rounding {
                    clamped = true;
                }
                0.0
            } else {
                v
            }
        };
        let throughput = Vec3::new(unlog(raw[6], 1e-6), unlog(raw[7], 1e-6), unlog(raw[8], 1e-6));
        // Radiance as on its positive side: a non-emitter's decoder rounds
        // its zeros to a few 1e-6 either way (the committed tube's: 76% of
        // its exits were reported as repairs, and the render warned that
        // the estimator was undertrained).
        let r = EXIT_RADIANCE_TOLERANCE;
        let radiance = Vec3::new(unlog(raw[9], r), unlog(raw[10], r), unlog(raw[11], r));
        // A count: whatever rounds to 0 is 0.
        let b = unlog(raw[12], 0.5).round();
        // More than the material can return is a broken or forged network,
        // and would brighten the image without bound.
        if throughput.max_element() > 1.01 * bounds.throughput {
            clamped = true;
        }
        let throughput = throughput.min(Vec3::splat(bounds.throughput));
        // Likewise radiance: a non-emitting object's data holds zeros, and a
        // decoder trained on them returns a few 1e-5 at most.
        if radiance.max_element() > 1.01 * bounds.radiance + EXIT_RADIANCE_TOLERANCE {
            clamped = true;
        }
        let radiance = radiance.min(Vec3::splat(bounds.radiance));
        if clamped {
            repairs.clamped += 1;
        }
        let bounces = (b.clamp(0.0, max_bounces as f32)) as u32;
        Exit { position, direction, throughput, radiance, bounces }
    }
}

/// Per-feature mean and standard deviation of feature rows (the std
/// floored at 1e-3 so that a constant feature stays finite); mean 0, std 1
/// for no rows. Shared by the exit and vertex transforms.
pub(crate) fn fit_mean_std<const N: usize>(rows: impl Iterator<Item = [f32; N]>) -> ([f32; N], [f32; N]) {
    let mut n = 0.0f64;
    let mut s = [0.0f64; N];
    let mut s2 = [0.0f64; N];
    for f in rows {
        n += 1.0;
        for i in 0..N {
            s[i] += f[i] as f64;
            s2[i] += (f[i] as f64) * (f[i] as f64);
        }
    }
    let (mut mean, mut std) = ([0.0f32; N], [1.0f32; N]);
    if n == 0.0 {
        return (mean, std);
    }
    for i in 0..N {
        let m = s[i] / n;
        let var = (s2[i] / n - m * m).max(0.0);
        mean[i] = m as f32;
        std[i] = (var.sqrt() as f32).max(1e-3);
    }
    (mean, std)
}

/// `(f - mean) / std`, per feature.
pub(crate) fn standardize<const N: usize>(mut f: [f32; N], mean: &[f32; N], std: &[f32; N]) -> [f32; N] {
    for ((v, m), s) in f.iter_mut().zip(mean).zip(std) {
        *v = (*v - m) / s;
    }
    f
}

/// Normalizes without overflow: a finite vector with components near f32::MAX
/// has an infinite squared length, and plain `normalize` would turn it into
/// zero. Scaling by the largest component first keeps it a unit vector.
pub(crate) fn safe_normalize(v: Vec3) -> Option<Vec3> {
    if !v.is_finite() {
        return None;
    }
    let m = v.abs().max_element();
    // `v` is finite here, so these comparisons see no NaN.
    if m <= 0.0 {
        return None;
    }
    let s = v / m;
    if m * s.length() <= 1e-6 {
        return None;
    }
    Some(s.normalize())
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #[test]
        fn encode_decode_round_trips(
            th in 0.0f32..1.0, ph in 0.0f32..std::f32::consts::TAU, t in 0.0f32..=1.0, r in 0.0f32..100.0, b in 0u32..50
        ) {
            let p = Vec3::new(th.sin() * ph.cos(), th.sin() * ph.sin(), th.cos());
            let d = (p + Vec3::new(0.1, 0.2, 0.3)).normalize();
            prop_assume!(d.dot(p) > 0.0);
            let e = Exit { position: p, direction: d, throughput: Vec3::splat(t), radiance: Vec3::new(r, 0.0, r * 0.5), bounces: b };
            let tr = ExitTransform { mean: [0.1; EXIT_FEATURES], std: [0.7; EXIT_FEATURES] };
            let mut rep = DecodeRepairs::default();
            let bounds = ExitBounds::new(false, 100.0);
            let back = tr.decode(&tr.encode(&e), 1000, bounds, &mut rep);
            prop_assert_eq!(rep, DecodeRepairs::default());
            prop_assert!(back.position.distance(p) < 1e-4);
            prop_assert!(back.direction.distance(d) < 1e-4);
            prop_assert!((back.throughput - e.throughput).abs().max_element() < 1e-4 * (1.0 + t));
            prop_assert!((back.radiance - e.radiance).abs().max_element() < 1e-4 * (1.0 + r));
            prop_assert_eq!(back.bounces, b);
        }

        #[test]
        fn decode_never_returns_invalid(f in proptest::array::uniform13(prop_oneof![-1e30f32..1e30, Just(f32::NAN), Just(f32::INFINITY), Just(0.0f32)])) {
            let tr = ExitTransform::default();
            let mut rep = DecodeRepairs::default();
            let e = tr.decode(&f, 64, ExitBounds::new(false, 100.0), &mut rep);
            prop_assert!((e.position.length() - 1.0).abs() < 1e-4);
            prop_assert!((e.direction.length() - 1.0).abs() < 1e-4);
            prop_assert!(e.direction.dot(e.position) >= -1e-4);
            prop_assert!(e.throughput.is_finite() && e.throughput.min_element() >= 0.0);
            prop_assert!(e.throughput.max_element() <= 1.0);
            prop_assert!(e.radiance.is_finite() && e.radiance.min_element() >= 0.0);
            prop_assert!(e.radiance.max_element() <= 100.0);
            prop_assert!(e.bounces <= 64);
            prop_assert!(rep.degenerate + rep.inward <= 1 && rep.clamped <= 1, "{:?}", rep);
        }
    }

    #[test]
    fn throughput_above_one_is_clamped_and_counted() {
        let tr = ExitTransform::default();
        let e = Exit { position: Vec3::Z, direction: Vec3::Z, throughput: Vec3::new(5.0, 0.5, 1.0), radiance: Vec3::ZERO, bounces: 1 };
        let mut rep = DecodeRepairs::default();
        let back = tr.decode(&tr.encode(&e), 8, ExitBounds::SURFACE, &mut rep);
        assert_eq!(rep.clamped, 1);
        assert!((back.throughput - Vec3::new(1.0, 0.5, 1.0)).abs().max_element() < 1e-5);
        // A translucent object's exits may carry up to 3 per channel.
        let mut rep = DecodeRepairs::default();
        let e = Exit { throughput: Vec3::new(2.5, 0.5, 1.2), ..e };
        let back = tr.decode(&tr.encode(&e), 8, ExitBounds::new(true, 0.0), &mut rep);
        assert_eq!(rep.clamped, 0);
        assert!((back.throughput - e.throughput).abs().max_element() < 1e-5);
        let e = Exit { throughput: Vec3::new(5.0, 0.5, 1.0), ..e };
        let back = tr.decode(&tr.encode(&e), 8, ExitBounds::new(true, 0.0), &mut rep);
        assert_eq!(rep.clamped, 1);
        assert!((back.throughput.x - EXIT_THROUGHPUT_BOUND_MEDIUM).abs() < 1e-5);
    }

    /// A forged decoder's radiance (found by an adversarial pass: biases that
    /// decode to e^80 rendered pixels of 1e34 with no repair reported).
    #[test]
    fn radiance_of_a_non_emitter_is_zeroed_and_counted() {
        let tr = ExitTransform::default();
        let mut f = [0.0f32; EXIT_FEATURES];
        f[2] = 1.0;
        f[5] = 1.0;
        f[9..12].copy_from_slice(&[80.0, 80.0, 80.0]);
        let mut rep = DecodeRepairs::default();
        let e = tr.decode(&f, 8, ExitBounds::SURFACE, &mut rep);
        assert_eq!(e.radiance, Vec3::ZERO);
        assert_eq!(rep, DecodeRepairs { clamped: 1, ..Default::default() });
        // An emitter's exits keep up to its radiance.
        let mut rep = DecodeRepairs::default();
        let e = tr.decode(&f, 8, ExitBounds::new(false, 17.0), &mut rep);
        assert_eq!(e.radiance, Vec3::splat(17.0));
        assert_eq!(rep.clamped, 1);
        f[9..12].copy_from_slice(&[2.0f32.ln_1p(), 0.0, 1e-6]);
        let mut rep = DecodeRepairs::default();
        let e = tr.decode(&f, 8, ExitBounds::new(false, 17.0), &mut rep);
        assert!((e.radiance - Vec3::new(2.0, 0.0, 1e-6)).abs().max_element() < 1e-5);
        assert_eq!(rep, DecodeRepairs::default());
        // A trained non-emitter's decoder returns rounding, not a repair,
        // on either side of 0.
        let e = tr.decode(&f.map(|x| x.min(1e-5)), 8, ExitBounds::SURFACE, &mut rep);
        assert_eq!((e.radiance, rep.clamped), (Vec3::ZERO, 0));
        f[9..12].copy_from_slice(&[(-4e-6f32).ln_1p(), (-1e-4f32).ln_1p(), 0.0]);
        let e = tr.decode(&f, 8, ExitBounds::SURFACE, &mut rep);
        assert_eq!((e.radiance, rep.clamped), (Vec3::ZERO, 0));
        // Well below 0 is a broken decoder.
        f[9] = (-0.5f32).ln_1p();
        let e = tr.decode(&f, 8, ExitBounds::SURFACE, &mut rep);
        assert_eq!((e.radiance, rep.clamped), (Vec3::ZERO, 1));
    }
}
