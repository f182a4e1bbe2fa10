//! Scattering functions in the local shading frame (normal = +z).
//!
//! `sample` returns the throughput weight f * |cos| / pdf directly, which is
//! what the integrator multiplies by; `eval` returns f * |cos| and the pdf of
//! sampling that direction, which next-event estimation and MIS need.

use glam::{Vec2, Vec3};
use nppp_geom::sampling::{cosine_hemisphere, cosine_hemisphere_pdf};
use std::f32::consts::{FRAC_1_PI, PI, TAU};

/// Roughness below this is treated as a perfect mirror: the GGX lobe is then
/// narrower than f32 can resolve and its pdf overflows.
pub const MIN_ALPHA: f32 = 1e-4;

/// A scattering material as the integrator sees it at one vertex.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Bsdf {
    Diffuse { albedo: Vec3 },
    Conductor { reflectance: Vec3, alpha: f32 },
    Dielectric { ior: f32 },
}

#[derive(Clone, Copy, Debug)]
pub struct BsdfSample {
    /// Local incident direction (towards the next vertex).
    pub wi: Vec3,
    /// f * |cos(wi)| / pdf.
    pub weight: Vec3,
    /// Solid-angle pdf; for delta lobes the discrete probability of the lobe.
    pub pdf: f32,
    pub delta: bool,
    /// Whether the sample crossed the surface (refraction): the integrator
    /// learns it here instead of guessing from the material or the sides.
    pub transmitted: bool,
}

impl Bsdf {
    /// Whether the lobe is a Dirac delta (no NEE, no MIS).
    pub fn is_delta(&self) -> bool {
        match *self {
            Bsdf::Diffuse { .. } => false,
            Bsdf::Conductor { alpha, .. } => alpha < MIN_ALPHA,
            Bsdf::Dielectric { .. } => true,
        }
    }

    /// Two-sided materials are evaluated with wo flipped into the upper hemisphere;
    /// the dielectric keeps the geometric side (outside = +z).
    pub fn two_sided(&self) -> bool {
        !matches!(self, Bsdf::Dielectric { .. })
    }

    /// `wo` must be in the upper hemisphere for two-sided materials.
    #[inline]
    pub fn sample(&self, wo: Vec3, u_lobe: f32, u: Vec2) -> Option<BsdfSample> {
        match *self {
            Bsdf::Diffuse { albedo } => {
                let wi = cosine_hemisphere(u);
                if wi.z <= 0.0 {
                    return None;
                }
                Some(BsdfSample {
                    wi,
                    weight: albedo,
                    pdf: cosine_hemisphere_pdf(wi.z),
                    delta: false,
                    transmitted: false,
                })
            }
            Bsdf::Conductor { reflectance, alpha } => {
                if wo.z <= 0.0 {
                    return None;
                }
                if alpha < MIN_ALPHA {
                    let wi = Vec3::new(-wo.x, -wo.y, wo.z);
                    return Some(BsdfSample {
                        wi,
                        weight: reflectance,
                        pdf: 1.0,
                        delta: true,
                        transmitted: false,
                    });
                }
                let m = ggx_sample_visible(wo, alpha, u);
                let wi = reflect(wo, m);
                if wi.z <= 0.0 {
                    return None;
                }
                let pdf = ggx_reflection_pdf(wo, wi, m, alpha);
                if pdf.is_nan() || pdf <= 0.0 || !pdf.is_finite() {
                    return None;
                }
                // f cos / pdf collapses to F * G1(wi) for visible-normal sampling.
                Some(BsdfSample {
                    wi,
                    weight: reflectance * smith_g1(wi, alpha),
                    pdf,
                    delta: false,
                    transmitted: false,
                })
            }
            Bsdf::Dielectric { ior } => {
                let f = fresnel_dielectric(wo.z, ior);
                if u_lobe < f {
                    let wi = Vec3::new(-wo.x, -wo.y, wo.z);
                    Some(BsdfSample {
                        wi,
                        weight: Vec3::ONE,
                        pdf: f,
                        delta: true,
                        transmitted: false,
                    })
                } else {
                    let entering = wo.z > 0.0;
                    let eta = if entering { ior } else { 1.0 / ior };
                    let wi = refract(wo, eta)?;
                    // Radiance is scaled by (eta_i / eta_t)^2 across the boundary.
                    let scale = 1.0 / (eta * eta);
                    Some(BsdfSample {
                        wi,
                        weight: Vec3::splat(scale),
                        pdf: 1.0 - f,
                        delta: true,
                        transmitted: true,
                    })
                }
            }
        }
    }

    /// f * |cos(wi)| and the pdf `sample` would give wi; zero for delta lobes.
    #[inline]
    pub fn eval(&self, wo: Vec3, wi: Vec3) -> (Vec3, f32) {
        match *self {
            Bsdf::Diffuse { albedo } => {
                if wo.z <= 0.0 || wi.z <= 0.0 {
                    return (Vec3::ZERO, 0.0);
                }
                (albedo * (FRAC_1_PI * wi.z), cosine_hemisphere_pdf(wi.z))
            }
            Bsdf::Conductor { reflectance, alpha } => {
                if alpha < MIN_ALPHA || wo.z <= 0.0 || wi.z <= 0.0 {
                    return (Vec3::ZERO, 0.0);
                }
                let h = wo + wi;
                if h.length_squared() == 0.0 {
                    return (Vec3::ZERO, 0.0);
                }
                let m = h.normalize();
                let d = ggx_d(m, alpha);
                let g = smith_g1(wo, alpha) * smith_g1(wi, alpha);
                let f_cos = reflectance * (d * g / (4.0 * wo.z));
                let pdf = ggx_reflection_pdf(wo, wi, m, alpha);
                if !f_cos.is_finite() || !pdf.is_finite() {
                    return (Vec3::ZERO, 0.0);
                }
                (f_cos, pdf)
            }
            Bsdf::Dielectric { .. } => (Vec3::ZERO, 0.0),
        }
    }
}

#[inline]
pub fn reflect(wo: Vec3, m: Vec3) -> Vec3 {
    2.0 * wo.dot(m) * m - wo
}

/// Refraction of `wo` through the z = 0 boundary with relative index `eta`
/// (transmitted side over incident side); `None` on total internal reflection.
#[inline]
pub fn refract(wo: Vec3, eta: f32) -> Option<Vec3> {
    let cos_i = wo.z.abs();
    let sin2_t = (1.0 - cos_i * cos_i).max(0.0) / (eta * eta);
    if sin2_t >= 1.0 {
        return None;
    }
    let cos_t = (1.0 - sin2_t).sqrt();
    let n_sign = if wo.z > 0.0 { 1.0 } else { -1.0 };
    let wi = -wo / eta + Vec3::new(0.0, 0.0, n_sign * (cos_i / eta - cos_t));
    Some(wi.normalize())
}

/// Unpolarized Fresnel reflectance of a smooth dielectric boundary; `cos_i`
/// is measured against the outward (front) normal, `ior` is inside / outside.
pub fn fresnel_dielectric(cos_i: f32, ior: f32) -> f32 {
    let mut cos_i = cos_i.clamp(-1.0, 1.0);
    let mut eta = ior;
    if cos_i < 0.0 {
        eta = 1.0 / eta;
        cos_i = -cos_i;
    }
    let sin2_t = (1.0 - cos_i * cos_i) / (eta * eta);
    if sin2_t >= 1.0 {
        return 1.0;
    }
    let cos_t = (1.0 - sin2_t).max(0.0).sqrt();
    let r_parl = (eta * cos_i - cos_t) / (eta * cos_i + cos_t);
    let r_perp = (cos_i - eta * cos_t) / (cos_i + eta * cos_t);
    0.5 * (r_parl * r_parl + r_perp * r_perp)
}

/// Trowbridge-Reitz normal distribution.
#[inline]
pub fn ggx_d(m: Vec3, alpha: f32) -> f32 {
    if m.z <= 0.0 {
        return 0.0;
    }
    let a2 = alpha * alpha;
    let t = (m.x * m.x + m.y * m.y) / a2 + m.z * m.z;
    1.0 / (PI * a2 * t * t)
}

/// Smith's masking for one direction.
#[inline]
pub fn smith_g1(w: Vec3, alpha: f32) -> f32 {
    if w.z <= 0.0 {
        return 0.0;
    }
    let tan2 = (w.x * w.x + w.y * w.y) / (w.z * w.z);
    let lambda = 0.5 * ((1.0 + alpha * alpha * tan2).sqrt() - 1.0);
    1.0 / (1.0 + lambda)
}

/// pdf of reflecting `wo` into `wi` about `m` under visible-normal sampling.
#[inline]
fn ggx_reflection_pdf(wo: Vec3, wi: Vec3, m: Vec3, alpha: f32) -> f32 {
    let _ = wi;
    let wo_m = wo.dot(m);
    if wo_m <= 0.0 || wo.z <= 0.0 {
        return 0.0;
    }
    // D_wo(m) = G1(wo) max(0, wo.m) D(m) / wo.z ; Jacobian 1 / (4 wo.m).
    smith_g1(wo, alpha) * ggx_d(m, alpha) / (4.0 * wo.z)
}

/// Heitz 2018, "Sampling the GGX Distribution of Visible Normals".
pub fn ggx_sample_visible(wo: Vec3, alpha: f32, u: Vec2) -> Vec3 {
    let vh = Vec3::new(alpha * wo.x, alpha * wo.y, wo.z).normalize();
    let lensq = vh.x * vh.x + vh.y * vh.y;
    let t1 = if lensq > 0.0 {
        Vec3::new(-vh.y, vh.x, 0.0) / lensq.sqrt()
    } else {
        Vec3::X
    };
    let t2 = vh.cross(t1);
    let r = u.x.sqrt();
    let phi = TAU * u.y;
    let p1 = r * phi.cos();
    let mut p2 = r * phi.sin();
    let s = 0.5 * (1.0 + vh.z);
    p2 = (1.0 - s) * (1.0 - p1 * p1).max(0.0).sqrt() + s * p2;
    let nh = p1 * t1 + p2 * t2 + (1.0 - p1 * p1 - p2 * p2).max(0.0).sqrt() * vh;
    Vec3::new(alpha * nh.x, alpha * nh.y, nh.z.max(1e-6)).normalize()
}

#[cfg(test)]
mod tests {
    use super::*;
    use nppp_geom::SampleRng;
    use nppp_geom::sampling::uniform_sphere;

    fn dir(theta_deg: f32) -> Vec3 {
        let t = theta_deg.to_radians();
        Vec3::new(t.sin(), 0.0, t.cos())
    }

    /// Directional albedo two ways: the mean sampled weight, and eval()
    /// integrated with uniform sphere sampling. They agree only if sample()
    /// and eval() describe the same BSDF.
    fn albedo_two_ways(b: &Bsdf, wo: Vec3, n: usize) -> (f64, f64, f64) {
        let mut rng = SampleRng::from_seed(17);
        let mut by_sampling = 0.0f64;
        let mut by_eval = 0.0f64;
        let mut pdf_integral = 0.0f64;
        for _ in 0..n {
            if let Some(s) = b.sample(wo, rng.uniform(), rng.uniform2()) {
                by_sampling += s.weight.x as f64;
            }
            let wi = uniform_sphere(rng.uniform2());
            let (f, pdf) = b.eval(wo, wi);
            by_eval += f.x as f64 * 4.0 * std::f64::consts::PI;
            pdf_integral += pdf as f64 * 4.0 * std::f64::consts::PI;
        }
        (
            by_sampling / n as f64,
            by_eval / n as f64,
            pdf_integral / n as f64,
        )
    }

    #[test]
    fn sample_and_eval_agree() {
        for b in [
            Bsdf::Diffuse {
                albedo: Vec3::splat(0.7),
            },
            Bsdf::Conductor {
                reflectance: Vec3::ONE,
                alpha: 0.5,
            },
            Bsdf::Conductor {
                reflectance: Vec3::ONE,
                alpha: 0.2,
            },
            Bsdf::Conductor {
                reflectance: Vec3::ONE,
                alpha: 1.0,
            },
        ] {
            for th in [0.0, 30.0, 60.0, 80.0] {
                let (s, e, p) = albedo_two_ways(&b, dir(th), 400_000);
                assert!(
                    (s - e).abs() < 0.02 * s.max(0.1),
                    "{b:?} theta {th}: sampled {s} vs eval {e}"
                );
                assert!(
                    p <= 1.01 && p > 0.5,
                    "{b:?} theta {th}: pdf integrates to {p}"
                );
            }
        }
    }

    #[test]
    fn dielectric_fresnel_limits() {
        assert!((fresnel_dielectric(1.0, 1.5) - 0.04).abs() < 1e-4);
        assert_eq!(fresnel_dielectric(0.0, 1.5), 1.0);
        // Total internal reflection from inside past the critical angle.
        assert_eq!(fresnel_dielectric(-0.3, 1.5), 1.0);
        assert!(fresnel_dielectric(1.0, 1.0) < 1e-7);
    }
}
