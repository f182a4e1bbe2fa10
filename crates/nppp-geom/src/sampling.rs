//! Warps from the unit square to the domains the integrator samples, with
//! their densities.

use glam::{Vec2, Vec3};
use std::f32::consts::{FRAC_1_PI, PI, TAU};

/// Cosine-weighted hemisphere around +z (Malley's method over a concentric disk).
///
/// `#[inline]` here and on the other per-bounce samplers: without it the
/// renderer (another crate, built without LTO) calls them out of line.
#[inline]
pub fn cosine_hemisphere(u: Vec2) -> Vec3 {
    let d = concentric_disk(u);
    let z = (1.0 - d.length_squared()).max(0.0).sqrt();
    Vec3::new(d.x, d.y, z)
}

#[inline]
pub fn cosine_hemisphere_pdf(cos_theta: f32) -> f32 {
    cos_theta.max(0.0) * FRAC_1_PI
}

/// Shirley-Chiu concentric map: area preserving, low distortion.
#[inline]
pub fn concentric_disk(u: Vec2) -> Vec2 {
    let o = u * 2.0 - Vec2::ONE;
    if o.x == 0.0 && o.y == 0.0 {
        return Vec2::ZERO;
    }
    // Both wedges need the sine and cosine of an angle in [-pi/4, pi/4]
    // (the second's pi/2 - phi swaps them). Written as selects around one
    // evaluation: the wedge is a coin flip per sample, and a branch on it
    // was mispredicted half the time.
    let x_wedge = o.x.abs() > o.y.abs();
    let (r, other) = if x_wedge { (o.x, o.y) } else { (o.y, o.x) };
    let (sin, cos) = sin_cos_quarter((PI / 4.0) * (other / r));
    let (along, across) = (r * cos, r * sin);
    if x_wedge {
        Vec2::new(along, across)
    } else {
        Vec2::new(across, along)
    }
}

/// `(sin x, cos x)` for `|x| <= pi/4`, by the minimax polynomials of
/// Cephes' `sinf`/`cosf` on that interval (within 2 ulp of the correctly
/// rounded values there). libm's `sincosf` reduces the argument first and
/// took 3% of a path-tracing render (perf), behind every diffuse bounce.
#[inline]
pub fn sin_cos_quarter(x: f32) -> (f32, f32) {
    let (s, c) = (QUARTER_SIN, QUARTER_COS);
    let z = x * x;
    let sin = x + x * z * (s[0] + z * (s[1] + z * s[2]));
    let cos = 1.0 - 0.5 * z + z * z * (c[0] + z * (c[1] + z * c[2]));
    (sin, cos)
}

/// [`sin_cos_quarter`]'s coefficients: sin x = x + x z (s0 + z (s1 + z s2)),
/// cos x = 1 - z / 2 + z^2 (c0 + z (c1 + z c2)), z = x^2 (the renderer's
/// SIMD lanes evaluate the same polynomials).
pub const QUARTER_SIN: [f32; 3] = [-1.666_665_5e-1, 8.332_161e-3, -1.951_529_6e-4];
/// See [`QUARTER_SIN`].
pub const QUARTER_COS: [f32; 3] = [4.166_664_6e-2, -1.388_731_6e-3, 2.443_315_7e-5];

/// Uniform direction on the unit sphere.
pub fn uniform_sphere(u: Vec2) -> Vec3 {
    let z = 1.0 - 2.0 * u.x;
    let r = (1.0 - z * z).max(0.0).sqrt();
    let phi = TAU * u.y;
    Vec3::new(r * phi.cos(), r * phi.sin(), z)
}

pub const UNIFORM_SPHERE_PDF: f32 = 1.0 / (4.0 * PI);

/// Uniform barycentrics on a triangle (Heitz's low-distortion square-to-triangle map).
#[inline]
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

        /// The polynomial sine and cosine agree with libm's on the quarter
        /// circle the concentric map uses.
        #[test]
        fn quarter_sin_cos_matches_libm(x in -std::f32::consts::FRAC_PI_4..=std::f32::consts::FRAC_PI_4) {
            let (s, c) = sin_cos_quarter(x);
            prop_assert!((s - x.sin()).abs() <= 2.5e-7, "sin {x}: {s} against {}", x.sin());
            prop_assert!((c - x.cos()).abs() <= 2.5e-7, "cos {x}: {c} against {}", x.cos());
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
