//! One path's state between bounces: what the wavefront integrator advances
//! and what an estimator entry reads and continues.

use crate::medium::HeroChannel;
use glam::Vec3;
use nppp_geom::SampleRng;

/// One path's state between bounces.
#[derive(Clone, Debug)]
pub struct PathState {
    /// Index of the pixel inside the batch's accumulation buffer.
    pub slot: u32,
    pub rng: SampleRng,
    pub origin: Vec3,
    pub dir: Vec3,
    /// Throughput.
    pub beta: Vec3,
    /// Radiance gathered so far.
    pub radiance: Vec3,
    pub depth: u32,
    /// BSDF pdf of the direction that produced this ray (for MIS at an emitter hit).
    pub prev_pdf: f32,
    /// Whether that direction came from a delta lobe (or an estimator exit): MIS weight 1.
    pub prev_delta: bool,
    /// Position of the vertex the ray left from.
    pub prev_point: Vec3,
    /// Product of the radiance scalings at refractions, undone for Russian roulette.
    pub eta_scale: f32,
    /// The instance whose estimator this ray has just left (ignored by the
    /// next intersection), or `NO_SKIP`.
    pub skip_instance: u32,
    /// The medium the path is travelling through: set when the path
    /// refracts into a translucent object, cleared when it refracts out of
    /// one (media do not nest: out of an inner translucent object is
    /// vacuum, as in Mitsuba 3); surfaces without a medium keep it.
    pub medium: Option<MediumVisit>,
    /// The path's spectral MIS over all its medium visits: picked at its
    /// first entry into a medium, kept to its end (see `crate::medium`).
    pub hero: Option<HeroChannel>,
}

/// A path's visit of a translucent object's medium.
#[derive(Clone, Copy, Debug)]
pub struct MediumVisit {
    /// The instance whose medium it is (`RenderScene::media`).
    pub instance: u32,
    /// How much of the medium lies on the ray behind its origin: a ray
    /// leaving a surface starts a small offset off it ([`skin_behind`]),
    /// and the free flight must cover that stretch too.
    pub skin: f32,
}

/// The length of the ray `wi`, behind an origin moved `eps` off a surface
/// of normal `ng`, back to that surface: the stretch of a medium the offset
/// skipped. Without it a dense medium rendered dark (a skin of 2e-5 times
/// the distance from the origin where nothing scattered: 0.8% at a mean
/// free path of 0.011 at x = 278, 3% at 0.0011), and darker the farther
/// from the origin it stood. Capped at two offsets: for a grazing ray the
/// stretch runs along the surface, and a scattering point there could fall
/// outside a thin part of the object.
#[inline]
pub fn skin_behind(eps: f32, wi: Vec3, ng: Vec3) -> f32 {
    eps / wi.dot(ng).abs().max(0.5)
}

impl PathState {
    pub fn camera(slot: u32, rng: SampleRng, origin: Vec3, dir: Vec3) -> Self {
        Self {
            slot,
            rng,
            origin,
            dir,
            beta: Vec3::ONE,
            radiance: Vec3::ZERO,
            depth: 0,
            prev_pdf: 0.0,
            prev_delta: true,
            prev_point: origin,
            eta_scale: 1.0,
            skip_instance: crate::accel::NO_SKIP,
            medium: None,
            hero: None,
        }
    }
}
