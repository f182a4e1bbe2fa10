//! Area lights for next-event estimation: every triangle of every emitter
//! instance, in world space, chosen with probability proportional to its
//! power (area times luminance of its radiance).

use glam::{Vec2, Vec3};
use nppp_geom::{luminance_f64, sampling::uniform_triangle};

#[derive(Clone, Copy, Debug)]
pub struct LightTriangle {
    pub v0: Vec3,
    pub e1: Vec3,
    pub e2: Vec3,
    /// Unit front-side normal (the side that emits).
    pub normal: Vec3,
    pub area: f32,
    pub radiance: Vec3,
    /// Its instance's ray offset floor (`RenderScene::offset_floor`), for
    /// ending shadow rays short of the light.
    pub offset_floor: f32,
}

/// A point sampled on a light, with the solid-angle pdf seen from the shading point.
#[derive(Clone, Copy, Debug)]
pub struct LightSample {
    pub point: Vec3,
    pub wi: Vec3,
    pub dist: f32,
    pub radiance: Vec3,
    pub pdf: f32,
    pub offset_floor: f32,
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
            // In f64: a 1e38 lamp's power overflows f32, and an infinite
            // weight below would silently drop the light from NEE.
            let w = t.area as f64 * luminance_f64(t.radiance);
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
            .map(|i| match lights.select_pdf(i) / lights.triangles[i].area {
                // A zero-area or zero-power triangle is never chosen.
                p if p.is_finite() => p,
                _ => 0.0,
            })
            .collect();
        lights
    }

    pub fn is_empty(&self) -> bool {
        self.total <= 0.0
    }

    /// Probability of choosing triangle `i`.
    #[inline]
    pub fn select_pdf(&self, i: usize) -> f32 {
        // Emitters whose radiance is all zero give no light to choose.
        if self.total <= 0.0 {
            return 0.0;
        }
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

    /// The triangle a light sample with selection number `u_select` takes
    /// (the lights must not be empty).
    #[inline]
    pub fn pick(&self, u_select: f32) -> usize {
        let target = u_select as f64 * self.total;
        crate::prefix::partition_point(&self.cdf, |&c| c <= target).min(self.triangles.len() - 1)
    }

    /// [`Self::pdf_solid_angle`]'s constant part for triangle `i`: its
    /// selection probability over its area.
    #[inline]
    pub fn pdf_area(&self, i: usize) -> f32 {
        self.pdf_area[i]
    }

    /// Samples a point on a light as seen from `p`; `None` if the point is on
    /// the light's back side or degenerate.
    #[inline]
    pub fn sample(&self, p: Vec3, u_select: f32, u: Vec2) -> Option<LightSample> {
        if self.is_empty() {
            return None;
        }
        let i = self.pick(u_select);
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
            offset_floor: t.offset_floor,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tri(scale: f32, radiance: f32) -> LightTriangle {
        LightTriangle {
            v0: Vec3::ZERO,
            e1: Vec3::X * scale,
            e2: Vec3::Z * scale,
            normal: Vec3::NEG_Y,
            area: 0.5 * scale * scale,
            radiance: Vec3::splat(radiance),
            offset_floor: 1e-7,
        }
    }

    #[test]
    fn a_lamp_whose_power_overflows_f32_is_still_sampled() {
        // area 5e3 x luminance 1e38 is past f32::MAX.
        let l = Lights::new(vec![tri(100.0, 1e38), tri(1.0, 1.0)]);
        assert!(!l.is_empty());
        assert!(l.select_pdf(0) > 0.99);
        let s = l.sample(Vec3::new(0.2, -1.0, 0.2), 0.5, Vec2::new(0.3, 0.3));
        assert!(s.is_some_and(|s| s.pdf.is_finite() && s.pdf > 0.0));
    }

    #[test]
    fn dark_emitters_give_no_light_and_no_nan() {
        let l = Lights::new(vec![tri(1.0, 0.0), tri(2.0, 0.0)]);
        assert!(l.is_empty());
        for i in 0..2 {
            assert_eq!(l.select_pdf(i), 0.0);
            assert_eq!(l.pdf_solid_angle(i, 3.0, 0.5), 0.0);
        }
        assert!(l.sample(Vec3::NEG_Y, 0.5, Vec2::splat(0.5)).is_none());
    }
}
