//! The wavefront path tracer.
//!
//! A batch of paths (a tile's pixels times a slice of their samples) is
//! advanced one bounce per step: intersect every live path, shade every hit
//! (emission with MIS, next-event estimation with MIS, BSDF sampling, Russian
//! roulette), then compact away the paths that ended. Each sample owns its
//! random stream, so batching and thread count never change the image.
//! Diffuse bounces outside media, most of a plain path tracer's, are shaded
//! eight paths at a time in SIMD lanes (`diffuse_lanes`), bit for bit as
//! `shade` shades one.
//!
//! Inside a translucent object a path also samples free flights through
//! its medium (`scatter_in_medium`): a scattering event there is a bounce like
//! one on a surface, and gets no next-event estimation (every light is
//! behind the object's smooth boundary, which a shadow ray cannot cross).
//!
//! Bounce convention (docs/scene-format.md): `depth` counts scattering events so
//! far; emission found after `depth` events contributes to the image when
//! `depth <= max_bounces`, and NEE at a vertex contributes a path with
//! `depth + 1` events.

use crate::accel::SceneHit;
use crate::bsdf::Bsdf;
use crate::entry::EntryBatch;
use crate::estimator::{EntryNee, Estimator, EstimatorStats, Estimators, Meet, SkippedVertices};
use crate::film::PixelSum;
use crate::medium::HeroChannel;
use crate::path::{MediumVisit, PathState};
use crate::scene_data::RenderScene;
use crate::surface::{SurfaceKind, offset_ray_origin, sample_scatter, shading_frame};
use glam::{Vec2, Vec3};
use nppp_geom::Frame;
use nppp_geom::sampling::power_heuristic;

mod diffuse_lanes;
use diffuse_lanes::{lane_albedo, shade_diffuse_lanes};

/// Russian roulette starts after this many scattering events.
pub const RR_START_DEPTH: u32 = 3;
/// From this many scattering events on, a path is terminated at each
/// surface event with probability at least `RR_MIN_TERMINATION`, so that
/// lossless paths (albedo 1, mirrors, glass) end even when `max_bounces` is
/// huge. Unbiased. Not at a medium's events (see `roulette`).
pub const RR_CAP_DEPTH: u32 = 64;
/// The floor is small so that it never stands in for a real medium's
/// absorption: at 5% (Mitsuba's cap, which it applies from its rr_depth on)
/// a walk in cornell-jade's medium (albedo 0.996, walks of up to M = 256
/// events) was ended 5% per event past bounce 64 and its survivors
/// reweighted by up to 1/0.95^192 = 19,000x: PT's relMSE at 64 spp moved
/// between 0.07 and 0.70 with the seed. At 0.2% the reweighting is at most
/// 1.5x there (relMSE 0.053-0.059 at four seeds, 1.2x-1.45x the time), and
/// a trapped lossless path still ends after about 500 more bounces.
pub const RR_MIN_TERMINATION: f32 = 0.002;

#[derive(Clone, Copy, Debug)]
pub struct IntegratorSettings {
    pub max_bounces: u32,
    pub seed: u64,
}

/// Work a render did, counted: deterministic at any thread count, unlike
/// its time, so that decisions made from a pilot render (`--estimators
/// auto`) are deterministic too.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct WorkCounts {
    /// Closest-hit queries (one per live path per wavefront step).
    pub rays: u64,
    /// The part of `rays` that are camera rays (one per sample): the same
    /// in every configuration of a scene, so the `auto` pilot's cost model
    /// counts only the later ones.
    pub camera_rays: u64,
    /// Shadow rays traced for next-event estimation.
    pub shadow_rays: u64,
    /// BVH nodes and leaves visited by all traversals (closest hits, shadow
    /// rays, estimator queries, oracle walks).
    pub node_visits: u64,
    /// The part of `node_visits` spent on the camera rays' closest hits:
    /// coherent rays whose nodes are in cache, far cheaper per visit than a
    /// deep path's (the `auto` pilot's cost model leaves them out).
    pub camera_node_visits: u64,
    /// The leaves (triangle packets, TLAS leaves) among `node_visits` not
    /// spent on camera rays: the `auto` pilot's cost model counts inner
    /// nodes only (a leaf's packets were prefetched while its parent was
    /// tested).
    pub leaf_visits: u64,
}

impl WorkCounts {
    pub fn merge(&mut self, o: &WorkCounts) {
        self.rays += o.rays;
        self.camera_rays += o.camera_rays;
        self.shadow_rays += o.shadow_rays;
        self.node_visits += o.node_visits;
        self.camera_node_visits += o.camera_node_visits;
        self.leaf_visits += o.leaf_visits;
    }
}

/// Reusable buffers of one worker: no allocation per bounce.
#[derive(Default)]
pub struct Wavefront {
    pub paths: Vec<PathState>,
    pub meets: Vec<Meet>,
    /// Outcome per path of this step's estimator exits.
    next: Vec<Next>,
    batch: EntryBatch,
    pub estimator_stats: EstimatorStats,
    pub work: WorkCounts,
    /// Per path of this step: what comes next.
    outcome: Vec<Next>,
    /// This step's paths waiting for SIMD diffuse shading: (path, hit, albedo).
    lanes: Vec<(u32, SceneHit, Vec3)>,
    /// Tests only: shade every path with the scalar `shade`, to compare
    /// whole renders with the lanes.
    #[cfg(test)]
    scalar_only: bool,
}

/// Outcome of advancing one path by one event.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Next {
    Continue,
    Terminate,
}

impl Wavefront {
    /// Runs every path in `self.paths` to completion, adding each to its slot in `film`.
    pub fn run(
        &mut self,
        scene: &RenderScene,
        settings: &IntegratorSettings,
        film: &mut [PixelSum],
    ) {
        // Everything below runs on this thread: the visits counted here are
        // this batch's own.
        let visits_before = crate::bvh::node_visits();
        let leaves_before = crate::bvh::leaf_visits();
        let mut camera_leaves = 0;
        let mut camera_step = true;
        while !self.paths.is_empty() {
            self.intersect(scene, settings);
            if camera_step {
                self.work.camera_rays += self.paths.len() as u64;
                self.work.camera_node_visits += crate::bvh::node_visits() - visits_before;
                camera_leaves = crate::bvh::leaf_visits() - leaves_before;
                camera_step = false;
            }
            self.answer_estimators(scene, settings);
            // Each path's next event; diffuse bounces go to SIMD lanes,
            // eight paths at a time, and fill in their outcomes there.
            self.outcome.clear();
            self.lanes.clear();
            for r in 0..self.paths.len() {
                let path = &mut self.paths[r];
                let next = match self.meets[r] {
                    Meet::Estimator(_) => self.next[r],
                    // In a medium, an event may happen before the surface.
                    meet if path.medium.is_some() => {
                        let hit = match meet {
                            Meet::Surface(h) => Some(h),
                            _ => None,
                        };
                        let t_max = hit.map_or(f32::INFINITY, |h| h.t);
                        match (scatter_in_medium(scene, settings, path, t_max), hit) {
                            (Some(next), _) => next,
                            (None, Some(hit)) => shade(scene, settings, path, hit, &mut self.work),
                            (None, None) => Next::Terminate,
                        }
                    }
                    Meet::Nothing => Next::Terminate,
                    Meet::Surface(hit) => match lane_albedo(scene, settings, path, &hit) {
                        #[cfg(test)]
                        Some(_) if self.scalar_only => {
                            shade(scene, settings, path, hit, &mut self.work)
                        }
                        Some(albedo) => {
                            self.lanes.push((r as u32, hit, albedo));
                            Next::Continue
                        }
                        None => shade(scene, settings, path, hit, &mut self.work),
                    },
                };
                self.outcome.push(next);
                if self.lanes.len() == diffuse_lanes::LANES {
                    self.shade_lanes(scene);
                }
            }
            self.shade_lanes(scene);
            let mut w = 0;
            for r in 0..self.paths.len() {
                match self.outcome[r] {
                    Next::Continue => {
                        // Slots w..r hold finished paths (their radiance
                        // is in the film): overwrite one, no swap needed.
                        if w != r {
                            self.paths[w] = self.paths[r].clone();
                        }
                        w += 1;
                    }
                    Next::Terminate => {
                        let p = &self.paths[r];
                        film[p.slot as usize].add(p.radiance);
                    }
                }
            }
            self.paths.truncate(w);
        }
        self.work.node_visits += crate::bvh::node_visits() - visits_before;
        self.work.leaf_visits += crate::bvh::leaf_visits() - leaves_before - camera_leaves;
    }

    /// Shades the paths waiting in `self.lanes` together and empties it.
    fn shade_lanes(&mut self, scene: &RenderScene) {
        if !self.lanes.is_empty() {
            shade_diffuse_lanes(
                scene,
                &mut self.paths,
                &self.lanes,
                &mut self.outcome,
                &mut self.work,
            );
            self.lanes.clear();
        }
    }

    fn intersect(&mut self, scene: &RenderScene, settings: &IntegratorSettings) {
        self.meets.clear();
        self.work.rays += self.paths.len() as u64;
        let stats = &mut self.estimator_stats;
        let m = settings.max_bounces;
        self.meets.extend(self.paths.iter_mut().map(|p| {
            match &scene.estimators {
                // A path at depth M only looks for emission: the real mesh serves (and P >= M never estimates).
                // A path inside a medium traces every object for real: an
                // estimator learned its object in vacuum.
                Some(est)
                    if p.medium.is_none()
                        && p.depth >= est.min_bounces
                        && p.depth < m
                        && !est.cannot_enter(&scene.accel, p.origin, p.dir) =>
                {
                    est.intersect(
                        &scene.accel,
                        p.origin,
                        p.dir,
                        p.skip_instance,
                        p.depth,
                        stats,
                    )
                }
                // Only a path that has just left an estimator skips an
                // instance, and only the estimator layout keeps it apart.
                _ if p.skip_instance == crate::accel::NO_SKIP => scene
                    .plain()
                    .intersect(p.origin, p.dir, f32::INFINITY)
                    .map_or(Meet::Nothing, Meet::Surface),
                _ => scene
                    .accel
                    .intersect_skipping(p.origin, p.dir, f32::INFINITY, p.skip_instance)
                    .map_or(Meet::Nothing, Meet::Surface),
            }
        }));
    }

    /// Gathers this step's estimator entries, answers them in one batch, and
    /// moves each of those paths to its exit.
    fn answer_estimators(&mut self, scene: &RenderScene, settings: &IntegratorSettings) {
        let Some(ests) = &scene.estimators else {
            return;
        };
        self.batch.entries.clear();
        self.batch
            .entries
            .extend(self.meets.iter().enumerate().filter_map(|(i, m)| match m {
                Meet::Estimator(e) => Some((i, *e)),
                _ => None,
            }));
        if self.batch.entries.is_empty() {
            return;
        }
        self.batch.answer(
            ests,
            scene,
            &mut self.paths,
            settings.max_bounces,
            &mut self.estimator_stats,
        );
        self.next.clear();
        self.next.resize(self.paths.len(), Next::Terminate);
        for (k, (i, entry)) in self.batch.entries.iter().enumerate() {
            let est =
                &ests.list[ests.per_instance()[entry.instance as usize].unwrap_or(0) as usize];
            let exit = self.batch.exits[k];
            let path = &mut self.paths[*i];
            if est.entry_nee != EntryNee::Off {
                light_skipped_vertex(
                    scene,
                    path,
                    entry.instance,
                    &self.batch.skipped[k],
                    &mut self.work,
                );
            }
            self.next[*i] = follow_exit(
                scene,
                settings,
                path,
                entry.instance,
                ests,
                est,
                &exit,
                &self.batch.skipped[k],
                &mut self.estimator_stats,
            );
        }
    }
}

/// Next-event estimation at the skipped vertex an estimator returned (mesh
/// space of `instance`), against the whole scene, the object included. The
/// random numbers are drawn whether or not there is a vertex.
fn light_skipped_vertex(
    scene: &RenderScene,
    path: &mut PathState,
    instance: u32,
    skipped: &SkippedVertices,
    work: &mut WorkCounts,
) {
    let u_light = path.rng.uniform();
    let u_light2 = path.rng.uniform2();
    let Some((v, bsdf)) = &skipped.nee else {
        return;
    };
    let x = &scene.accel.instances[instance as usize];
    let p = x.point_to_world(v.point);
    let mis = !skipped.light_alone;
    let ng = x.dir_to_world(v.ng).normalize();
    let ns = x.dir_to_world(v.ns).normalize();
    let wo_world = x.dir_to_world(v.wo).normalize();
    let (frame, ng_side) = shading_frame(bsdf, ng, ns, wo_world);
    let vertex = SurfaceVertex {
        p,
        ng_side,
        frame,
        wo: frame.to_local(wo_world),
        eps: scene.offset_at(p, instance),
    };
    path.radiance +=
        path.beta * v.beta * sample_ld_weighted(scene, bsdf, &vertex, u_light, u_light2, mis, work);
}

/// Continues a path from an estimator exit. The exit ray starts on the
/// exit line where [`Estimators::exit_origin`] says (the middle of its
/// chord, or the object's last crossing where the line meets other
/// geometry inside the sphere near the object); the instance itself is
/// skipped by the next intersection.
#[allow(clippy::too_many_arguments)]
fn follow_exit(
    scene: &RenderScene,
    s: &IntegratorSettings,
    path: &mut PathState,
    instance: u32,
    ests: &Estimators,
    est: &Estimator,
    e: &nppp_estimator::Exit,
    skipped: &SkippedVertices,
    stats: &mut EstimatorStats,
) -> Next {
    path.radiance += path.beta * e.radiance;
    path.beta *= e.throughput;
    path.depth = path.depth.saturating_add(e.bounces);
    if path.depth > s.max_bounces {
        stats.over_max_bounces += 1;
        return Next::Terminate;
    }
    if path.beta == Vec3::ZERO || !path.beta.is_finite() {
        return Next::Terminate;
    }
    // Out of bounces, the exit ray could only find an emitter, and after
    // light sampled alone at the skipped vertices that counts 0 (below):
    // not traced (a quarter of the default scene's entries at P = 1 are at
    // the last bounce).
    if skipped.light_alone && path.depth >= s.max_bounces {
        return Next::Terminate;
    }
    let x = &scene.accel.instances[instance as usize];
    path.origin = x.point_to_world(ests.exit_origin(&scene.accel, instance, est, e, stats));
    path.dir = x.dir_to_world(e.direction).normalize();
    match skipped.last {
        // The light at the skipped vertices was the light sample's alone:
        // an emitter hit next counts 0 (a BSDF pdf of 0 in the MIS weight;
        // every emitter can be light-sampled).
        _ if skipped.light_alone => {
            path.prev_delta = false;
            path.prev_pdf = 0.0;
            path.prev_point = path.origin;
        }
        // Light was sampled at the skipped vertices: an emitter hit next is
        // the BSDF technique of the last one, weighted against it.
        Some((last, pdf)) => {
            path.prev_delta = false;
            path.prev_pdf = pdf;
            path.prev_point = x.point_to_world(last);
        }
        // No NEE at the skipped vertices: an emitter hit next counts fully.
        None => {
            path.prev_delta = true;
            path.prev_point = path.origin;
        }
    }
    path.skip_instance = instance;
    path.medium = None;
    Next::Continue
}

fn shade(
    scene: &RenderScene,
    s: &IntegratorSettings,
    path: &mut PathState,
    hit: SceneHit,
    work: &mut WorkCounts,
) -> Next {
    let p = path.origin + path.dir * hit.t;
    let (ng, ns) = scene.normals_at(&hit);
    let wo_world = -path.dir;
    let bsdf = match scene.surface[hit.instance as usize] {
        SurfaceKind::Emitter { radiance } => {
            let cos_l = wo_world.dot(ng);
            if cos_l > 0.0 {
                let w = if path.prev_delta {
                    1.0
                } else {
                    let li = (scene.light_base[hit.instance as usize] + hit.prim) as usize;
                    let dist = (p - path.prev_point).length();
                    power_heuristic(path.prev_pdf, scene.lights.pdf_solid_angle(li, dist, cos_l))
                };
                // A hit of weight 0 adds nothing, also where beta x radiance
                // overflows (a lamp near f32's limit: inf x 0 made the
                // sample NaN, and the film dropped it whole).
                if w > 0.0 {
                    path.radiance += path.beta * radiance * w;
                }
            }
            return Next::Terminate;
        }
        SurfaceKind::Scatter(b) => b,
    };
    if path.depth >= s.max_bounces {
        return Next::Terminate;
    }
    let (frame, ng_side) = shading_frame(&bsdf, ng, ns, wo_world);
    let wo = frame.to_local(wo_world);
    let eps = scene.offset_at(p, hit.instance);

    // Next-event estimation (the random numbers are drawn even when unused so
    // that the stream position never depends on scene content). None inside
    // a medium: a shadow ray from there would have to cross the medium's
    // smooth boundary, so every light sample would be blocked.
    let u_light = path.rng.uniform();
    let u_light2 = path.rng.uniform2();
    let in_medium = path.medium.is_some();
    if !in_medium {
        let vertex = SurfaceVertex {
            p,
            ng_side,
            frame,
            wo,
            eps,
        };
        path.radiance += path.beta * sample_ld(scene, &bsdf, &vertex, u_light, u_light2, work);
    }

    // BSDF sampling.
    let u_lobe = path.rng.uniform();
    let u_dir = path.rng.uniform2();
    let u_rr = path.rng.uniform();
    let Some((wi, bs)) = sample_scatter(&bsdf, &frame, ng, wo_world, u_lobe, u_dir) else {
        return Next::Terminate;
    };
    if bs.transmitted {
        path.eta_scale /= bs.weight.x;
    }
    path.beta *= bs.weight;
    path.prev_pdf = bs.pdf;
    // Without a light sample here, an emitter hit next counts fully.
    path.prev_delta = bs.delta || in_medium;
    path.prev_point = p;
    path.depth += 1;
    path.origin = offset_ray_origin(p, ng, wi, eps);
    path.dir = wi;
    path.skip_instance = crate::accel::NO_SKIP;
    // Through a translucent object's boundary: into its medium from the
    // front side, out of it (into vacuum) from the back side. A surface
    // without a medium (plain glass) leaves the path's medium as it is, as
    // Mitsuba 3's `volpath` does for a shape that names no media: glass
    // inside a translucent object is surrounded by that object's medium.
    if bs.transmitted && scene.media[hit.instance as usize].is_some() {
        path.medium = if wo_world.dot(ng) > 0.0 {
            // One hero channel for all the path's medium visits, drawn at
            // every entry and used from the first (`crate::medium`).
            let picked = HeroChannel::pick(path.rng.uniform());
            path.hero.get_or_insert(picked);
            Some(MediumVisit {
                instance: hit.instance,
                skin: 0.0,
            })
        } else {
            None
        };
    }
    if let Some(visit) = &mut path.medium {
        visit.skin = crate::path::skin_behind(eps, wi, ng);
    }
    russian_roulette(path, u_rr)
}

/// A free flight through the medium the path is in, up to the surface at
/// distance `t_max` (infinite: none). `Some` when an event ended the flight
/// in the medium (the path scattered, or ended there); `None` when the path
/// reached the surface, its throughput weighted by the transmittance.
fn scatter_in_medium(
    scene: &RenderScene,
    s: &IntegratorSettings,
    path: &mut PathState,
    t_max: f32,
) -> Option<Next> {
    let visit = path.medium.as_mut()?;
    let medium = scene.media[visit.instance as usize]?;
    let hero = path.hero.as_mut()?;
    // From the surface the ray left, not its offset origin.
    let skin = std::mem::take(&mut visit.skin);
    let flight = medium.sample_free_flight(t_max + skin, hero.channel, path.rng.uniform());
    hero.apply(&mut path.beta, &flight);
    if !flight.scattered {
        return None;
    }
    if path.depth >= s.max_bounces {
        return Some(Next::Terminate);
    }
    let p = path.origin + path.dir * (flight.t - skin);
    let (wi, pdf) = medium.sample_phase(path.dir, path.rng.uniform2());
    let u_rr = path.rng.uniform();
    path.prev_pdf = pdf;
    // No light sample in a medium: an emitter hit next counts fully.
    path.prev_delta = true;
    path.prev_point = p;
    path.depth += 1;
    path.origin = p;
    path.dir = wi;
    path.skip_instance = crate::accel::NO_SKIP;
    Some(roulette(path, u_rr, false))
}

/// Russian roulette after a surface event (from `RR_START_DEPTH` on), on
/// the throughput with the refractions' radiance scaling undone, with the
/// floor `RR_MIN_TERMINATION` from `RR_CAP_DEPTH` on.
#[inline]
fn russian_roulette(path: &mut PathState, u_rr: f32) -> Next {
    roulette(path, u_rr, true)
}

/// Russian roulette; `floor` says whether the termination floor applies.
/// It does not at a medium's scattering events: a walk in a finite medium
/// ends by itself (it reaches the surface), and in a dense lossless one it
/// takes about (radius x sigma)^2 events, over which the floor's kills and
/// their survivors' reweighting (e^20 for 10^4 events at 0.2%) were an
/// estimator no render could sample: a white furnace around a ball of
/// sigma_s 100 rendered 2.4% dark at every seed. Lossless paths between
/// surfaces still meet the floor at each bounce.
#[inline]
fn roulette(path: &mut PathState, u_rr: f32, floor: bool) -> Next {
    if path.depth >= RR_START_DEPTH {
        let mut q = (1.0 - (path.beta * path.eta_scale).max_element()).max(0.0);
        if floor && path.depth >= RR_CAP_DEPTH {
            q = q.max(RR_MIN_TERMINATION);
        }
        if q > 0.0 {
            if u_rr < q {
                return Next::Terminate;
            }
            path.beta /= 1.0 - q;
        }
    }
    if path.beta == Vec3::ZERO {
        return Next::Terminate;
    }
    Next::Continue
}

/// A scattering vertex as next-event estimation sees it (world space).
#[derive(Clone, Copy, Debug)]
pub struct SurfaceVertex {
    pub p: Vec3,
    /// Geometric normal on the side the path arrived from.
    pub ng_side: Vec3,
    /// Shading frame (its normal on the same side).
    pub frame: Frame,
    /// Towards the previous vertex, in the shading frame.
    pub wo: Vec3,
    /// How far to move a ray origin off the surface here.
    pub eps: f32,
}

/// Next-event estimation at a vertex (pbrt's `SampleLd`): one point on the
/// lights chosen by power, its shadow ray against the whole scene (the
/// plain layout: every estimator object is there as real geometry), weighted
/// by the power heuristic against BSDF sampling. Returns the radiance it
/// carries towards `wo`, per unit throughput. Zero for delta lobes.
#[inline]
pub fn sample_ld(
    scene: &RenderScene,
    bsdf: &Bsdf,
    v: &SurfaceVertex,
    u_light: f32,
    u_light2: Vec2,
    work: &mut WorkCounts,
) -> Vec3 {
    sample_ld_weighted(scene, bsdf, v, u_light, u_light2, true, work)
}

/// [`sample_ld`], with the MIS weight against the vertex's BSDF sample
/// (`mis`), or alone (weight 1: no BSDF sample of this vertex will count
/// an emitter it hits).
pub fn sample_ld_weighted(
    scene: &RenderScene,
    bsdf: &Bsdf,
    v: &SurfaceVertex,
    u_light: f32,
    u_light2: Vec2,
    mis: bool,
    work: &mut WorkCounts,
) -> Vec3 {
    if bsdf.is_delta() || scene.lights.is_empty() {
        return Vec3::ZERO;
    }
    let origin = offset_ray_origin(v.p, v.ng_side, v.ng_side, v.eps);
    let Some(ls) = scene.lights.sample(origin, u_light, u_light2) else {
        return Vec3::ZERO;
    };
    // Only the side the path arrived on can receive light for opaque two-sided surfaces.
    if ls.wi.dot(v.ng_side) <= 0.0 {
        return Vec3::ZERO;
    }
    let (f, bsdf_pdf) = bsdf.eval(v.wo, v.frame.to_local(ls.wi));
    if f == Vec3::ZERO {
        return Vec3::ZERO;
    }
    let light_eps =
        (ls.point.abs().max_element() * crate::surface::OFFSET_REL).max(ls.offset_floor);
    let tmax = ls.dist - light_eps;
    if tmax <= 0.0 {
        return Vec3::ZERO;
    }
    work.shadow_rays += 1;
    if scene.plain().occluded(origin, ls.wi, tmax) {
        return Vec3::ZERO;
    }
    let w = if mis {
        power_heuristic(ls.pdf, bsdf_pdf)
    } else {
        1.0
    };
    f * ls.radiance * (w / ls.pdf)
}
