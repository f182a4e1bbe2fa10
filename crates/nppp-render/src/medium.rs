//! Homogeneous participating media (the inside of a `translucent` object):
//! free-flight distance sampling and the Henyey-Greenstein phase function.
//!
//! Chromatic media (a different extinction per channel) are sampled with
//! spectral MIS over a whole path (the hero scheme of pbrt-v4's
//! `VolPathIntegrator`, after Wilkie et al. 2014 and Miller, Georgiev and
//! Jarosz 2019): one channel, the hero, is picked when the path first
//! enters a medium and drives every free flight of the path, in that
//! medium and in any it enters later; each channel's contribution is then
//! divided by the average of the three channels' pdfs of all the path's
//! free flights, not by the hero's alone. Per channel the MIS weight is
//! bounded by three times the albedo product (Russian roulette's
//! reweighting comes on top), where using the hero's pdf
//! alone (Mitsuba's `volpath`) or mixing per event has unbounded weights: a
//! dense channel's long random walks are sampled rarely, with huge weights,
//! and a finite render underestimates it (2.26 and 1.67 instead of 2 in the
//! furnace test with per-event mixing). The bound holds for the path, not
//! per visit: with a hero picked at every entry, the factor of up to three
//! compounded over visits, and in a room of 2,025 jade knots under a
//! skylight a path that went through half a dozen knots carried 67,000
//! times the light in one channel (a 64-spp pixel of 1,200 where its
//! neighbours had 0.5). An object walk (data generation, the oracle) keeps
//! one hero for the walk likewise.

use glam::{Vec2, Vec3};
use nppp_geom::Frame;
use nppp_scene::Material;
use std::f32::consts::PI;

/// A homogeneous medium: coefficients per unit length in the frame it is
/// used in (mesh space in object walks, world space in the renderer).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Medium {
    pub sigma_s: Vec3,
    /// Extinction, sigma_s + sigma_a.
    pub sigma_t: Vec3,
    /// Henyey-Greenstein mean cosine, |g| < 1.
    pub g: f32,
}

/// What a free-flight sample decided for a segment of length `t_max`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FreeFlight {
    /// Distance along the ray: of the scattering event, or `t_max`.
    pub t: f32,
    /// Whether a real scattering event happens at `t` (before `t_max`).
    pub scattered: bool,
    /// The event's contribution: sigma_s Tr(t) for a scattering event,
    /// Tr(t_max) otherwise.
    pub f: Vec3,
    /// Each channel's pdf of the same event: sigma_t Tr(t) for a
    /// scattering event, Tr(t_max) (no event before the surface) otherwise.
    pub pdf: Vec3,
}

/// The spectral MIS state of a path that has entered a medium: its hero
/// channel and, per channel, the pdf of its free flights so far, up to a common
/// factor (kept so that the largest is 1: only ratios matter, and a long
/// visit would otherwise overflow f32).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HeroChannel {
    pub channel: u8,
    pub pdf_ratio: Vec3,
}

impl HeroChannel {
    /// A path's first entry into a medium; `u` picks the channel uniformly.
    #[inline]
    pub fn pick(u: f32) -> Self {
        Self {
            channel: ((u * 3.0) as u8).min(2),
            pdf_ratio: Vec3::ONE,
        }
    }

    /// Folds a free flight into a throughput that already carries the
    /// path's MIS weight: the throughput stays f / mean(p) over the path's
    /// free flights (the hero's pdf cancels, so nothing is divided by it).
    #[inline]
    pub fn apply(&mut self, beta: &mut Vec3, flight: &FreeFlight) {
        let joint = self.pdf_ratio * flight.pdf;
        let (sum, max) = (joint.element_sum(), joint.max_element());
        if !(sum > 0.0 && sum.is_finite()) {
            *beta = Vec3::ZERO;
            return;
        }
        *beta *= flight.f * (self.pdf_ratio.element_sum() / sum);
        self.pdf_ratio = joint / max;
    }
}

impl Medium {
    /// The medium inside a material's boundary (translucent objects), in
    /// the mesh's own units.
    pub fn of(m: &Material) -> Option<Medium> {
        match *m {
            Material::Translucent {
                sigma_s,
                sigma_a,
                g,
                ..
            } => Some(Medium::new(sigma_s, sigma_a, g)),
            _ => None,
        }
    }

    pub fn new(sigma_s: Vec3, sigma_a: Vec3, g: f32) -> Self {
        Self {
            sigma_s,
            sigma_t: sigma_s + sigma_a,
            g,
        }
    }

    /// The medium of an object scaled by `scale` (uniform), in the scaled
    /// frame: lengths grow by `scale`, so coefficients shrink by it.
    pub fn scaled(&self, scale: f32) -> Self {
        Self {
            sigma_s: self.sigma_s / scale,
            sigma_t: self.sigma_t / scale,
            g: self.g,
        }
    }

    /// Transmittance over a distance `t` (infinite: 0, or 1 in a channel
    /// without extinction).
    #[inline]
    pub fn transmittance(&self, t: f32) -> Vec3 {
        let tr = |s: f32| if s > 0.0 { (-s * t).exp() } else { 1.0 };
        Vec3::new(tr(self.sigma_t.x), tr(self.sigma_t.y), tr(self.sigma_t.z))
    }

    /// Samples where along a segment of length `t_max` (may be infinite)
    /// the next event happens, by the hero channel's extinction, with
    /// `u_dist` choosing the distance.
    #[inline]
    pub fn sample_free_flight(&self, t_max: f32, hero: u8, u_dist: f32) -> FreeFlight {
        let st = self.sigma_t[hero as usize];
        let t = if st > 0.0 {
            -(1.0 - u_dist).ln() / st
        } else {
            f32::INFINITY
        };
        let (t, scattered, f, pdf) = if t < t_max {
            let tr = self.transmittance(t);
            (t, true, self.sigma_s * tr, self.sigma_t * tr)
        } else {
            let tr = self.transmittance(t_max);
            (t_max, false, tr, tr)
        };
        FreeFlight {
            t,
            scattered,
            f,
            pdf,
        }
    }

    /// Samples the direction a path scattered at a medium point continues
    /// in, given the direction `d` it arrived travelling in. Returns the new
    /// direction and its solid-angle pdf; the weight (phase / pdf) is 1.
    #[inline]
    pub fn sample_phase(&self, d: Vec3, u: Vec2) -> (Vec3, f32) {
        let g = self.g;
        let cos = if g.abs() < 1e-3 {
            1.0 - 2.0 * u.x
        } else {
            let s = (1.0 - g * g) / (1.0 - g + 2.0 * g * u.x);
            ((1.0 + g * g - s * s) / (2.0 * g)).clamp(-1.0, 1.0)
        };
        let sin = (1.0 - cos * cos).max(0.0).sqrt();
        let phi = 2.0 * PI * u.y;
        let local = Vec3::new(sin * phi.cos(), sin * phi.sin(), cos);
        let wi = Frame::from_normal(d).to_world(local).normalize();
        (wi, hg_phase(cos, g))
    }
}

/// The Henyey-Greenstein phase function (per steradian) at the cosine
/// between the incoming and the outgoing propagation directions; g > 0
/// scatters forward.
#[inline]
pub fn hg_phase(cos: f32, g: f32) -> f32 {
    let denom = 1.0 + g * g - 2.0 * g * cos;
    (1.0 - g * g) / (4.0 * PI * denom * denom.max(0.0).sqrt())
}

#[cfg(test)]
mod tests {
    use super::*;
    use nppp_geom::SampleRng;
    use proptest::prelude::*;

    /// One channel's own estimate of an event (contribution over its pdf),
    /// without the visit's MIS weight.
    fn weight(f: &FreeFlight, channel: u8) -> Vec3 {
        let p = f.pdf[channel as usize];
        if p > 0.0 { f.f / p } else { Vec3::ZERO }
    }

    #[test]
    fn free_flight_weights_average_to_the_transmittance_and_scattering() {
        // E[weight over the "passed" outcomes] = Tr(t_max) and
        // E[weight * f(t) over scatter events] = int sigma_s Tr(t) f(t) dt.
        // One event per visit: the visit's MIS weight is the event's.
        let m = Medium::new(Vec3::new(0.5, 2.0, 4.0), Vec3::new(0.5, 0.0, 1.0), 0.0);
        let t_max = 0.7;
        let mut rng = SampleRng::new(3, 0, 0);
        let n = 400_000;
        let (mut passed, mut scattered) = (Vec3::ZERO, Vec3::ZERO);
        for _ in 0..n {
            let mut hero = HeroChannel::pick(rng.uniform());
            let f = m.sample_free_flight(t_max, hero.channel, rng.uniform());
            let mut beta = Vec3::ONE;
            hero.apply(&mut beta, &f);
            // Bounded: at most three times each channel's own estimate.
            for c in 0..3 {
                assert!(
                    beta[c] <= 3.0 * weight(&f, c as u8)[c] + 1e-4,
                    "{beta} {f:?}"
                );
            }
            if f.scattered {
                assert!(f.t < t_max);
                scattered += beta;
            } else {
                passed += beta;
            }
        }
        let passed = passed / n as f32;
        let scattered = scattered / n as f32;
        let tr = m.transmittance(t_max);
        // int_0^t_max sigma_s exp(-sigma_t t) dt = sigma_s / sigma_t (1 - Tr).
        let expect_s = m.sigma_s / m.sigma_t * (Vec3::ONE - tr);
        for c in 0..3 {
            assert!((passed[c] - tr[c]).abs() < 0.01, "passed {passed} vs {tr}");
            assert!(
                (scattered[c] - expect_s[c]).abs() < 0.01,
                "{scattered} vs {expect_s}"
            );
        }
    }

    #[test]
    fn a_medium_without_extinction_never_scatters() {
        let m = Medium::new(Vec3::ZERO, Vec3::ZERO, 0.3);
        let f = m.sample_free_flight(f32::INFINITY, 1, 0.999);
        assert!(!f.scattered);
        assert_eq!(weight(&f, 1), Vec3::ONE);
    }

    #[test]
    fn an_escaping_ray_in_a_medium_has_zero_weight_where_it_must_scatter() {
        let m = Medium::new(Vec3::ONE, Vec3::ZERO, 0.0);
        let f = m.sample_free_flight(f32::INFINITY, 1, 0.5);
        assert!(f.scattered && weight(&f, 1).is_finite());
    }

    #[test]
    fn hg_mean_cosine_is_g() {
        for g in [-0.7f32, -0.2, 0.0, 0.5, 0.9] {
            let m = Medium::new(Vec3::ONE, Vec3::ZERO, g);
            let d = Vec3::new(0.3, -0.5, 0.8).normalize();
            let mut rng = SampleRng::new(9, 1, 0);
            let n = 200_000;
            let mean: f64 = (0..n)
                .map(|_| m.sample_phase(d, rng.uniform2()).0.dot(d) as f64)
                .sum::<f64>()
                / n as f64;
            assert!((mean - g as f64).abs() < 0.01, "g {g}: mean cosine {mean}");
        }
    }

    proptest! {
        #[test]
        fn hg_is_normalized(g in -0.95f32..0.95) {
            // Integral over the sphere, midpoint rule in cos.
            let n = 20_000;
            let sum: f64 = (0..n)
                .map(|i| {
                    let cos = -1.0 + (i as f32 + 0.5) * 2.0 / n as f32;
                    hg_phase(cos, g) as f64
                })
                .sum::<f64>() * 2.0 / n as f64 * 2.0 * std::f64::consts::PI;
            prop_assert!((sum - 1.0).abs() < 2e-3, "g {}: {}", g, sum);
        }

        #[test]
        fn sampled_directions_are_unit_with_the_phase_as_pdf(
            g in -0.95f32..0.95, ux in 0.0f32..1.0, uy in 0.0f32..1.0,
            dx in -1.0f32..1.0, dy in -1.0f32..1.0, dz in -1.0f32..1.0,
        ) {
            let d = Vec3::new(dx, dy, dz);
            prop_assume!(d.length() > 0.1);
            let d = d.normalize();
            let (wi, pdf) = Medium::new(Vec3::ONE, Vec3::ZERO, g).sample_phase(d, Vec2::new(ux, uy));
            prop_assert!((wi.length() - 1.0).abs() < 1e-4);
            let expect = hg_phase(wi.dot(d).clamp(-1.0, 1.0), g);
            prop_assert!(pdf.is_finite() && pdf > 0.0);
            prop_assert!((pdf - expect).abs() <= 2e-2 * expect.max(1e-3), "{} vs {}", pdf, expect);
        }

        #[test]
        fn free_flight_weights_are_finite(
            s in prop::array::uniform3(0.0f32..1e4), a in prop::array::uniform3(0.0f32..1e4),
            t_max in 1e-6f32..1e3, uc in 0.0f32..1.0, ud in 0.0f32..1.0,
        ) {
            let m = Medium::new(Vec3::from(s), Vec3::from(a), 0.0);
            let mut hero = HeroChannel::pick(uc);
            let f = m.sample_free_flight(t_max, hero.channel, ud);
            prop_assert!(f.f.is_finite() && f.f.min_element() >= 0.0);
            prop_assert!(f.pdf.is_finite() && f.pdf.min_element() >= 0.0);
            prop_assert!(f.t <= t_max);
            let mut beta = Vec3::ONE;
            for _ in 0..50 {
                hero.apply(&mut beta, &f);
            }
            prop_assert!(beta.is_finite() && beta.min_element() >= 0.0);
        }
    }
}
