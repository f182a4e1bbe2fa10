//! Estimators attached to instances, and how a path meets them.
//!
//! For a path with at least P bounces whose ray starts outside an estimator
//! instance's bounding sphere, the instance is a sphere: the ray is
//! intersected with the sphere in instance space, the mask decides whether
//! the real mesh would have been hit (a miss skips the instance without
//! touching its BLAS), and a hit whose chord is clear of other geometry
//! becomes an *estimator entry*. Entries are gathered across the wavefront
//! and answered in one batch ([`crate::entry`]: neural decoder, oracle walk
//! or cost floor), then each path continues from its exit.
//!
//! This module holds what an estimator is and how a ray meets one; it does
//! not know the render scene (which holds the estimators) nor the path
//! state, so the modules stay acyclic (tests/module_graph.rs).

use crate::accel::{Accel, InstanceXform, SceneHit};
use crate::bsdf::Bsdf;
use crate::bvh::Visit;
use crate::object_walk::WalkVertex;
use crate::surface::{SurfaceKind, offset_ray_origin};
use glam::Vec3;
use nppp_estimator::{DecodeRepairs, EstimatorSampler, Exit};
use nppp_geom::sphere_pair::{Chord, unit_sphere_chord};
use nppp_geom::{BoundingSphere, Ray, SpherePair};

/// What answers an estimator query.
// A scene holds a handful of these (one per estimator file), so the size of
// the neural variant costs nothing worth a box.
#[allow(clippy::large_enum_variant)]
pub enum EstimatorModel {
    /// A baked neural estimator (its sampler runs whichever decoder backend
    /// was attached to it, the CPU decoder by default).
    Neural { sampler: EstimatorSampler },
    /// Ground truth: traces the object alone from the entry ray. Exact up to
    /// the interaction with other geometry inside the sphere, so it tests the
    /// integration independently of any network.
    Oracle { max_internal_bounces: u32 },
    /// A timing instrument, not an estimate: the baked estimator's mask
    /// decides entries as in a neural render, and every entry is answered
    /// at no cost (no latent lookup, no decoder).
    ///
    /// `continue_with: None` (`--estimators cost-floor`): the entry ends its
    /// path. No estimator that uses this mask can render a sample faster,
    /// so its time bounds what any network could gain on a scene; but a
    /// real estimator's path goes on from its exit, so no real estimator
    /// reaches it either. The image is biased dark by design.
    ///
    /// `continue_with: Some(exit)` (`--estimators free-exits`): the path
    /// goes on from a free exit, straight through the sphere with the
    /// training data's typical throughput and bounce count
    /// ([`typical_exit`]), so it pays for what follows an exit as a real
    /// estimator's path does. Its time is the render's with decoding free:
    /// the gap to a neural render's time is what its entries cost. The
    /// image is not an estimate of the scene.
    CostFloor {
        sampler: EstimatorSampler,
        continue_with: Option<Exit>,
    },
}

/// The exit a free-exits entry continues with (direction and position are
/// the entry's own, straight through): the throughput and internal bounce
/// count of the training data's mean exit features, decoded (standardized
/// features of zero are the data's means; as the features store
/// `ln(1 + x)`, that is the geometric mean of `1 + x`, less 1), and no
/// radiance.
pub fn typical_exit(sampler: &EstimatorSampler) -> Exit {
    let t = &sampler.baked().transform;
    let mut repairs = DecodeRepairs::default();
    let e = t.decode(
        &[0.0; nppp_estimator::EXIT_FEATURES],
        sampler.meta().max_internal_bounces,
        sampler.bounds,
        &mut repairs,
    );
    Exit {
        radiance: Vec3::ZERO,
        ..e
    }
}

pub struct Estimator {
    pub model: EstimatorModel,
    /// In mesh space.
    pub sphere: BoundingSphere,
    /// The scene mesh and the surface it stands for (one estimator serves
    /// one (mesh, material) pair): what the oracle traces, and where
    /// first-vertex NEE finds its vertex.
    pub mesh: usize,
    pub surface: SurfaceKind,
    /// The medium inside the object (translucent), in mesh units.
    pub medium: Option<crate::medium::Medium>,
    /// P for this estimator: used once a path has made this many bounces.
    pub min_bounces: u32,
    /// Next-event estimation through this estimator.
    pub entry_nee: EntryNee,
    /// Where a neural estimator's picked vertex is moved onto the real
    /// surface (built for networks with a vertex head whose object takes
    /// light samples).
    pub surface_snap: Option<crate::surface_snap::SurfaceSnap>,
}

impl Estimator {
    /// Whether its object takes light samples (a non-delta surface): where
    /// next-event estimation through the estimator applies.
    pub fn takes_light_samples(&self) -> bool {
        self.surface.light_sampled_bsdf().is_some()
    }

    /// Whether it is a neural estimator whose file has a vertex head (it
    /// returns a picked vertex for `EntryNee::PickedVertex`).
    pub fn has_vertex_head(&self) -> bool {
        matches!(&self.model, EstimatorModel::Neural { sampler } if sampler.has_vertex_head())
    }

    /// `nee`, where this estimator's object takes light samples; else off
    /// (see [`Estimators::configure`]).
    pub fn applicable_entry_nee(&self, nee: EntryNee) -> EntryNee {
        if self.takes_light_samples() {
            nee
        } else {
            EntryNee::Off
        }
    }

    /// The next-event estimation through this estimator that applies: at
    /// the picked vertex its file's vertex head returns, else at the first
    /// vertex found on the real mesh; off where its object takes no light
    /// sample (delta lobes: smooth glass).
    pub fn light_sampling_entry_nee(&self) -> EntryNee {
        self.applicable_entry_nee(if self.has_vertex_head() {
            EntryNee::PickedVertex
        } else {
            EntryNee::FirstVertex
        })
    }
}

/// All estimators of a scene and which instance uses which.
pub struct Estimators {
    pub list: Vec<Estimator>,
    /// Per instance: index into `list`. Set through
    /// [`Estimators::set_per_instance`], which keeps `sole_instance` in step.
    per_instance: Vec<Option<u32>>,
    /// The smallest P of the estimators in use (each has its own): paths
    /// with fewer bounces need no estimator query at all. Kept by
    /// [`Estimators::configure`] and [`Estimators::configure_one`].
    pub min_bounces: u32,
    /// How an entry reads the latent grid.
    pub latent_lookup: LatentLookup,
    /// Who decides whether an entry ray hits the object.
    pub entry_mask: EntryMask,
    /// The one instance that uses an estimator, when only one does (kept by
    /// the constructor and [`Estimators::configure_one`]): a ray that
    /// starts inside its sphere (a sphere is convex) or misses it can meet
    /// no estimator, so it needs no estimator query and takes the merged
    /// layout (see [`Estimators::cannot_enter`]).
    sole_instance: Option<u32>,
    /// Per instance as loaded, its estimator and that estimator's sphere in
    /// world space (`None` for instances without one):
    /// [`Estimators::cannot_enter`]'s quick test.
    world_spheres: Vec<Option<(u32, WorldSphere)>>,
    /// Per instance: the world box around other geometry inside its
    /// estimator's sphere (`None`: nothing else is inside), for
    /// [`Estimators::exit_origin`]. Until
    /// [`Estimators::set_other_geometry_in_spheres`] says what is where,
    /// every sphere holds an unbounded box: every exit takes the exact
    /// rule, which is always right, the thesis' shortcut only where
    /// nothing else is in the way.
    other_geometry_in_sphere: Vec<Option<(Vec3, Vec3)>>,
}

/// Where the line `o + t d` runs inside the box `b`: its interval of `t`
/// (over the whole line, both ways), `None` where it misses the box.
fn line_in_box(o: Vec3, d: Vec3, b: (Vec3, Vec3)) -> Option<(f32, f32)> {
    // `max` and `min` pass NaN over: a NaN line is refused here.
    if !(o.is_finite() && d.is_finite()) {
        return None;
    }
    let (mut t0, mut t1) = (f32::NEG_INFINITY, f32::INFINITY);
    for k in 0..3 {
        if d[k] == 0.0 {
            if o[k] < b.0[k] || o[k] > b.1[k] {
                return None;
            }
            continue;
        }
        let (a, c) = ((b.0[k] - o[k]) / d[k], (b.1[k] - o[k]) / d[k]);
        t0 = t0.max(a.min(c));
        t1 = t1.min(a.max(c));
    }
    (t0 <= t1).then_some((t0, t1))
}

/// An estimator instance's sphere in world space, for a test that needs no
/// transform of the ray: most of a path's later rays start far from the
/// sphere or inside it and are answered by it alone (on the default scene
/// at P = 1 the exact test's two quaternion rotations and division, for
/// every ray, made the render 2-4% slower). (Used as well for each instance
/// a ray's TLAS search visits in the room, it saved nothing measurable:
/// those rays mostly enter the spheres.)
#[derive(Clone, Copy, Debug)]
struct WorldSphere {
    center: Vec3,
    radius: f32,
    /// What the rounding of either test grows with besides the ray's
    /// origin: the instance's translation and the sphere's centre.
    magnitude: f32,
}

/// How close (relative to the radius) to the sphere's boundary the
/// world-space test leaves a ray to the exact test. The world and
/// object-space arithmetic round differently, by about 1e-7 of the
/// coordinates involved; that part of the margin is added per ray
/// ([`WorldSphere::classify`]).
const WORLD_SPHERE_MARGIN: f32 = 1e-3;

/// Rounding of either test per unit of the coordinates involved, with room
/// to spare (f32's epsilon is 1.2e-7; a few operations each).
const WORLD_SPHERE_ROUNDING: f32 = 2e-6;

impl WorldSphere {
    fn new(sphere: &BoundingSphere, x: &InstanceXform) -> Self {
        let center = x.point_to_world(sphere.center);
        let magnitude = x.translation.abs().max_element()
            + sphere.center.abs().max_element() * x.scale
            + center.abs().max_element();
        Self {
            center,
            radius: sphere.radius * x.scale,
            magnitude,
        }
    }

    /// What the exact test ([`sphere_entry`]) says of a ray from `o` along
    /// the unit direction `d`, where the answer is certain; `None` near the
    /// boundary (and for NaN), where only the exact test decides.
    #[inline(always)]
    fn classify(&self, o: Vec3, d: Vec3) -> Option<WorldEntry> {
        let oc = o - self.center;
        let dist2 = oc.length_squared();
        let margin = self.radius * WORLD_SPHERE_MARGIN
            + WORLD_SPHERE_ROUNDING * (o.abs().max_element() + self.magnitude);
        let (r_in, r_out) = (self.radius - margin, self.radius + margin);
        let (r2_in, r2_out) = (r_in.max(0.0) * r_in.max(0.0), r_out * r_out);
        if dist2 < r2_in {
            return Some(WorldEntry::Inside);
        }
        // Also NaN.
        if dist2.partial_cmp(&r2_out) != Some(std::cmp::Ordering::Greater) {
            return None;
        }
        let b = oc.dot(d);
        if b >= 0.0 {
            // Outside and heading away.
            return Some(WorldEntry::Misses);
        }
        // The line's closest point to the centre, in the same stable form
        // as `unit_sphere_chord`; its rounding grows with the distance
        // (squared bounds: `2 r e |oc| <= e (r^2 + |oc|^2)`).
        let closest2 = (oc - d * b).length_squared();
        let slack = WORLD_SPHERE_ROUNDING * dist2;
        if closest2 > r2_out * (1.0 + WORLD_SPHERE_ROUNDING) + slack {
            Some(WorldEntry::Misses)
        } else if closest2 < r2_in * (1.0 - WORLD_SPHERE_ROUNDING) - slack {
            Some(WorldEntry::Enters)
        } else {
            None
        }
    }
}

/// [`WorldSphere::classify`]'s answers: [`SphereEntry`]'s cases without
/// the ray in the sphere's frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum WorldEntry {
    Inside,
    Misses,
    Enters,
}

/// Where a world ray starts and heads against an estimator instance's
/// sphere: the one test [`Estimators::intersect`] and
/// [`Estimators::cannot_enter`] both make, so that they agree bit for bit.
enum SphereEntry {
    /// The ray starts inside the sphere (a sphere is convex: it never
    /// enters it).
    Inside,
    /// It does not enter the sphere ahead.
    Misses,
    /// It enters: its origin in object space, the ray in the sphere's unit
    /// frame (object-space direction), and its chord there.
    Enters {
        oo: Vec3,
        unit_ray: Ray,
        chord: Chord,
    },
}

#[inline(always)]
fn sphere_entry(sphere: &BoundingSphere, x: &InstanceXform, o: Vec3, d: Vec3) -> SphereEntry {
    let oo = x.point_to_object(o);
    let uo = sphere.to_unit_point(oo);
    // Outside only when `> 1`: a NaN origin counts as inside (its mesh is
    // traced).
    if uo.length_squared() > 1.0 {
        let unit_ray = Ray::new(uo, x.dir_to_object(d));
        match unit_sphere_chord(&unit_ray) {
            None => SphereEntry::Misses,
            Some(chord) if chord.t_in < 0.0 => SphereEntry::Misses,
            Some(chord) => SphereEntry::Enters {
                oo,
                unit_ray,
                chord,
            },
        }
    } else {
        SphereEntry::Inside
    }
}

/// Who decides whether a ray entering an estimator's sphere hits the object
/// (and is answered by the estimator) or passes by.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum EntryMask {
    /// The real mesh for translucent objects, the learned mask grid for the
    /// rest. A translucent entry replaces ~100 internal BVH queries, so one
    /// more keeps the silhouette exact at P = 0 (the 64^4 mask grid drew the
    /// jade knot visibly fatter) for about a tenth of the render's time
    /// (cornell-jade at P = 0: 0.21x PT's time instead of 0.19x).
    #[default]
    Auto,
    /// The baked mask grid (the thesis): no BVH query per entry.
    Learned,
    /// A closest-hit query of the object's own BVH: the exact silhouette.
    Exact,
}

/// How a neural estimator reads its latent grid at an entry.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum LatentLookup {
    /// Quadrilinear interpolation of the 16 corners (the thesis' lookup).
    #[default]
    Interpolate,
    /// One corner picked with the probability of its weight (stochastic
    /// filtering): one memory access instead of 16, unbiased in expectation
    /// over the mixture of the corners' distributions.
    Stochastic,
}

/// Next-event estimation through an estimator: which skipped vertex gets a
/// light sample, and which exits are then weighted by MIS against it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum EntryNee {
    /// None (the thesis): an emitter the exit ray hits counts fully.
    #[default]
    Off,
    /// The entry's first vertex, found by tracing the entry ray against the
    /// real mesh (one closest-hit query of its BVH); an exit that left after
    /// that one bounce is weighted by MIS against the light sample there
    /// (the BSDF pdf at the first vertex towards the exit direction). Needs
    /// nothing from the estimator beyond its exit, so it works with any
    /// estimator file; exact for the oracle.
    FirstVertex,
    /// One vertex of the skipped path, picked in proportion to its
    /// throughput. The oracle weights its light sample by MIS against the
    /// last vertex's BSDF sample (the exit ray's emitter hit). A network's
    /// vertex head has learned the picked vertex's distribution alone, not
    /// jointly with the exit (it runs on the exit's noise, which its
    /// expectation does not depend on), so there is no last vertex to weight
    /// against: the light sample counts
    /// alone and the exit's emitter hit counts 0 (as [`Self::PickedVertexLightOnly`]).
    /// Needs the oracle or an estimator file with a vertex head.
    PickedVertex,
    /// [`Self::PickedVertex`] without MIS, for any estimator: the light at
    /// the skipped vertices is the light sample's alone, an emitter hit by
    /// the exit ray counts 0. Lets the oracle measure the network's scheme.
    PickedVertexLightOnly,
}

impl EntryNee {
    /// Whether the estimator returns a picked vertex of the skipped path.
    pub fn is_picked(self) -> bool {
        matches!(
            self,
            EntryNee::PickedVertex | EntryNee::PickedVertexLightOnly
        )
    }
}

/// The skipped vertices of one entry as the renderer uses them (mesh space).
#[derive(Clone, Copy, Debug, Default)]
pub struct SkippedVertices {
    /// The vertex for next-event estimation, picked among the vertices where
    /// it may happen in proportion to the luminance of their throughput; its
    /// `beta` is already divided by the probability of the pick.
    pub nee: Option<(WalkVertex, Bsdf)>,
    /// The last vertex's position and the solid-angle pdf of its BSDF sample
    /// (the exit direction); `None` for a delta lobe or no vertex (an emitter
    /// hit next counts with MIS weight 1).
    pub last: Option<(Vec3, f32)>,
    /// The light at the skipped vertices is the light sample's alone (MIS
    /// weight 1) and an emitter hit by the exit ray counts 0; `last` is then
    /// unused. The picked-vertex scheme of a network, whose vertex is not
    /// tied to its exit.
    pub light_alone: bool,
}

/// Picks the vertex for next-event estimation among `verts` (those before
/// `budget` internal bounces: NEE there still fits under M) with
/// probability proportional to the luminance of its throughput, using `u`.
pub fn pick_skipped(verts: &[WalkVertex], bsdf: Bsdf, budget: u32, u: f32) -> SkippedVertices {
    let last = verts
        .last()
        .filter(|v| !v.delta && v.pdf > 0.0)
        .map(|v| (v.point, v.pdf));
    let weight = |v: &WalkVertex| {
        if v.index < budget {
            nppp_geom::luminance(v.beta).max(0.0)
        } else {
            0.0
        }
    };
    let total: f32 = verts.iter().map(weight).sum();
    if bsdf.is_delta() || !total.is_finite() || total <= 0.0 {
        return SkippedVertices {
            nee: None,
            last,
            light_alone: false,
        };
    }
    let mut target = u * total;
    let mut chosen = None;
    for v in verts {
        let w = weight(v);
        if w <= 0.0 {
            continue;
        }
        chosen = Some((*v, w));
        if target < w {
            break;
        }
        target -= w;
    }
    let nee = chosen.map(|(mut v, w)| {
        v.beta *= total / w;
        (v, bsdf)
    });
    SkippedVertices {
        nee,
        last,
        light_alone: false,
    }
}

/// How far (in sphere radii) a network's picked vertex is moved along its
/// normal, to the side the path arrived on, before its light sample, where
/// it cannot be moved onto the real surface ([`crate::surface_snap`]: no
/// triangle within its reach). The vertex head's positions scatter around
/// the surface (0.06-0.08 radii from the nearest real vertex on the knot's
/// held-out rays), and a light sample taken from inside the object is
/// shadowed by the object itself. On the default scene at 64 spp (P = 0 /
/// P = 1, image mean against the reference's 0.2112 in red), before the
/// vertices were moved onto the surface: offset 0 gave relMSE 0.00432 / -
/// and mean 0.2063; 0.01: 0.00351 / 0.00180, 0.2075 / 0.2091; 0.03:
/// 0.00294 / 0.00181, 0.2091 / 0.2101; 0.05: 0.00290 / 0.00185, 0.2099 /
/// 0.2107.
const NETWORK_VERTEX_OFFSET: f32 = 0.04;

/// How far (in sphere radii) a picked vertex moved onto the real surface is
/// lifted off it, along the real normal to the side the path arrived on,
/// before its light sample. From the surface itself the shadow ray starts
/// among the triangles around it, which its traversal then tests: on the
/// default scene at P = 1 that took 1.09x PT's time where the lifted ray
/// takes 1.05x (0.02: 1.05x; the vertex pushed 0.04 along its predicted
/// normal, before it was moved onto the surface: 1.04x). The image mean
/// moved by less than its noise at P = 1 on the side-lit scenes of
/// BENCHMARKS.md ("The picked vertex on the real surface").
const SURFACE_VERTEX_LIFT: f32 = 0.01;

/// The picked vertex a network's vertex head returned (unit sphere frame)
/// as the renderer uses it: in mesh space, on the real surface (lifted by
/// `SURFACE_VERTEX_LIFT`) where `on_surface` finds a point there
/// (mesh-space point, geometric and shading normals, from the predicted
/// mesh-space position) that faces as the prediction does (its winding
/// normal on the predicted normal's side, and the path arriving on the
/// same side of it: a point of the other side
/// of a thin part is not where the path scattered), else moved off the
/// surface by `NETWORK_VERTEX_OFFSET`; no light sample when it carries no
/// throughput or lies past the `budget` of bounces left; the light at the
/// skipped vertices counted by the light sample alone.
pub fn network_skipped(
    v: &nppp_estimator::PickedVertex,
    sphere: &BoundingSphere,
    bsdf: Bsdf,
    budget: u32,
    on_surface: impl FnOnce(Vec3) -> Option<(Vec3, Vec3, Vec3)>,
) -> SkippedVertices {
    let usable = v.beta.max_element() > 0.0 && v.index < budget && !bsdf.is_delta();
    let nee = usable.then(|| {
        let faces_alike = |&(_, ng, _): &(Vec3, Vec3, Vec3)| {
            ng.dot(v.normal) > 0.0 && (ng.dot(v.wo) > 0.0) == (v.normal.dot(v.wo) > 0.0)
        };
        let surface = on_surface(sphere.from_unit_point(v.position)).filter(faces_alike);
        let surface = surface.map(|(p, ng, ns)| {
            let lift = SURFACE_VERTEX_LIFT * sphere.radius;
            (offset_ray_origin(p, ng, v.wo, lift), ng, ns)
        });
        let (point, ng, ns) = surface.unwrap_or_else(|| {
            let pushed = offset_ray_origin(v.position, v.normal, v.wo, NETWORK_VERTEX_OFFSET);
            (sphere.from_unit_point(pushed), v.normal, v.normal)
        });
        let vertex = WalkVertex {
            point,
            ng,
            ns,
            wo: v.wo,
            beta: v.beta,
            index: v.index,
            pdf: 0.0,
            delta: false,
        };
        (vertex, bsdf)
    });
    SkippedVertices {
        nee,
        last: None,
        light_alone: true,
    }
}

/// First-vertex NEE for one entry: the light sample at `first` (if it fits
/// under M: `budget` > 0), and, when the exit left after exactly that one
/// bounce, the BSDF pdf at `first` towards the exit direction for MIS. An
/// exit direction the first vertex cannot scatter to (pdf 0: a network's
/// exit that disagrees with the real surface) counts fully instead.
pub fn first_vertex_skipped(
    first: Option<WalkVertex>,
    bsdf: Bsdf,
    budget: u32,
    exit: &Exit,
) -> SkippedVertices {
    let Some(v) = first else {
        return SkippedVertices::default();
    };
    if bsdf.is_delta() || budget == 0 {
        return SkippedVertices::default();
    }
    let last = (exit.bounces == 1)
        .then(|| {
            let (frame, _) = crate::surface::shading_frame(&bsdf, v.ng, v.ns, v.wo);
            let (_, pdf) = bsdf.eval(frame.to_local(v.wo), frame.to_local(exit.direction));
            (v.point, pdf)
        })
        .filter(|(_, pdf)| *pdf > 0.0 && pdf.is_finite());
    SkippedVertices {
        nee: Some((v, bsdf)),
        last,
        light_alone: false,
    }
}

/// A path's ray entering an estimator sphere, in that estimator's unit frame.
#[derive(Clone, Copy, Debug)]
pub struct EstimatorEntry {
    pub instance: u32,
    /// Starts at the sphere entry point.
    pub ray: Ray,
    pub pair: SpherePair,
}

/// What a path's ray meets next.
#[derive(Clone, Copy, Debug)]
pub enum Meet {
    Nothing,
    Surface(SceneHit),
    Estimator(EstimatorEntry),
}

/// Counters reported at the end of a render.
#[derive(Clone, Copy, Debug, Default)]
pub struct EstimatorStats {
    pub entries: u64,
    /// Rays through a sphere that skipped its instance: the mesh's BVH root
    /// boxes were missed (certain), or the mask said miss.
    pub mask_skips: u64,
    /// Rays whose closest other hit fell inside the chord: traced for real.
    pub ambiguous: u64,
    pub repairs: DecodeRepairs,
    /// Exits whose internal bounces took the path past M.
    pub over_max_bounces: u64,
    /// Batches the configured decoder failed on (answered by the CPU decoder).
    pub decoder_fallbacks: u64,
    /// Decoder calls (one per neural estimator per wavefront step with
    /// entries): `entries / decoder_batches` is the batch size a decoder
    /// backend sees in this render.
    pub decoder_batches: u64,
    /// Decoder rows run: one per neural entry, and one more per entry whose
    /// picked vertex a vertex head decoded.
    pub decoder_rows: u64,
    /// Their multiply-adds (rows times each decoder's size).
    pub decoder_multiply_adds: u64,
    /// Standard normals drawn as their noise.
    pub decoder_normals: u64,
    /// Exit rays started at the object's last crossing of their line, for
    /// other geometry inside the sphere ([`Estimators::exit_origin`]).
    pub exits_from_object: u64,
}

impl EstimatorStats {
    /// `rows` decoder rows of `multiply_adds` each, with `noise_dim`
    /// standard normals each.
    pub fn count_decoder_rows(&mut self, rows: usize, multiply_adds: usize, noise_dim: usize) {
        self.decoder_rows += rows as u64;
        self.decoder_multiply_adds += (rows * multiply_adds) as u64;
        self.decoder_normals += (rows * noise_dim) as u64;
    }

    pub fn merge(&mut self, o: &EstimatorStats) {
        self.entries += o.entries;
        self.mask_skips += o.mask_skips;
        self.ambiguous += o.ambiguous;
        self.over_max_bounces += o.over_max_bounces;
        self.decoder_fallbacks += o.decoder_fallbacks;
        self.decoder_batches += o.decoder_batches;
        self.decoder_rows += o.decoder_rows;
        self.decoder_multiply_adds += o.decoder_multiply_adds;
        self.decoder_normals += o.decoder_normals;
        self.exits_from_object += o.exits_from_object;
        self.repairs.degenerate += o.repairs.degenerate;
        self.repairs.inward += o.repairs.inward;
        self.repairs.clamped += o.repairs.clamped;
        self.repairs.vertices += o.repairs.vertices;
    }
}

struct Candidate {
    t_in: f32,
    t_out: f32,
    entry: EstimatorEntry,
}

impl Estimators {
    /// True when a ray from `o` along `d` certainly meets no estimator: the
    /// scene has one estimator instance, and the ray starts inside its
    /// sphere or does not enter it ahead (the same tests, in the same
    /// arithmetic, as [`Estimators::intersect`]). Such a ray is traced in
    /// the merged layout: one traversal instead of the merged BLAS, the
    /// TLAS and the instance's BLAS through its transform. Rays from inside
    /// are the walk of a path in a glass or translucent object the camera
    /// sees at P >= 1 and rays leaving an opaque object after a bounce
    /// below P (on cornell-glass at P = 1 the two-level queries took 16% of
    /// the render); rays that miss the sphere are most of a path's later
    /// rays.
    #[inline]
    pub fn cannot_enter(&self, accel: &Accel, o: Vec3, d: Vec3) -> bool {
        let Some(inst) = self.sole_instance else {
            return false;
        };
        let Some(ei) = self.per_instance[inst as usize] else {
            return false;
        };
        if let Some(answer) = self.world_entry(inst, ei, o, d) {
            return answer != WorldEntry::Enters;
        }
        let x = &accel.instances[inst as usize];
        !matches!(
            sphere_entry(&self.list[ei as usize].sphere, x, o, d),
            SphereEntry::Enters { .. }
        )
    }

    /// [`WorldSphere::classify`] of instance `inst`'s sphere, where it
    /// has estimator `ei`'s (as loaded) and is certain.
    #[inline(always)]
    fn world_entry(&self, inst: u32, ei: u32, o: Vec3, d: Vec3) -> Option<WorldEntry> {
        match self.world_spheres.get(inst as usize) {
            Some(&Some((e, world))) if e == ei => world.classify(o, d),
            _ => None,
        }
    }

    /// Closest-hit query for a path that may use estimators. `skip` is an
    /// instance the ray has just left through its estimator (ignored entirely).
    pub fn intersect(
        &self,
        accel: &Accel,
        o: Vec3,
        d: Vec3,
        skip: u32,
        depth: u32,
        stats: &mut EstimatorStats,
    ) -> Meet {
        // Estimator instances are never merged: the merged world BLAS only
        // sets how far the TLAS has to look.
        let mut best: Option<SceneHit> = accel.merged_hit(o, d, f32::INFINITY);
        let tmax = best.map_or(f32::INFINITY, |h| h.t);
        let mut cand: Option<Candidate> = None;
        let mut chords_overlap = false;
        // Per instance: the distance the search may shrink to (INFINITY: no change).
        let mut visit = |inst: u32, tmax: f32| -> f32 {
            if inst == skip {
                return f32::INFINITY;
            }
            if let Some(ei) = self.per_instance[inst as usize]
                && depth >= self.list[ei as usize].min_bounces
            {
                let x = &accel.instances[inst as usize];
                let est = &self.list[ei as usize];
                match sphere_entry(&est.sphere, x, o, d) {
                    // A ray from inside the sphere never uses it: trace the mesh.
                    SphereEntry::Inside => {}
                    SphereEntry::Misses => return f32::INFINITY,
                    SphereEntry::Enters {
                        oo,
                        unit_ray,
                        chord,
                    } => {
                        let od = unit_ray.dir;
                        // Something closer hides the sphere: nothing to ask.
                        let to_world = est.sphere.radius * x.scale;
                        let (t_in, t_out) = (chord.t_in * to_world, chord.t_out * to_world);
                        if t_in >= tmax {
                            return f32::INFINITY;
                        }
                        // A ray that misses every box under the mesh's BVH root
                        // certainly misses the mesh: no mask lookup (two memory
                        // misses in an 8 MiB grid) for what geometry already
                        // knows. The mask judges only rays that could hit.
                        if !accel.blas[x.blas as usize].may_hit(oo.into(), od.into()) {
                            stats.mask_skips += 1;
                            return f32::INFINITY;
                        }
                        let entry_p = unit_ray.at(chord.t_in);
                        let pair = SpherePair::from_points(entry_p, unit_ray.at(chord.t_out));
                        if !self.mask_hits(est, accel, &Ray::new(entry_p, od), &pair) {
                            stats.mask_skips += 1;
                            return f32::INFINITY;
                        }
                        if let Some(c) = &cand
                            && t_in < c.t_out
                            && c.t_in < t_out
                        {
                            // Two estimators' chords overlap: neither knows the
                            // other's object, so the ray is traced for real.
                            chords_overlap = true;
                        }
                        if cand.as_ref().is_none_or(|c| t_in < c.t_in) {
                            cand = Some(Candidate {
                                t_in,
                                t_out,
                                entry: EstimatorEntry {
                                    instance: inst,
                                    ray: Ray::new(entry_p, od),
                                    pair,
                                },
                            });
                        }
                        // Geometry inside the chord must still be found (it makes
                        // the ray ambiguous), anything past its far end cannot
                        // change the answer: the traversal stops there.
                        return t_out;
                    }
                }
            }
            match accel.item_hit(inst, o, d, tmax) {
                Some(h) => {
                    best = Some(h);
                    h.t
                }
                None => f32::INFINITY,
            }
        };
        accel
            .tlas
            .traverse(o.into(), d.into(), tmax, true, |item, tmax| {
                *tmax = tmax.min(visit(accel.tlas_items[item as usize], *tmax));
                Visit::Continue
            });
        if chords_overlap {
            stats.ambiguous += 1;
            return accel
                .intersect_skipping(o, d, f32::INFINITY, skip)
                .map_or(Meet::Nothing, Meet::Surface);
        }
        match (cand, best) {
            (None, None) => Meet::Nothing,
            (None, Some(h)) => Meet::Surface(h),
            (Some(c), None) => Meet::Estimator(c.entry),
            (Some(c), Some(h)) if h.t < c.t_in => Meet::Surface(h),
            (Some(c), Some(h)) if h.t > c.t_out => Meet::Estimator(c.entry),
            (Some(c), Some(h)) => {
                // Other geometry inside the chord: the order of events is
                // ambiguous, so this one ray is traced against the real mesh.
                // `h` is already the closest of everything else up to the
                // chord's end, so the candidate's own mesh is all that is
                // left to trace.
                stats.ambiguous += 1;
                Meet::Surface(accel.item_hit(c.entry.instance, o, d, h.t).unwrap_or(h))
            }
        }
    }

    fn mask_hits(&self, est: &Estimator, accel: &Accel, unit_ray: &Ray, pair: &SpherePair) -> bool {
        let exact = match self.entry_mask {
            EntryMask::Auto => est.medium.is_some(),
            EntryMask::Learned => false,
            EntryMask::Exact => true,
        };
        match &est.model {
            EstimatorModel::Neural { sampler } | EstimatorModel::CostFloor { sampler, .. }
                if !exact =>
            {
                sampler.hits(pair)
            }
            _ => {
                let o = est.sphere.from_unit_point(unit_ray.origin);
                accel.blas[est.mesh]
                    .intersect(o.into(), unit_ray.dir.into(), 0.0, f32::INFINITY)
                    .is_some()
            }
        }
    }
}

/// Which estimators a render uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum EstimatorMode {
    /// Plain path tracing: `estimator` keys are ignored and no estimator code runs.
    Off,
    /// The baked `.nppp` files the scene names.
    Neural,
    /// Ground-truth walks through the real object for every instance that names an estimator.
    Oracle,
    /// The baked files' masks, every entry ending its path: see
    /// [`EstimatorModel::CostFloor`]. For timing only.
    CostFloor,
    /// The baked files' masks, every entry going on from a free exit: see
    /// [`EstimatorModel::CostFloor`]. For timing only.
    FreeExits,
}

#[derive(Debug, thiserror::Error)]
pub enum EstimatorLoadError {
    /// The file itself is unusable (its error names the file).
    #[error("instances[{instance}].estimator: {err}")]
    File {
        instance: usize,
        err: nppp_estimator::EstimatorFileError,
    },
    #[error(
        "instances[{instance}].estimator: {file}: this estimator was trained for mesh \"{trained_mesh}\" (hash {trained_mesh_hash:016x}) with material \"{trained_material}\" (hash {trained_material_hash:016x}), but the instance uses mesh \"{mesh}\" (hash {mesh_hash:016x}) with material \"{material}\" (hash {material_hash:016x}): {what_differs}. An estimator answers for one mesh and material only: train one for this instance (`nppp gen --scene SCENE --instance {instance}`, then `nppp train` and `nppp bake`: README, \"Set up\"), remove the instance's `estimator` key, or render with `--estimators off`"
    )]
    Mismatch {
        file: std::path::PathBuf,
        instance: usize,
        trained_mesh: String,
        trained_mesh_hash: u64,
        trained_material: String,
        trained_material_hash: u64,
        mesh: String,
        mesh_hash: u64,
        material: String,
        material_hash: u64,
        /// Which of the two differs, in words (a material of the same name
        /// with other parameters differs by its hash alone).
        what_differs: &'static str,
    },
    #[error(
        "instances[{instance}].estimator: {file}: its bounding sphere (centre {center}, radius {radius}) does not fit mesh \"{mesh}\" (centre {mesh_center}, radius {mesh_radius}): the file is damaged or was made for other geometry"
    )]
    Sphere {
        file: std::path::PathBuf,
        instance: usize,
        center: Vec3,
        radius: f32,
        mesh: String,
        mesh_center: Vec3,
        mesh_radius: f32,
    },
}

/// Which file an `estimator` key names: one file under any spelling (`m/x`,
/// `./m/x`, a link) is one estimator (four spellings of the knot's file
/// were loaded four times, 65 MiB for 16, and decided on apart by `auto`).
pub(crate) fn estimator_file_key(path: &std::path::Path) -> std::path::PathBuf {
    std::fs::canonicalize(path).unwrap_or_else(|_| path.to_path_buf())
}

/// Whether instance `ii` is a lamp. A path that reaches an emitter ends
/// there, so an estimator has nothing to skip; and the light a lamp's
/// estimator would return is light the vertex before the entry has already
/// sampled, which the exit rule adds without a MIS weight: an oracle on a
/// lamp over a floor rendered 6% bright. Such an instance is traced for
/// real, and the renderer says so ([`unused_on_emitters`]).
pub(crate) fn on_emitter(scene: &nppp_scene::Scene, ii: usize) -> bool {
    let inst = &scene.instances[ii];
    inst.estimator.is_some()
        && matches!(
            scene.materials[inst.material],
            nppp_scene::Material::Emitter { .. }
        )
}

/// What the renderer tells the user about estimators named on emitter
/// instances, which it leaves unused (see [`on_emitter`]): one line naming
/// the first few, empty when there are none.
pub fn unused_on_emitters(scene: &nppp_scene::Scene) -> Option<String> {
    const NAMED: usize = 3;
    let found: Vec<usize> = (0..scene.instances.len())
        .filter(|&i| on_emitter(scene, i))
        .collect();
    let first = *found.first()?;
    let mut names: Vec<String> = found
        .iter()
        .take(NAMED)
        .map(|i| format!("instances[{i}].estimator"))
        .collect();
    if found.len() > NAMED {
        names.push(format!("{} more", found.len() - NAMED));
    }
    Some(format!(
        "{} not used: the material \"{}\" is an emitter, which ends every path that reaches it \
         (nothing to skip) and whose light is sampled directly; the instance is traced for real",
        names.join(", ") + if found.len() > 1 { " are" } else { " is" },
        scene.material_names[scene.instances[first].material]
    ))
}

/// Internal bounce cap of the oracle. Each walk also stops where the path
/// runs out of bounces (M minus its depth: whatever happens later is cut by
/// M anyway), so the oracle is the real object at every M up to this,
/// dense media included, and never walks further than the path may go.
pub const ORACLE_MAX_INTERNAL_BOUNCES: u32 = 1 << 16;

impl Estimators {
    /// Builds the scene's estimators; one file loaded once serves every
    /// instance that names it. Returns `None` for `Off` or when no instance
    /// has an estimator, so such renders run no estimator code.
    // Loading runs once per render; a large error value is no cost.
    #[allow(clippy::result_large_err)]
    pub fn load(
        scene: &nppp_scene::Scene,
        mode: EstimatorMode,
        min_bounces: u32,
    ) -> Result<Option<Self>, EstimatorLoadError> {
        if mode == EstimatorMode::Off || scene.instances.iter().all(|i| i.estimator.is_none()) {
            return Ok(None);
        }
        let mut list: Vec<Estimator> = Vec::new();
        let mut by_key: std::collections::HashMap<(std::path::PathBuf, usize, usize), u32> =
            Default::default();
        let mut per_instance = vec![None; scene.instances.len()];
        for (ii, inst) in scene.instances.iter().enumerate() {
            let Some(path) = &inst.estimator else {
                continue;
            };
            if on_emitter(scene, ii) {
                // Traced for real: see `unused_on_emitters`.
                continue;
            }
            let key = (estimator_file_key(path), inst.mesh, inst.material);
            if let Some(&e) = by_key.get(&key) {
                per_instance[ii] = Some(e);
                continue;
            }
            let mesh = &scene.meshes[inst.mesh];
            let surface = SurfaceKind::of(&scene.materials[inst.material]);
            let medium = crate::medium::Medium::of(&scene.materials[inst.material]);
            let est = match mode {
                EstimatorMode::Oracle => Estimator {
                    model: EstimatorModel::Oracle {
                        max_internal_bounces: ORACLE_MAX_INTERNAL_BOUNCES,
                    },
                    sphere: BoundingSphere::around(&mesh.positions, nppp_estimator::SPHERE_MARGIN),
                    mesh: inst.mesh,
                    surface,
                    medium,
                    min_bounces,
                    entry_nee: EntryNee::Off,
                    surface_snap: None,
                },
                _ => {
                    let file_err = |err| EstimatorLoadError::File { instance: ii, err };
                    let baked = nppp_estimator::BakedEstimator::load(path).map_err(file_err)?;
                    let mesh_hash = nppp_scene::mesh_content_hash(mesh);
                    let material_hash =
                        nppp_scene::material_content_hash(&scene.materials[inst.material]);
                    if baked.meta.mesh_hash != mesh_hash
                        || baked.meta.material_hash != material_hash
                    {
                        return Err(EstimatorLoadError::Mismatch {
                            file: path.clone(),
                            instance: ii,
                            trained_mesh: baked.meta.mesh_name.clone(),
                            trained_mesh_hash: baked.meta.mesh_hash,
                            trained_material: baked.meta.material_name.clone(),
                            trained_material_hash: baked.meta.material_hash,
                            mesh: scene.mesh_names[inst.mesh].clone(),
                            mesh_hash,
                            material: scene.material_names[inst.material].clone(),
                            material_hash,
                            what_differs: match (
                                baked.meta.mesh_hash != mesh_hash,
                                baked.meta.material_hash != material_hash,
                            ) {
                                (true, true) => {
                                    "the mesh's triangles and the material's parameters differ"
                                }
                                (true, false) => "the mesh's triangles differ",
                                _ => "the material's parameters differ",
                            },
                        });
                    }
                    let sphere = baked.meta.sphere;
                    // The hashes match, so the sphere is the one `nppp gen`
                    // put around this mesh, unless the file was forged or
                    // damaged past its checksum: a sphere that does not
                    // enclose the mesh, or dwarfs it, would render the object
                    // in the wrong place or not at all.
                    let own =
                        BoundingSphere::around(&mesh.positions, nppp_estimator::SPHERE_MARGIN);
                    let reach = sphere.radius * 1.001 + 1e-6 * sphere.center.abs().max_element();
                    let encloses = mesh
                        .positions
                        .iter()
                        .all(|p| p.distance(sphere.center) <= reach);
                    if !encloses || sphere.radius > 4.0 * own.radius {
                        return Err(EstimatorLoadError::Sphere {
                            file: path.clone(),
                            instance: ii,
                            center: sphere.center,
                            radius: sphere.radius,
                            mesh: scene.mesh_names[inst.mesh].clone(),
                            mesh_center: own.center,
                            mesh_radius: own.radius,
                        });
                    }
                    let mut sampler = EstimatorSampler::try_new(baked).map_err(file_err)?;
                    // Every entry reads 16 scattered nodes of each grid.
                    crate::huge_pages::collapse(&sampler.baked().latent.data);
                    crate::huge_pages::collapse(&sampler.baked().mask.data);
                    let emitted = match surface {
                        SurfaceKind::Emitter { radiance } => radiance.max_element(),
                        SurfaceKind::Scatter(_) => 0.0,
                    };
                    sampler.bounds = nppp_estimator::ExitBounds::new(medium.is_some(), emitted);
                    let model = match mode {
                        EstimatorMode::CostFloor => EstimatorModel::CostFloor {
                            sampler,
                            continue_with: None,
                        },
                        EstimatorMode::FreeExits => EstimatorModel::CostFloor {
                            continue_with: Some(typical_exit(&sampler)),
                            sampler,
                        },
                        _ => EstimatorModel::Neural { sampler },
                    };
                    let mut est = Estimator {
                        model,
                        sphere,
                        mesh: inst.mesh,
                        surface,
                        medium,
                        min_bounces,
                        entry_nee: EntryNee::Off,
                        surface_snap: None,
                    };
                    if est.has_vertex_head() && est.takes_light_samples() {
                        est.surface_snap =
                            Some(crate::surface_snap::SurfaceSnap::build(mesh, &sphere));
                    }
                    est
                }
            };
            list.push(est);
            let id = (list.len() - 1) as u32;
            by_key.insert(key, id);
            per_instance[ii] = Some(id);
        }
        let world_spheres = scene
            .instances
            .iter()
            .zip(&per_instance)
            .map(|(inst, e)| {
                e.map(|e| {
                    let x = InstanceXform::new(0, &inst.transform);
                    (e, WorldSphere::new(&list[e as usize].sphere, &x))
                })
            })
            .collect();
        let mut estimators = Self {
            other_geometry_in_sphere: vec![
                Some((Vec3::NEG_INFINITY, Vec3::INFINITY));
                per_instance.len()
            ],
            list,
            per_instance,
            world_spheres,
            min_bounces,
            latent_lookup: LatentLookup::Interpolate,
            entry_mask: EntryMask::Auto,
            sole_instance: None,
        };
        estimators.find_sole_instance();
        Ok(Some(estimators))
    }

    /// Says, per instance, where other geometry lies inside its
    /// estimator's sphere
    /// ([`crate::estimator_overlap::find_other_geometry_in_spheres`]).
    pub fn set_other_geometry_in_spheres(&mut self, per_instance: Vec<Option<(Vec3, Vec3)>>) {
        assert_eq!(per_instance.len(), self.per_instance.len());
        self.other_geometry_in_sphere = per_instance;
    }

    /// The world box around other geometry inside the sphere of instance
    /// `inst`'s estimator, as [`Estimators::exit_origin`] uses it.
    pub fn other_geometry_in_sphere(&self, inst: usize) -> Option<(Vec3, Vec3)> {
        self.other_geometry_in_sphere.get(inst).copied().flatten()
    }

    /// Where the exit ray of exit `e` of instance `inst` (estimator `est`)
    /// starts, in the object's space.
    ///
    /// The thesis' rule starts it at the middle of the exit line's chord
    /// through the sphere. The instance itself is skipped by the next
    /// query, so any point of the line between the object's last crossing
    /// and the sphere's boundary serves where nothing else is inside the
    /// sphere. Other geometry inside it can lie between that crossing and
    /// the middle, on either side: an exit from the mouth of a tube lying
    /// on a floor, falling to the floor, started under it and missed it
    /// (at P = 0 and M = 2 a block beside the lit mouth rendered at 0.41
    /// of PT's brightness), and one rising towards a lamp started under
    /// the floor and was stopped by it (the tube 2.3% dark at P = 1). So
    /// where the line meets the other geometry's box between the middle
    /// and the object's box (where the crossing is), the ray starts at the
    /// object's last crossing: the first hit of the object's own BVH
    /// looking back from where the line leaves the sphere. The object's
    /// convex hull holds no other geometry ([`crate::estimator_overlap`]),
    /// so this is exact for the oracle; a network's line takes the same
    /// rule, and the middle where it misses the object. The default
    /// scene's knot's sphere cuts the floor, but no exit line meets it
    /// near the knot (no query, the image bit for bit as before); in the
    /// room, whose knots' spheres all cut the floor, 5% of the entries
    /// take the query, and the image moves within rounding.
    #[inline]
    pub fn exit_origin(
        &self,
        accel: &Accel,
        inst: u32,
        est: &Estimator,
        e: &Exit,
        stats: &mut EstimatorStats,
    ) -> Vec3 {
        let middle = est
            .sphere
            .from_unit_point(e.position - e.direction * e.position.dot(e.direction));
        let Some(other) = self.other_geometry_in_sphere[inst as usize] else {
            return middle;
        };
        // Along the line from the middle (t = 0): where it meets the other
        // geometry's box (world space: its distances are the object's
        // times the scale; most lines miss it, so it is asked first), and
        // where the object's box (its own, tight in its space) holds the
        // crossing, padded far above rounding.
        let x = &accel.instances[inst as usize];
        let (o, d) = (x.point_to_world(middle), x.dir_to_world(e.direction));
        let Some((o0, o1)) = line_in_box(o, d, other) else {
            return middle;
        };
        let Some((b0, b1)) = line_in_box(middle, e.direction, accel.blas[est.mesh].bounds) else {
            return middle;
        };
        let slack = 1e-4 * est.sphere.radius;
        let (lo, hi) = (
            (b0.min(0.0) - slack) * x.scale,
            (b1.max(0.0) + slack) * x.scale,
        );
        if o0 > hi || o1 < lo {
            return middle;
        }
        stats.exits_from_object += 1;
        let far = est.sphere.from_unit_point(e.position);
        let chord = 2.0 * est.sphere.radius;
        match accel.blas[est.mesh].intersect(far.into(), (-e.direction).into(), 0.0, chord) {
            Some(h) => far - e.direction * h.t,
            None => middle,
        }
    }

    /// Per instance: index into `list`, `None` where the instance is traced
    /// as plain geometry.
    pub fn per_instance(&self) -> &[Option<u32>] {
        &self.per_instance
    }

    /// Which estimator each instance uses (`None`: traced as plain
    /// geometry).
    pub fn set_per_instance(&mut self, per_instance: Vec<Option<u32>>) {
        self.per_instance = per_instance;
        self.find_sole_instance();
    }

    fn find_sole_instance(&mut self) {
        let mut users = (0u32..)
            .zip(&self.per_instance)
            .filter(|(_, e)| e.is_some());
        self.sole_instance = match (users.next(), users.next()) {
            (Some((i, _)), None) => Some(i),
            _ => None,
        };
    }

    /// Sets P and the entry NEE of every estimator. An estimator whose
    /// object takes no light samples (smooth glass, a smooth mirror, a
    /// translucent boundary) keeps its entry NEE off: there is nothing to
    /// sample at its vertices, and every entry-NEE scheme counts the exit's
    /// emitter hit by a weight that assumes a light sample was taken (the
    /// light-only scheme counts it 0: a mirror ball rendered 34% dark).
    pub fn configure(&mut self, min_bounces: u32, entry_nee: EntryNee) {
        for e in &mut self.list {
            e.min_bounces = min_bounces;
            e.entry_nee = e.applicable_entry_nee(entry_nee);
        }
        self.min_bounces = min_bounces;
    }

    /// Sets P and the entry NEE of estimator `index`, or (`None`) turns it
    /// off: its instances are then traced as plain geometry.
    pub fn configure_one(&mut self, index: usize, choice: Option<(u32, EntryNee)>) {
        match choice {
            Some((p, nee)) => {
                let e = &mut self.list[index];
                e.min_bounces = p;
                e.entry_nee = e.applicable_entry_nee(nee);
            }
            None => {
                for e in self.per_instance.iter_mut() {
                    if *e == Some(index as u32) {
                        *e = None;
                    }
                }
            }
        }
        self.min_bounces = self
            .per_instance
            .iter()
            .flatten()
            .map(|&e| self.list[e as usize].min_bounces)
            .min()
            .unwrap_or(u32::MAX);
        self.find_sole_instance();
    }

    /// Whether any instance still uses an estimator.
    pub fn any_in_use(&self) -> bool {
        self.per_instance.iter().any(Option::is_some)
    }

    /// Bytes of estimator data shared by all instances.
    pub fn memory_bytes(&self) -> usize {
        self.list
            .iter()
            .map(|e| match &e.model {
                EstimatorModel::Neural { sampler } | EstimatorModel::CostFloor { sampler, .. } => {
                    sampler.memory_bytes()
                }
                EstimatorModel::Oracle { .. } => 0,
            })
            .sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nppp_scene::Transform;
    use proptest::prelude::*;

    fn vec3() -> impl Strategy<Value = Vec3> {
        (-1.0f32..1.0, -1.0f32..1.0, -1.0f32..1.0).prop_map(|(x, y, z)| Vec3::new(x, y, z))
    }

    proptest! {
        /// `line_in_box` gives the line's part inside the box: points of
        /// the interval are in the box, points beyond it (by 1% of the
        /// box) are not, and a line that misses has no interval. Also for
        /// directions with zero components and unbounded boxes; a NaN
        /// line meets nothing.
        #[test]
        fn line_in_box_is_the_line_inside_the_box(
            o in vec3(), d in vec3(), lo in vec3(), size in vec3(), zero in 0usize..4,
            unbounded in proptest::bool::ANY,
        ) {
            let mut d = d;
            if zero < 3 {
                d[zero] = 0.0;
            }
            prop_assume!(d.length() > 1e-3);
            let d = d.normalize();
            let o = o * 3.0;
            let b = if unbounded {
                (Vec3::new(lo.x, f32::NEG_INFINITY, lo.z), Vec3::new(lo.x + size.x.abs() + 0.1, f32::INFINITY, lo.z + size.z.abs() + 0.1))
            } else {
                (lo, lo + size.abs() + Vec3::splat(0.1))
            };
            let inside = |p: Vec3, slack: f32| p.cmpge(b.0 - slack).all() && p.cmple(b.1 + slack).all();
            prop_assert_eq!(line_in_box(o * f32::NAN, d, b), None);
            prop_assert_eq!(line_in_box(o, d * f32::NAN, b), None);
            match line_in_box(o, d, b) {
                Some((t0, t1)) => {
                    prop_assert!(t0 <= t1);
                    for k in 0..=8 {
                        let t = t0.max(-1e3) + (t1.min(1e3) - t0.max(-1e3)) * k as f32 / 8.0;
                        prop_assert!(inside(o + d * t, 1e-4), "t {t} of {t0}..{t1}");
                    }
                    let margin = 0.01 * (b.1 - b.0).min_element();
                    if t0.is_finite() {
                        prop_assert!(!inside(o + d * (t0 - margin), -1e-4 * margin));
                    }
                    if t1.is_finite() {
                        prop_assert!(!inside(o + d * (t1 + margin), -1e-4 * margin));
                    }
                }
                None => {
                    // The closest approach to the box's centre is outside it.
                    let c = if unbounded { Vec3::new((b.0.x + b.1.x) * 0.5, o.y, (b.0.z + b.1.z) * 0.5) } else { (b.0 + b.1) * 0.5 };
                    for k in -200..=200 {
                        let t = (c - o).dot(d) + k as f32 * 0.05;
                        prop_assert!(!inside(o + d * t, -1e-4), "t {t} inside");
                    }
                }
            }
        }

        /// Where the world-space test answers, it gives the exact test's
        /// answer (rays from inside, from near the boundary, from far away,
        /// grazing), whatever the instance's rotation, scale and place.
        #[test]
        fn world_sphere_test_agrees_with_the_exact_one(
            axis in vec3(), angle in 0.0f32..6.3, scale_log in -3.0f32..3.0,
            translation in vec3(), far in prop_oneof![Just(1.0f32), Just(1e3), Just(1e5)],
            center in vec3(), radius in 0.01f32..2.0,
            origin_dir in vec3(), origin_dist in prop_oneof![0.0f32..0.999, 0.999f32..1.001, 1.001f32..3.0, (1.1f32..9.2).prop_map(f32::exp)],
            dir in vec3(), toward in 0.0f32..1.0, offset in vec3(),
        ) {
            let axis = if axis.length() > 1e-3 { axis.normalize() } else { Vec3::Z };
            let t = Transform {
                scale: scale_log.exp(),
                rotation: glam::Quat::from_axis_angle(axis, angle),
                translation: translation * far,
            };
            let x = InstanceXform::new(0, &t);
            let sphere = BoundingSphere { center, radius };
            let world = WorldSphere::new(&sphere, &x);
            let r = radius * x.scale;
            let from = if origin_dir.length() > 1e-3 { origin_dir.normalize() } else { Vec3::X };
            let o = world.center + from * origin_dist * r;
            // Half the rays aim near the sphere (grazing ones included).
            let target = world.center + offset * r * 1.2;
            let d = if toward < 0.5 { (target - o).normalize_or(Vec3::Y) } else { dir.normalize_or(Vec3::Y) };
            let exact = match sphere_entry(&sphere, &x, o, d) {
                SphereEntry::Inside => WorldEntry::Inside,
                SphereEntry::Misses => WorldEntry::Misses,
                SphereEntry::Enters { .. } => WorldEntry::Enters,
            };
            if let Some(answer) = world.classify(o, d) {
                prop_assert_eq!(answer, exact, "o {} d {} world {:?}", o, d, world);
            }
        }
    }

    /// The quick test answers most rays itself (else it would save nothing).
    #[test]
    fn world_sphere_test_answers_rays_away_from_the_boundary() {
        let x = InstanceXform::new(0, &Transform::default());
        let world = WorldSphere::new(
            &BoundingSphere {
                center: Vec3::ZERO,
                radius: 1.0,
            },
            &x,
        );
        use WorldEntry::*;
        assert_eq!(world.classify(Vec3::ZERO, Vec3::X), Some(Inside));
        assert_eq!(
            world.classify(Vec3::new(0.0, 0.0, -3.0), Vec3::Z),
            Some(Enters)
        );
        assert_eq!(
            world.classify(Vec3::new(0.0, 0.0, -3.0), -Vec3::Z),
            Some(Misses)
        );
        assert_eq!(
            world.classify(Vec3::new(0.0, 2.0, -3.0), Vec3::Z),
            Some(Misses)
        );
        assert_eq!(world.classify(Vec3::new(0.0, 1.0, -3.0), Vec3::Z), None);
        assert_eq!(world.classify(Vec3::new(0.0, 0.0, 1.0), Vec3::Z), None);
        assert_eq!(world.classify(Vec3::splat(f32::NAN), Vec3::Z), None);
    }

    /// The network's vertex takes the real surface's point and normals
    /// where `on_surface` finds a point that faces as predicted; a point of
    /// the other side of a thin part, or none, leaves it pushed off along
    /// its own normal.
    #[test]
    fn a_network_vertex_moves_onto_the_surface_only_where_it_faces_alike() {
        let sphere = BoundingSphere {
            center: Vec3::new(10.0, 0.0, 0.0),
            radius: 2.0,
        };
        let bsdf = Bsdf::Diffuse {
            albedo: Vec3::splat(0.5),
        };
        let v = nppp_estimator::PickedVertex {
            position: Vec3::new(0.0, 0.3, 0.0),
            normal: Vec3::Y,
            wo: Vec3::new(0.0, 0.6, 0.8),
            beta: Vec3::ONE,
            index: 0,
        };
        let real = (Vec3::new(10.0, 0.5, 0.0), Vec3::new(0.0, 0.8, 0.6), Vec3::Y);
        let s = network_skipped(&v, &sphere, bsdf, 5, |p| {
            assert_eq!(p, Vec3::new(10.0, 0.6, 0.0), "asked in mesh space");
            Some(real)
        });
        let (w, _) = s.nee.expect("a light sample");
        // Lifted along the real normal, to the side the path came from.
        let lifted = real.0 + real.1 * SURFACE_VERTEX_LIFT * 2.0;
        assert!(w.point.distance(lifted) < 1e-6, "{}", w.point);
        assert_eq!((w.ng, w.ns), (real.1, real.2));
        assert!(s.light_alone);
        let pushed = Vec3::new(10.0, 0.6 + NETWORK_VERTEX_OFFSET * 2.0, 0.0);
        // The far side of a thin part faces the other way.
        let far_side = (Vec3::new(10.0, 0.2, 0.0), -Vec3::Y, -Vec3::Y);
        for found in [Some(far_side), None] {
            let (w, _) = network_skipped(&v, &sphere, bsdf, 5, |_| found)
                .nee
                .unwrap();
            assert!(w.point.distance(pushed) < 1e-6, "{}", w.point);
            assert_eq!((w.ng, w.ns), (Vec3::Y, Vec3::Y));
        }
        // Past the bounce budget: no light sample, nothing looked up.
        let s = network_skipped(&v, &sphere, bsdf, 0, |_| -> Option<(Vec3, Vec3, Vec3)> {
            panic!("looked up an unused vertex")
        });
        assert!(s.nee.is_none());
    }
}
