//! Warps from the unit square to the domains the integrator samples, with
//! their densities.

use glam::{Vec2, Vec3};
use std::f32::consts::{FRAC_1_PI, PI, TAU};

/// Cosine-weighted hemisphere around +z (Malley's method over a concentric disk).
pub fn cosine_hemisphere(u: Vec2) -> Vec3 {
    let d = concentric_disk(u);
    let z = (1.0 - d.length_squared()).max(0.0).sqrt();
    Vec3::new(d.x, d.y, z)
}

pub fn cosine_hemisphere_pdf(cos_theta: f32) -> f32 {
    cos_theta.max(0.0) * FRAC_1_PI
}

/// Shirley-Chiu concentric map: area preserving, low distortion.
pub fn concentric_disk(u: Vec2) -> Vec2 {
    let o = u * 2.0 - Vec2::ONE;
    if o.x == 0.0 && o.y == 0.0 {
        return Vec2::ZERO;
    }
    let (r, theta) = if o.x.abs() > o.y.abs() {
        (o.x, (PI / 4.0) * (o.y / o.x))
    } else {
        (o.y, PI / 2.0 - (PI / 4.0) * (o.x / o.y))
    };
    Vec2::new(r * theta.cos(), r * theta.sin())
}

/// Uniform direction on the unit sphere.
pub fn uniform_sphere(u: Vec2) -> Vec3 {
    let z = 1.0 - 2.0 * u.x;
    let r = (1.0 - z * z).max(0.0).sqrt();
    let phi = TAU * u.y;
    Vec3::new(r * phi.cos(), r * phi.sin(), z)
}

pub const UNIFORM_SPHERE_PDF: f32 = 1.0 / (4.0 * PI);

/// Uniform barycentrics on a triangle (Heitz's low-distortion square-to-triangle map).
pub fn uniform_triangle(u: Vec2) -> (f32, f32) {
    let (mut b0, mut b1);
    if u.x < u.y {
        b0 = u.x / 2.0;
        b1 = u.y - b0;
    } else {
        b1 = u.y / 2.0;
        b0 = u.x - b1;
    }
    b0 = b0.clamp(0.0, 1.0);
    b1 = b1.clamp(0.0, 1.0 - b0);
    (b0, b1)
}

/// The balance heuristic would also serve; the power heuristic (beta = 2) is
/// what pbrt and Mitsuba use and gives lower variance on glossy lobes.
#[inline]
pub fn power_heuristic(pdf_a: f32, pdf_b: f32) -> f32 {
    let a = pdf_a * pdf_a;
    let b = pdf_b * pdf_b;
    if a.is_infinite() {
        return 1.0;
    }
    if a + b <= 0.0 { 0.0 } else { a / (a + b) }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #[test]
        fn warps_stay_in_their_domains(x in 0.0f32..1.0, y in 0.0f32..1.0) {
            let d = cosine_hemisphere(Vec2::new(x, y));
            prop_assert!((d.length() - 1.0).abs() < 1e-4 && d.z >= 0.0);
            let s = uniform_sphere(Vec2::new(x, y));
            prop_assert!((s.length() - 1.0).abs() < 1e-4);
            let (b0, b1) = uniform_triangle(Vec2::new(x, y));
            prop_assert!(b0 >= 0.0 && b1 >= 0.0 && b0 + b1 <= 1.0 + 1e-6);
        }

        #[test]
        fn mis_weights_sum_to_one(a in 1e-6f32..1e6, b in 1e-6f32..1e6) {
            let s = power_heuristic(a, b) + power_heuristic(b, a);
            prop_assert!((s - 1.0).abs() < 1e-5);
        }
    }

    #[test]
    fn cosine_hemisphere_mean_cos_is_two_thirds() {
        // E[cos] under p = cos/pi is 2/3.
        let mut r = crate::SampleRng::from_seed(3);
        let n = 100_000;
        let m: f64 = (0..n)
            .map(|_| cosine_hemisphere(r.uniform2()).z as f64)
            .sum::<f64>()
            / n as f64;
        assert!((m - 2.0 / 3.0).abs() < 0.005, "{m}");
    }
}
