//! Math shared by every stage of nppp: rays, orthonormal frames, sampling
//! routines, per-sample random streams and the sphere-pair parameterization
//! of rays that the estimator is indexed by.
//!
//! Everything here is plain data and pure functions so that the renderer,
//! the data generator and the estimator runtime agree bit for bit.

pub mod atan2;
pub mod frame;
pub mod rng;
pub mod sampling;
pub mod sphere_pair;
pub mod ziggurat;

pub use frame::Frame;
pub use glam::{Vec2, Vec3};
pub use rng::SampleRng;
pub use sphere_pair::{BoundingSphere, SpherePair};

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

/// Luminance (Rec. 709 weights), used for Russian roulette and statistics.
pub fn luminance(c: Vec3) -> f32 {
    0.2126 * c.x + 0.7152 * c.y + 0.0722 * c.z
}

/// [`luminance`] in f64, for sums that must not overflow (a light's power,
/// area times luminance, passes f32::MAX for a 1e38 lamp).
pub fn luminance_f64(c: Vec3) -> f64 {
    0.2126 * c.x as f64 + 0.7152 * c.y as f64 + 0.0722 * c.z as f64
}
