//! Tracing a path through one object alone: no lights, no other geometry, no
//! Russian roulette, until it leaves the object's bounding sphere. This is
//! the ground truth the estimator learns (training data) and the "oracle"
//! estimator that checks the renderer's estimator integration.
//!
//! Everything is in mesh space, and in and out in the unit sphere's frame.

use crate::accel::Blas;
use crate::bsdf::Bsdf;
use crate::medium::{HeroChannel, Medium};
use crate::surface::{OFFSET_REL, SurfaceKind, offset_ray_origin, sample_scatter, shading_frame};
use glam::Vec3;
use nppp_estimator::Exit;
use nppp_geom::sphere_pair::unit_sphere_chord;
use nppp_geom::{BoundingSphere, Ray, SampleRng};

/// One object: its BLAS, what its surface does, its bounding sphere, and
/// (for smooth meshes) vertex normals.
pub struct ObjectTracer<'a> {
    pub blas: &'a Blas,
    pub surface: SurfaceKind,
    /// The medium inside the object (translucent), in mesh units: a walk
    /// that refracts in samples free flights and phase functions until it
    /// refracts out.
    pub medium: Option<Medium>,
    pub sphere: BoundingSphere,
    pub geo_normals: &'a [Vec3],
    pub shading_normals: Option<&'a [[Vec3; 3]]>,
    /// Paths still inside after this many internal bounces end as zero-throughput exits.
    pub max_internal_bounces: u32,
}

/// A scattering vertex inside the object, in mesh space, as a walk passes it:
/// what next-event estimation at that vertex needs.
#[derive(Clone, Copy, Debug)]
pub struct WalkVertex {
    pub point: Vec3,
    /// Geometric normal (the mesh's outward side).
    pub ng: Vec3,
    /// Shading normal on the geometric normal's side (not flipped to `wo`'s).
    pub ns: Vec3,
    /// Towards the previous vertex (or the entry).
    pub wo: Vec3,
    /// Throughput from the entry up to this vertex, before it scatters.
    pub beta: Vec3,
    /// Internal bounces before this vertex (0: the first hit).
    pub index: u32,
    /// Solid-angle pdf of the direction sampled here (0 if sampling failed):
    /// for the last vertex, the MIS weight of an emitter the exit ray hits.
    pub pdf: f32,
    /// Whether that direction came from a delta lobe, or the vertex is a
    /// scattering event in a medium (no next-event estimation there: the
    /// light is behind the object's smooth boundary).
    pub delta: bool,
}

/// The result of one walk.
#[derive(Clone, Copy, Debug)]
pub enum Walk {
    /// The entry ray never touched the mesh (mask label 0).
    Miss,
    /// It hit the mesh; this is where the light went.
    Exit(Exit),
}

impl ObjectTracer<'_> {
    /// Does the unit-frame ray hit the mesh at all (the mask label)?
    pub fn hits(&self, ray: &Ray) -> bool {
        let o = self.sphere.from_unit_point(ray.origin);
        self.blas
            .intersect(o.into(), ray.dir.into(), 0.0, f32::INFINITY)
            .is_some()
    }

    /// The first vertex of a walk: where the unit-frame `ray` hits the mesh
    /// (mesh space; `beta` 1, `pdf` 0), or `None` if it misses.
    pub fn first_vertex(&self, ray: &Ray) -> Option<WalkVertex> {
        let o = self.sphere.from_unit_point(ray.origin);
        let d = ray.dir;
        let h = self
            .blas
            .intersect(o.into(), d.into(), 0.0, f32::INFINITY)?;
        let ng = self.geo_normals[h.prim as usize];
        Some(WalkVertex {
            point: o + d * h.t,
            ng,
            ns: self.shading_normal(&h, ng),
            wo: -d,
            beta: Vec3::ONE,
            index: 0,
            pdf: 0.0,
            delta: false,
        })
    }

    /// The interpolated vertex normal at a hit, on `ng`'s side (`ng` for flat meshes).
    fn shading_normal(&self, h: &crate::accel::ObjectHit, ng: Vec3) -> Vec3 {
        match self.shading_normals {
            Some(n) => crate::surface::interpolated_normal(n[h.prim as usize], h.b1, h.b2, ng),
            None => ng,
        }
    }

    /// Follows the unit-frame ray `ray` (starting on or outside the sphere)
    /// through the object with the random stream `rng`.
    pub fn walk(&self, ray: &Ray, rng: &mut SampleRng) -> Walk {
        self.walk_recording(ray, rng, |_| {})
    }

    /// [`Self::walk`], passing each scattering vertex to `record` once its
    /// direction is sampled (the same random numbers: the walk is the same).
    pub fn walk_recording(
        &self,
        ray: &Ray,
        rng: &mut SampleRng,
        mut record: impl FnMut(WalkVertex),
    ) -> Walk {
        let r = self.sphere.radius;
        let mut o = self.sphere.from_unit_point(ray.origin);
        let mut d = ray.dir;
        let mut beta = Vec3::ONE;
        let mut radiance = Vec3::ZERO;
        let mut bounces = 0u32;
        let mut first = true;
        // The walk's spectral MIS (one hero channel for all its visits of
        // the medium: see `crate::medium`), and whether it is in the medium.
        let mut hero: Option<HeroChannel> = None;
        let mut in_medium = false;
        // The medium on the ray behind its offset origin (`skin_behind`).
        let mut skin = 0.0f32;
        loop {
            let hit = self.blas.intersect(o.into(), d.into(), 0.0, f32::INFINITY);
            if let (true, Some(hero), Some(medium)) = (in_medium, &mut hero, &self.medium) {
                let t_max = hit.map_or(f32::INFINITY, |h| h.t);
                let flight = medium.sample_free_flight(t_max + skin, hero.channel, rng.uniform());
                hero.apply(&mut beta, &flight);
                if flight.scattered {
                    let p = o + d * (flight.t - skin);
                    skin = 0.0;
                    if bounces >= self.max_internal_bounces {
                        return Walk::Exit(self.leave(p, d, Vec3::ZERO, radiance, bounces));
                    }
                    let (wi, pdf) = medium.sample_phase(d, rng.uniform2());
                    record(WalkVertex {
                        point: p,
                        ng: -d,
                        ns: -d,
                        wo: -d,
                        beta,
                        index: bounces,
                        pdf,
                        delta: true,
                    });
                    bounces += 1;
                    o = p;
                    d = wi;
                    if beta == Vec3::ZERO {
                        return Walk::Exit(self.leave(o, d, beta, radiance, bounces));
                    }
                    continue;
                }
            }
            let Some(h) = hit else {
                if first {
                    return Walk::Miss;
                }
                return Walk::Exit(self.leave(o, d, beta, radiance, bounces));
            };
            first = false;
            let p = o + d * h.t;
            let ng = self.geo_normals[h.prim as usize];
            let wo = -d;
            let bsdf: Bsdf = match self.surface {
                SurfaceKind::Emitter { radiance: le } => {
                    if wo.dot(ng) > 0.0 {
                        radiance += beta * le;
                    }
                    return Walk::Exit(self.leave(p, d, Vec3::ZERO, radiance, bounces));
                }
                SurfaceKind::Scatter(b) => b,
            };
            if bounces >= self.max_internal_bounces {
                return Walk::Exit(self.leave(p, d, Vec3::ZERO, radiance, bounces));
            }
            let ns = self.shading_normal(&h, ng);
            let (frame, _) = shading_frame(&bsdf, ng, ns, wo);
            let u_lobe = rng.uniform();
            let u_dir = rng.uniform2();
            let sampled = sample_scatter(&bsdf, &frame, ng, wo, u_lobe, u_dir);
            record(WalkVertex {
                point: p,
                ng,
                ns,
                wo,
                beta,
                index: bounces,
                pdf: sampled.map_or(0.0, |s| s.1.pdf),
                delta: sampled.is_some_and(|s| s.1.delta),
            });
            bounces += 1;
            let Some((wi, bs)) = sampled else {
                return Walk::Exit(self.leave(p, d, Vec3::ZERO, radiance, bounces));
            };
            beta *= bs.weight;
            if bs.transmitted {
                // Into the medium from the front (outside), out of it from the back.
                in_medium = wo.dot(ng) > 0.0 && self.medium.is_some();
                if in_medium {
                    // Drawn at every entry, used at the first.
                    let picked = HeroChannel::pick(rng.uniform());
                    hero.get_or_insert(picked);
                }
            }
            let eps = (p.abs().max_element().max(r) * OFFSET_REL).max(f32::MIN_POSITIVE);
            o = offset_ray_origin(p, ng, wi, eps);
            skin = if in_medium {
                crate::path::skin_behind(eps, wi, ng)
            } else {
                0.0
            };
            d = wi;
            if beta == Vec3::ZERO {
                return Walk::Exit(self.leave(o, d, beta, radiance, bounces));
            }
        }
    }

    /// The exit where the mesh-space ray (o, d) leaves the sphere, in the unit frame.
    fn leave(&self, o: Vec3, d: Vec3, throughput: Vec3, radiance: Vec3, bounces: u32) -> Exit {
        let uo = self.sphere.to_unit_point(o);
        let t = unit_sphere_chord(&Ray::new(uo, d)).map_or(0.0, |c| c.t_out.max(0.0));
        let position = (uo + d * t).normalize_or(Vec3::Z);
        Exit {
            position,
            direction: d,
            throughput,
            radiance,
            bounces,
        }
    }
}
