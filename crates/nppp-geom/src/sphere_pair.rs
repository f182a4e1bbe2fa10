//! The estimator's input parameterization.
//!
//! A ray crossing an object's bounding sphere is identified by the two points
//! where its line crosses the sphere (the chord's entry and exit). Each point
//! is mapped to (u, v) = ((1 + cos theta) / 2, phi / 2 pi) with theta measured
//! from +z and phi = atan2(y, x) in [0, 2 pi): an equal-area map, so a regular
//! grid in (u1, v1, u2, v2) gives cells of equal measure, and v wraps around.
//! All of this happens in the unit sphere's frame (centre 0, radius 1).

use crate::Ray;
use glam::{Vec2, Vec3};
use serde::{Deserialize, Serialize};
use std::f32::consts::TAU;

/// A bounding sphere in mesh space; maps mesh space to the unit sphere's frame.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct BoundingSphere {
    pub center: Vec3,
    pub radius: f32,
}

impl BoundingSphere {
    /// A tight sphere around `points` (Ritter's algorithm, then the exact
    /// farthest-point radius around its centre: within a few % of the
    /// minimal sphere), enlarged by
    /// `margin` (relative) so that no surface point lies on the sphere itself.
    pub fn around(points: &[Vec3], margin: f32) -> Self {
        if points.is_empty() {
            return Self {
                center: Vec3::ZERO,
                radius: 1.0,
            };
        }
        // Ritter: start from a near-diameter (the point farthest from an
        // arbitrary point, and the point farthest from that), then grow the
        // sphere to include any outlier.
        let far = |from: Vec3| {
            *points
                .iter()
                .max_by(|a, b| {
                    a.distance_squared(from)
                        .total_cmp(&b.distance_squared(from))
                })
                .unwrap_or(&from)
        };
        let y = far(points[0]);
        let z = far(y);
        let mut center = (y + z) * 0.5;
        let mut radius = 0.5 * y.distance(z);
        for p in points {
            let d = p.distance(center);
            if d > radius {
                let new_r = 0.5 * (radius + d);
                center += (*p - center) * ((new_r - radius) / d);
                radius = new_r;
            }
        }
        let exact = points
            .iter()
            .map(|p| p.distance(center))
            .fold(0.0f32, f32::max);
        let radius = exact.max(f32::MIN_POSITIVE) * (1.0 + margin);
        Self { center, radius }
    }

    pub fn to_unit_point(&self, p: Vec3) -> Vec3 {
        (p - self.center) / self.radius
    }

    pub fn from_unit_point(&self, p: Vec3) -> Vec3 {
        p * self.radius + self.center
    }
}

/// Where a ray's line crosses the unit sphere: `t_in <= t_out` along a unit direction.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Chord {
    pub t_in: f32,
    pub t_out: f32,
}

/// Intersects the line of a ray (unit direction) with the unit sphere at the
/// origin. Uses the numerically stable form (the chord's midpoint is computed
/// first) so grazing rays from far away keep their precision.
pub fn unit_sphere_chord(ray: &Ray) -> Option<Chord> {
    let b = ray.origin.dot(ray.dir);
    // Closest point of the line to the centre, then the half chord from it.
    let closest = ray.origin - ray.dir * b;
    let h2 = 1.0 - closest.length_squared();
    if h2.is_nan() || h2 < 0.0 {
        return None;
    }
    let h = h2.sqrt();
    Some(Chord {
        t_in: -b - h,
        t_out: -b + h,
    })
}

/// The 4D coordinates of a chord: (u1, v1) of the entry point, (u2, v2) of the exit point.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SpherePair(pub [f32; 4]);

/// (u, v) of a point on (or near) the unit sphere; the point is projected radially.
pub fn point_to_uv(p: Vec3) -> Vec2 {
    let len = p.length();
    let z = if len > 0.0 {
        (p.z / len).clamp(-1.0, 1.0)
    } else {
        1.0
    };
    let mut phi = crate::atan2::atan2(p.y, p.x);
    if phi < 0.0 {
        phi += TAU;
    }
    let v = phi / TAU;
    // atan2 may round to exactly 2 pi for tiny negative y.
    let v = if v >= 1.0 { 0.0 } else { v };
    Vec2::new(0.5 * (1.0 + z), v)
}

/// The point of the unit sphere with coordinates (u, v); v wraps, u is clamped.
pub fn uv_to_point(uv: Vec2) -> Vec3 {
    let z = (2.0 * uv.x - 1.0).clamp(-1.0, 1.0);
    let r = (1.0 - z * z).max(0.0).sqrt();
    let phi = TAU * uv.y;
    Vec3::new(r * phi.cos(), r * phi.sin(), z)
}

impl SpherePair {
    /// The chord of a ray (unit-sphere frame) or `None` if its line misses the sphere.
    pub fn from_ray(ray: &Ray) -> Option<(Self, Chord)> {
        let chord = unit_sphere_chord(ray)?;
        let a = point_to_uv(ray.at(chord.t_in));
        let b = point_to_uv(ray.at(chord.t_out));
        Some((Self([a.x, a.y, b.x, b.y]), chord))
    }

    pub fn from_points(entry: Vec3, exit: Vec3) -> Self {
        let a = point_to_uv(entry);
        let b = point_to_uv(exit);
        Self([a.x, a.y, b.x, b.y])
    }

    pub fn entry(&self) -> Vec3 {
        uv_to_point(Vec2::new(self.0[0], self.0[1]))
    }

    pub fn exit(&self) -> Vec3 {
        uv_to_point(Vec2::new(self.0[2], self.0[3]))
    }

    /// The ray from the entry point towards the exit point, or `None` when the
    /// two coincide (a tangent chord has no direction).
    pub fn to_ray(&self) -> Option<Ray> {
        let a = self.entry();
        let b = self.exit();
        let d = b - a;
        let len = d.length();
        if len.is_nan() || len <= 1e-6 {
            return None;
        }
        Some(Ray::new(a, d / len))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sampling::uniform_sphere;
    use proptest::prelude::*;

    proptest! {
        #[test]
        fn uv_round_trips(u in 0.001f32..0.999, v in 0.0f32..1.0) {
            let p = uv_to_point(Vec2::new(u, v));
            prop_assert!((p.length() - 1.0).abs() < 1e-5);
            let back = point_to_uv(p);
            prop_assert!((back.x - u).abs() < 1e-4);
            let dv = (back.y - v).abs();
            prop_assert!(dv.min(1.0 - dv) < 1e-4, "v {v} -> {}", back.y);
        }

        #[test]
        fn ray_round_trips_through_4d(a in 0.0f32..1.0, b in 0.0f32..1.0, c in 0.0f32..1.0, d in 0.0f32..1.0, back in 0.5f32..20.0) {
            let p1 = uniform_sphere(Vec2::new(a, b));
            let p2 = uniform_sphere(Vec2::new(c, d));
            prop_assume!(p1.distance(p2) > 1e-2);
            let dir = (p2 - p1).normalize();
            let ray = Ray::new(p1 - dir * back, dir);
            let (pair, chord) = SpherePair::from_ray(&ray).unwrap();
            prop_assert!((chord.t_in - back).abs() < 1e-3 * back.max(1.0));
            let r2 = pair.to_ray().unwrap();
            prop_assert!(r2.origin.distance(p1) < 1e-3);
            prop_assert!(r2.dir.dot(dir) > 1.0 - 1e-4);
        }

        #[test]
        fn bounding_sphere_contains_points(pts in proptest::collection::vec((-100.0f32..100.0, -100.0f32..100.0, -100.0f32..100.0), 1..50)) {
            let pts: Vec<Vec3> = pts.into_iter().map(|(x, y, z)| Vec3::new(x, y, z)).collect();
            let s = BoundingSphere::around(&pts, 0.01);
            for p in &pts {
                prop_assert!(s.to_unit_point(*p).length() < 1.0);
            }
        }
    }

    #[test]
    fn bounding_sphere_of_a_sphere_is_tight() {
        let mut r = crate::SampleRng::from_seed(4);
        let pts: Vec<Vec3> = (0..2000)
            .map(|_| uniform_sphere(r.uniform2()) * 0.5 + Vec3::new(3.0, -1.0, 2.0))
            .collect();
        let s = BoundingSphere::around(&pts, 0.0);
        assert!(s.radius < 0.5 * 1.03, "radius {}", s.radius);
        assert!(s.center.distance(Vec3::new(3.0, -1.0, 2.0)) < 0.02);
    }

    #[test]
    fn missing_and_tangent_rays() {
        assert!(SpherePair::from_ray(&Ray::new(Vec3::new(0.0, 2.0, -5.0), Vec3::Z)).is_none());
        let (pair, chord) =
            SpherePair::from_ray(&Ray::new(Vec3::new(0.0, 1.0, -5.0), Vec3::Z)).unwrap();
        assert!((chord.t_in - chord.t_out).abs() < 1e-3);
        assert!(pair.0.iter().all(|x| x.is_finite()));
        // Poles: u = 0 and u = 1 exactly, any v.
        let p = point_to_uv(Vec3::Z);
        assert_eq!(p.x, 1.0);
        let q = point_to_uv(-Vec3::Z);
        assert_eq!(q.x, 0.0);
    }
}
