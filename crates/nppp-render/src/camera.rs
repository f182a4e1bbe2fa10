//! The pinhole camera of docs/scene-format.md.

use glam::{Vec2, Vec3};
use nppp_geom::SampleRng;
use nppp_scene::Camera as CameraDesc;

/// Precomputed camera basis; `ray` maps a film position (in pixels, row 0 at
/// the top) to a world-space ray.
#[derive(Clone, Copy, Debug)]
pub struct PinholeCamera {
    pub origin: Vec3,
    forward: Vec3,
    right: Vec3,
    up: Vec3,
    tan_half_fov: f32,
    aspect: f32,
    pub width: u32,
    pub height: u32,
}

impl PinholeCamera {
    pub fn new(c: &CameraDesc) -> Self {
        let forward = (c.look_at - c.position).normalize();
        let right = forward.cross(c.up).normalize();
        let up = right.cross(forward);
        Self {
            origin: c.position,
            forward,
            right,
            up,
            tan_half_fov: (c.fov_y_deg.to_radians() * 0.5).tan(),
            aspect: c.width as f32 / c.height as f32,
            width: c.width,
            height: c.height,
        }
    }

    /// The same view at `scale` times the resolution (at least 1 x 1; the
    /// aspect ratio of the field of view is kept as it was).
    pub fn scaled(&self, scale: f64) -> Self {
        let side = |x: u32| ((x as f64 * scale).round().max(1.0) as u32).min(x.max(1));
        Self {
            width: side(self.width),
            height: side(self.height),
            ..*self
        }
    }

    /// The primary ray through film position `p` = (column, row) in pixels,
    /// continuous: pixel (i, j) covers [i, i+1) x [j, j+1).
    #[inline]
    pub fn ray_dir(&self, p: Vec2) -> Vec3 {
        let x = (2.0 * p.x / self.width as f32 - 1.0) * self.tan_half_fov * self.aspect;
        let y = (1.0 - 2.0 * p.y / self.height as f32) * self.tan_half_fov;
        (self.forward + self.right * x + self.up * y).normalize()
    }
}

/// The film position of a camera sample: uniform inside pixel (x, y), from
/// the sample's own random stream (its first two numbers).
#[inline]
pub fn jitter(rng: &mut SampleRng, x: u32, y: u32) -> Vec2 {
    let u = rng.uniform2();
    Vec2::new(x as f32 + u.x, y as f32 + u.y)
}
