//! What happens to a path at a surface, shared by the integrator, the object
//! walks (training data and the oracle) and next-event estimation through an
//! estimator: the surface's kind, its shading frame, the one BSDF-sampling
//! routine, and the offset that moves a spawned ray off the surface. Its own
//! module so that none of those users has to borrow it from another.

use crate::bsdf::Bsdf;
use glam::{Vec2, Vec3};
use nppp_geom::Frame;
use nppp_scene::Material;

/// What a surface does to a path; a closed enum so the hot loop matches instead of dispatching.
#[derive(Clone, Copy, Debug)]
pub enum SurfaceKind {
    Scatter(Bsdf),
    Emitter { radiance: Vec3 },
}

impl SurfaceKind {
    /// The BSDF whose vertices take light samples, so that next-event
    /// estimation through an estimator applies (and data generation records
    /// a picked vertex per walk): a non-delta surface. Glass (delta) and
    /// translucent objects (light is behind a smooth boundary) have none.
    pub fn light_sampled_bsdf(self) -> Option<Bsdf> {
        match self {
            SurfaceKind::Scatter(b) if !b.is_delta() => Some(b),
            _ => None,
        }
    }

    /// What a material does to a path at its surface (a translucent
    /// object's boundary is its dielectric interface; the medium inside is
    /// `Medium::of`).
    pub fn of(m: &Material) -> SurfaceKind {
        match *m {
            Material::Diffuse { albedo } => SurfaceKind::Scatter(Bsdf::Diffuse { albedo }),
            Material::Conductor {
                reflectance,
                roughness,
            } => SurfaceKind::Scatter(Bsdf::Conductor {
                reflectance,
                alpha: roughness,
            }),
            Material::Dielectric { ior } | Material::Translucent { ior, .. } => {
                SurfaceKind::Scatter(Bsdf::Dielectric { ior })
            }
            Material::Emitter { radiance } => SurfaceKind::Emitter { radiance },
        }
    }
}

/// Relative size of the offset that moves a spawned ray off its surface;
/// a few hundred ulps of the coordinates involved.
pub const OFFSET_REL: f32 = 2e-5;

/// A smooth triangle's vertex normals `n` interpolated at barycentrics
/// `(b1, b2)`, on geometric normal `ng`'s side; `ng` where they point the
/// other way (a shading normal on the far side of the surface is
/// meaningless) or are zero (a flat mesh).
#[inline]
pub fn interpolated_normal(n: [Vec3; 3], b1: f32, b2: f32, ng: Vec3) -> Vec3 {
    shading_normal_on_side(n[0] * (1.0 - b1 - b2) + n[1] * b1 + n[2] * b2, ng)
}

/// An interpolated (not yet unit) shading normal `s` made unit, or `ng`
/// where it points to the other side of the surface or is zero: the rule
/// of [`interpolated_normal`], for callers that move `s` to another space
/// first.
#[inline]
pub fn shading_normal_on_side(s: Vec3, ng: Vec3) -> Vec3 {
    let s = s.normalize_or_zero();
    if s.dot(ng) > 0.0 { s } else { ng }
}

/// The shading frame at a vertex and the geometric normal on the side the
/// path arrived from. Two-sided materials see the surface from wo's side;
/// glass keeps front = outside.
#[inline]
pub fn shading_frame(bsdf: &Bsdf, ng: Vec3, ns: Vec3, wo_world: Vec3) -> (Frame, Vec3) {
    let (ng_side, ns_side) = if bsdf.two_sided() && wo_world.dot(ng) < 0.0 {
        (-ng, -ns)
    } else {
        (ng, ns)
    };
    (Frame::from_normal(ns_side), ng_side)
}

/// Samples the continuation of a path at a surface: the one BSDF-sampling
/// routine that the renderer, the data generator and the oracle estimator
/// share. Returns the world direction and the local sample, or `None` when
/// the path ends (absorbed, or the direction disagrees with the geometric
/// surface: reflection must stay on wo's side, transmission must cross).
#[inline]
pub fn sample_scatter(
    bsdf: &Bsdf,
    frame: &Frame,
    ng: Vec3,
    wo_world: Vec3,
    u_lobe: f32,
    u_dir: Vec2,
) -> Option<(Vec3, crate::bsdf::BsdfSample)> {
    let wo = frame.to_local(wo_world);
    let bs = bsdf.sample(wo, u_lobe, u_dir)?;
    let wi = frame.to_world(bs.wi);
    let reflect_side = wi.dot(ng) * wo_world.dot(ng) > 0.0;
    if reflect_side == bs.transmitted {
        return None;
    }
    Some((wi, bs))
}

/// Moves `p` off the surface with normal `n` to the side `dir` points to.
#[inline]
pub fn offset_ray_origin(p: Vec3, n: Vec3, dir: Vec3, eps: f32) -> Vec3 {
    if dir.dot(n) >= 0.0 {
        p + n * eps
    } else {
        p - n * eps
    }
}
