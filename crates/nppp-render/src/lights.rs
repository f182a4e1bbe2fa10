//! Area lights for next-event estimation: every triangle of every emitter
//! instance, in world space, chosen with probability proportional to its
//! power (area times luminance of its radiance).

use glam::{Vec2, Vec3};
use nppp_geom::{luminance, sampling::uniform_triangle};

#[derive(Clone, Copy, Debug)]
pub struct LightTriangle {
    pub v0: Vec3,
    pub e1: Vec3,
    pub e2: Vec3,
    /// Unit front-side normal (the side that emits).
    pub normal: Vec3,
    pub area: f32,
    pub radiance: Vec3,
}

/// A point sampled on a light, with the solid-angle pdf seen from the shading point.
#[derive(Clone, Copy, Debug)]
pub struct LightSample {
    pub point: Vec3,
    pub wi: Vec3,
    pub dist: f32,
    pub radiance: Vec3,
    pub pdf: f32,
}

#[derive(Default)]
pub struct Lights {
    pub triangles: Vec<LightTriangle>,
    /// Inclusive prefix sums of the selection weights.
    cdf: Vec<f64>,
    total: f64,
    /// Per triangle: selection probability over area, the constant part of
    /// its solid-angle pdf (precomputed: two f64 divisions per NEE sample
    /// and per emitter hit otherwise).
    pdf_area: Vec<f32>,
}

impl Lights {
    pub fn new(triangles: Vec<LightTriangle>) -> Self {
        let mut cdf = Vec::with_capacity(triangles.len());
        let mut total = 0.0f64;
        for t in &triangles {
            let w = (t.area * luminance(t.radiance)) as f64;
            total += if w.is_finite() && w > 0.0 { w } else { 0.0 };
            cdf.push(total);
        }
        let mut lights = Self {
            triangles,
            cdf,
            total,
            pdf_area: vec![],
        };
        lights.pdf_area = (0..lights.triangles.len())
            .map(|i| lights.select_pdf(i) / lights.triangles[i].area)
            .collect();
        lights
    }

    pub fn is_empty(&self) -> bool {
        self.total <= 0.0
    }

    /// Probability of choosing triangle `i`.
    #[inline]
    pub fn select_pdf(&self, i: usize) -> f32 {
        let prev = if i == 0 { 0.0 } else { self.cdf[i - 1] };
        ((self.cdf[i] - prev) / self.total) as f32
    }

    /// Solid-angle pdf of reaching light triangle `i` at distance `dist` with
    /// cosine `cos_light` at the light (as BSDF sampling would have found it).
    #[inline]
    pub fn pdf_solid_angle(&self, i: usize, dist: f32, cos_light: f32) -> f32 {
        if cos_light <= 0.0 {
            return 0.0;
        }
        self.pdf_area[i] * dist * dist / cos_light
    }

    /// Samples a point on a light as seen from `p`; `None` if the point is on
    /// the light's back side or degenerate.
    pub fn sample(&self, p: Vec3, u_select: f32, u: Vec2) -> Option<LightSample> {
        if self.is_empty() {
            return None;
        }
        let target = u_select as f64 * self.total;
        let i = self
            .cdf
            .partition_point(|&c| c <= target)
            .min(self.triangles.len() - 1);
        let t = &self.triangles[i];
        let (b1, b2) = uniform_triangle(u);
        let point = t.v0 + t.e1 * b1 + t.e2 * b2;
        let d = point - p;
        let dist2 = d.length_squared();
        if dist2.is_nan() || dist2 <= 0.0 {
            return None;
        }
        let dist = dist2.sqrt();
        let wi = d / dist;
        let cos_light = -wi.dot(t.normal);
        let pdf = self.pdf_solid_angle(i, dist, cos_light);
        if pdf.is_nan() || pdf <= 0.0 || !pdf.is_finite() {
            return None;
        }
        Some(LightSample {
            point,
            wi,
            dist,
            radiance: t.radiance,
            pdf,
        })
    }
}
