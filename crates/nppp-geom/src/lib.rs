//! Math shared by every stage of nppp: rays, orthonormal frames, sampling
//! routines, per-sample random streams, the sphere-pair parameterization
//! of rays that the estimator is indexed by, and the closest point of a
//! triangle.
//!
//! Everything here is plain data and pure functions so that the renderer,
//! the data generator and the estimator runtime agree bit for bit.

pub mod atan2;
pub mod closest_point;
pub mod frame;
pub mod rng;
pub mod sampling;
pub mod sphere_pair;
pub mod ziggurat;

pub use frame::Frame;
pub use glam::{Vec2, Vec3};
pub use rng::SampleRng;
pub use sphere_pair::{BoundingSphere, SpherePair};

/// One step between 32-bit floats near `x`: the spacing at the power of
/// two at or below `|x|` (0 for 0). What a coordinate of that size can
/// resolve: the scene loader's size rules and the BVH builder's tie
/// breaking measure in it.
pub fn float_step(x: f32) -> f32 {
    f32::from_bits(x.abs().to_bits() & 0x7f80_0000) * f32::EPSILON
}

/// A ray with an origin and a unit direction.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ray {
    pub origin: Vec3,
    pub dir: Vec3,
}

impl Ray {
    pub fn new(origin: Vec3, dir: Vec3) -> Self {
        Self { origin, dir }
    }

    pub fn at(&self, t: f32) -> Vec3 {
        self.origin + self.dir * t
    }
}

/// `n` scaled to unit length, or zero for a zero or non-finite vector: a
/// triangle's normal from its edges' cross product. `Vec3::normalize_or_zero`
/// alone returns zero where the squared length overflows f32 (edges longer
/// than about 4e9, which the scene loader accepts: such a quad rendered
/// black) and a vector off unit length where it is subnormal; those are
/// rescaled by their largest component first.
#[inline]
pub fn unit_normal(n: Vec3) -> Vec3 {
    let l2 = n.length_squared();
    if l2.is_normal() {
        // What `normalize_or_zero` computes, bit for bit.
        return n * l2.sqrt().recip();
    }
    let m = n.abs().max_element();
    if m > 0.0 && n.is_finite() {
        let s = n / m;
        s * s.length_squared().sqrt().recip()
    } else {
        Vec3::ZERO
    }
}

/// Luminance (Rec. 709 weights), used for Russian roulette and statistics.
pub fn luminance(c: Vec3) -> f32 {
    0.2126 * c.x + 0.7152 * c.y + 0.0722 * c.z
}

/// [`luminance`] in f64, for sums that must not overflow (a light's power,
/// area times luminance, passes f32::MAX for a 1e38 lamp).
pub fn luminance_f64(c: Vec3) -> f64 {
    0.2126 * c.x as f64 + 0.7152 * c.y as f64 + 0.0722 * c.z as f64
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        /// Unit length and the same direction at every scale a scene can
        /// make, the f32 squared length's overflow and underflow included.
        #[test]
        fn unit_normal_is_unit_at_any_scale(x in -1.0f32..1.0, y in -1.0f32..1.0, z in -1.0f32..1.0, e in -30i32..30) {
            let n = Vec3::new(x, y, z);
            prop_assume!(n.length() > 1e-3);
            let u = unit_normal(n * 10f32.powi(e));
            prop_assert!((u.length() - 1.0).abs() < 1e-5, "{u}");
            prop_assert!(u.dot(n.normalize()) > 1.0 - 1e-5);
        }
    }

    #[test]
    fn unit_normal_of_nothing_is_zero() {
        assert_eq!(unit_normal(Vec3::ZERO), Vec3::ZERO);
        assert_eq!(unit_normal(Vec3::new(f32::NAN, 1.0, 0.0)), Vec3::ZERO);
        assert_eq!(unit_normal(Vec3::new(f32::INFINITY, 1.0, 0.0)), Vec3::ZERO);
    }
}
