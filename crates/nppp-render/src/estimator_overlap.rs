//! Other geometry inside an estimator's see-through object.
//!
//! An estimator learns its object alone, in vacuum. The walks through a
//! glass or translucent object go everywhere inside it, so another instance
//! that crosses its surface, lies inside it (a lamp in a jade ball, glass
//! balls in a medium) or holds it (a jade knot in a glass box: the walk's
//! relative index of refraction would be wrong) makes every answer of that
//! estimator wrong, not only those of rays whose straight chord meets the
//! other geometry (those are traced for real already). Such an instance is
//! traced for real instead: [`find_obstructed`] names it and the first other
//! instance found in the way, and the renderer says so.
//!
//! An opaque object's walk stays outside the object: other geometry near it
//! inside its sphere (a floor under a knot) is left to the exit rule (exit
//! rays start from the plane through the sphere's centre) and to the
//! ambiguous-chord test, as before.

use crate::accel::{Accel, Blas, InstanceXform};
use crate::bsdf::Bsdf;
use crate::estimator::Estimators;
use crate::surface::SurfaceKind;
use glam::{Vec3, Vec3A};
use nppp_geom::BoundingSphere;
use nppp_scene::Scene;
use std::sync::OnceLock;

/// An estimator instance whose object another instance crosses, fills or
/// holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Obstruction {
    /// The instance with the estimator (index into the scene's instances).
    pub instance: usize,
    /// The first other instance found in its way.
    pub other: usize,
}

impl Obstruction {
    /// What the renderer tells the user, naming both instances.
    pub fn describe(&self, scene: &Scene) -> String {
        let name = |i: usize| {
            let inst = &scene.instances[i];
            format!(
                "instances[{i}] (mesh \"{}\", material \"{}\")",
                scene.mesh_names[inst.mesh], scene.material_names[inst.material]
            )
        };
        format!(
            "{}.estimator is not used: {} crosses, fills or holds its see-through object, \
             which the estimator learned alone, so the instance is traced for real \
             (move the geometry out of the object or remove the instance's `estimator` key)",
            name(self.instance),
            name(self.other)
        )
    }
}

/// Whether paths walk inside an estimator's object: glass and translucent
/// objects.
fn see_through(scene: &Scene, instance: usize) -> bool {
    let material = &scene.materials[scene.instances[instance].material];
    crate::medium::Medium::of(material).is_some()
        || matches!(
            SurfaceKind::of(material),
            SurfaceKind::Scatter(Bsdf::Dielectric { .. })
        )
}

fn boxes_overlap(a: (Vec3, Vec3), b: (Vec3, Vec3)) -> bool {
    a.0.cmple(b.1).all() && b.0.cmple(a.1).all()
}

/// Per mesh, what the tests need, made once on first use and shared by
/// the threads.
struct MeshCache<'s> {
    scene: &'s Scene,
    accel: &'s Accel,
    /// BVHs built here for meshes the scene merged into the world BLAS.
    bvh: Vec<OnceLock<Blas>>,
    closed: Vec<OnceLock<bool>>,
    /// Object-space box of each triangle.
    triangle_boxes: Vec<OnceLock<Vec<(Vec3, Vec3)>>>,
    typical_edge: Vec<OnceLock<f32>>,
    sphere: Vec<OnceLock<BoundingSphere>>,
    /// The box of each run of [`VERTEX_RUN`] consecutive positions.
    vertex_boxes: Vec<OnceLock<Vec<(Vec3, Vec3)>>>,
}

impl<'s> MeshCache<'s> {
    fn new(scene: &'s Scene, accel: &'s Accel) -> Self {
        let n = scene.meshes.len();
        Self {
            scene,
            accel,
            bvh: (0..n).map(|_| OnceLock::new()).collect(),
            closed: (0..n).map(|_| OnceLock::new()).collect(),
            triangle_boxes: (0..n).map(|_| OnceLock::new()).collect(),
            typical_edge: (0..n).map(|_| OnceLock::new()).collect(),
            sphere: (0..n).map(|_| OnceLock::new()).collect(),
            vertex_boxes: (0..n).map(|_| OnceLock::new()).collect(),
        }
    }

    /// Whether the bounding spheres of instances `i` and `j` meet: unlike
    /// their world boxes (a rotated object's box is loose), a sphere
    /// stays tight under rotation, so neighbours in a dense layout are
    /// told apart without a triangle test.
    fn spheres_meet(&self, i: usize, j: usize) -> bool {
        let world = |k: usize| {
            let m = self.scene.instances[k].mesh;
            let s = self.sphere[m]
                .get_or_init(|| BoundingSphere::around(&self.scene.meshes[m].positions, 1e-3));
            let x = &self.accel.instances[k];
            (x.point_to_world(s.center), s.radius * x.scale)
        };
        let ((ci, ri), (cj, rj)) = (world(i), world(j));
        ci.distance(cj) <= ri + rj
    }

    /// The object-space triangles of `mesh` whose boxes overlap `region`
    /// (object space): one box test per triangle, no transform.
    fn triangles_in(&self, mesh: usize, region: (Vec3, Vec3)) -> Vec<[Vec3; 3]> {
        let m = &self.scene.meshes[mesh];
        let corners = |t: &[u32; 3]| t.map(|i| m.positions[i as usize]);
        let boxes = self.triangle_boxes[mesh].get_or_init(|| {
            m.triangles
                .iter()
                .map(|t| {
                    let [a, b, c] = corners(t);
                    (a.min(b).min(c), a.max(b).max(c))
                })
                .collect()
        });
        boxes
            .iter()
            .zip(&m.triangles)
            .filter(|(b, _)| boxes_overlap(**b, region))
            .map(|(_, t)| corners(t))
            .collect()
    }

    /// The mean edge length of `mesh` (its first edge per triangle).
    fn typical_edge(&self, mesh: usize) -> f32 {
        *self.typical_edge[mesh].get_or_init(|| {
            let m = &self.scene.meshes[mesh];
            let sum: f64 = m
                .triangles
                .iter()
                .map(|t| m.positions[t[0] as usize].distance(m.positions[t[1] as usize]) as f64)
                .sum();
            (sum / m.triangles.len().max(1) as f64) as f32
        })
    }

    fn vertex_boxes(&self, mesh: usize) -> &[(Vec3, Vec3)] {
        self.vertex_boxes[mesh].get_or_init(|| {
            self.scene.meshes[mesh]
                .positions
                .chunks(VERTEX_RUN)
                .map(|run| {
                    run.iter().fold(
                        (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
                        |(lo, hi), &p| (lo.min(p), hi.max(p)),
                    )
                })
                .collect()
        })
    }

    /// Whether `mesh` is closed (it has an inside).
    fn closed(&self, mesh: usize) -> bool {
        *self.closed[mesh].get_or_init(|| nppp_scene::open_edge(&self.scene.meshes[mesh]).is_none())
    }

    /// A BVH of `mesh` in its object space: the scene's own where it has
    /// one (instanced meshes), else one built here (meshes merged into the
    /// world BLAS keep none).
    fn bvh(&self, mesh: usize) -> &Blas {
        if self.accel.blas[mesh].triangle_count() > 0 {
            return &self.accel.blas[mesh];
        }
        self.bvh[mesh].get_or_init(|| Blas::build(&self.scene.meshes[mesh]))
    }
}

/// Whether a segment from `a` to `b` (object space of `bvh`) crosses its mesh.
fn segment_crosses(bvh: &Blas, a: Vec3, b: Vec3) -> bool {
    let d = b - a;
    let len = d.length();
    if !(len > 0.0 && len.is_finite()) {
        return false;
    }
    bvh.occluded(Vec3A::from(a), Vec3A::from(d / len), 0.0, len)
}

/// Whether `p` (object space) lies inside the closed mesh of `bvh`: the
/// parity of the surface crossings along a fixed ray. The direction is
/// off every axis and diagonal, so that it grazes no edge of a mesh built
/// on a grid.
fn inside_closed(bvh: &Blas, p: Vec3) -> bool {
    let d = Vec3A::new(0.431_934, 0.679_485, 0.593_011).normalize();
    let o = Vec3A::from(p);
    let mut crossings = 0u32;
    let mut t = 0.0f32;
    // Each crossing moves on past the hit; a mesh with more crossings
    // along one ray than this is not a sensible container.
    for _ in 0..4096 {
        match bvh.intersect(o, d, t, f32::INFINITY) {
            Some(h) => {
                crossings += 1;
                t = h.t * (1.0 + 1e-6) + 1e-7;
            }
            None => break,
        }
    }
    crossings % 2 == 1
}

/// The box around `region` (world space) in the object space of `x`.
fn box_to_object(x: &InstanceXform, region: (Vec3, Vec3)) -> (Vec3, Vec3) {
    let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
    for k in 0..8 {
        let c = Vec3::new(
            if k & 1 == 0 { region.0.x } else { region.1.x },
            if k & 2 == 0 { region.0.y } else { region.1.y },
            if k & 4 == 0 { region.0.z } else { region.1.z },
        );
        let o = x.point_to_object(c);
        lo = lo.min(o);
        hi = hi.max(o);
    }
    // The rotation's rounding: a hair more, never less.
    let pad = (hi - lo).max_element() * 1e-5 + 1e-30;
    (lo - pad, hi + pad)
}

/// Whether instance `j`'s geometry crosses, fills or holds instance `i`'s
/// closed object.
fn obstructs(cache: &MeshCache, i: usize, j: usize) -> bool {
    let (scene, accel) = (cache.scene, cache.accel);
    let (xi, xj) = (&accel.instances[i], &accel.instances[j]);
    let (mi, mj) = (scene.instances[i].mesh, scene.instances[j].mesh);
    let (bi, bj) = (accel.instance_bounds[i], accel.instance_bounds[j]);
    // Only the triangles where the two boxes meet can cross.
    let both = (bi.0.max(bj.0), bi.1.min(bj.1));
    // `j`'s triangles there, in `i`'s object space.
    let tris_j: Vec<[Vec3; 3]> = cache
        .triangles_in(mj, box_to_object(xj, both))
        .into_iter()
        .map(|t| t.map(|p| xi.point_to_object(xj.point_to_world(p))))
        .collect();
    // `j`'s edges through `i`'s surface.
    let bvh_i = &accel.blas[mi];
    if tris_j.iter().any(|&[a, b, c]| {
        segment_crosses(bvh_i, a, b) || segment_crosses(bvh_i, b, c) || segment_crosses(bvh_i, c, a)
    }) {
        return true;
    }
    // `j`'s faces through `i` with their edges outside it (a floor cutting
    // the object): `i`'s vertices on both sides of the face, in `i`'s
    // object space. Where `j` has many triangles there, those about as
    // small as `i`'s own cross it at an edge (tested above): only faces
    // larger than four of `i`'s typical edges are tested then.
    let large = if tris_j.len() <= 64 {
        0.0
    } else {
        4.0 * cache.typical_edge(mi)
    };
    let positions = &scene.meshes[mi].positions;
    let runs = cache.vertex_boxes(mi);
    tris_j.iter().any(|&[a, b, c]| {
        (b - a).length().max((c - b).length()).max((a - c).length()) > large
            && face_cuts(a, b, c, positions, runs)
    }) || contains(cache, i, j)
}

/// Vertices per box of [`MeshCache::vertex_boxes`].
const VERTEX_RUN: usize = 64;

/// Whether points of `positions` lie strictly on both sides of triangle
/// `a b c` within its prism (their projections inside it). `runs` bounds
/// each run of [`VERTEX_RUN`] consecutive positions: a run that cannot add
/// a side not seen yet is skipped whole, so a mesh beside a floor costs a
/// test per run, not per vertex.
fn face_cuts(a: Vec3, b: Vec3, c: Vec3, positions: &[Vec3], runs: &[(Vec3, Vec3)]) -> bool {
    let n = (b - a).cross(c - a);
    if n == Vec3::ZERO || !n.is_finite() {
        return false;
    }
    // Inside the prism: on the inner side of the three edge planes.
    let (ea, eb, ec) = (n.cross(b - a), n.cross(c - b), n.cross(a - c));
    let in_prism = |p: Vec3| ea.dot(p - a) >= 0.0 && eb.dot(p - b) >= 0.0 && ec.dot(p - c) >= 0.0;
    let (mut above, mut below) = (false, false);
    for (run, &(lo, hi)) in positions.chunks(VERTEX_RUN).zip(runs) {
        // The run's heights over the plane lie in `centre +- reach`.
        let centre = n.dot((lo + hi) * 0.5 - a);
        let reach = n.abs().dot((hi - lo) * 0.5);
        let may_add_above = !above && centre + reach > 0.0;
        let may_add_below = !below && centre - reach < 0.0;
        if !(may_add_above || may_add_below) {
            continue;
        }
        for &p in run {
            let h = n.dot(p - a);
            if ((h > 0.0 && !above) || (h < 0.0 && !below)) && in_prism(p) {
                above |= h > 0.0;
                below |= h < 0.0;
                if above && below {
                    return true;
                }
            }
        }
    }
    false
}

/// Whether `j` lies inside `i` whole, or `i` inside `j` (both closed).
fn contains(cache: &MeshCache, i: usize, j: usize) -> bool {
    let (scene, accel) = (cache.scene, cache.accel);
    let (xi, xj) = (&accel.instances[i], &accel.instances[j]);
    let (mi, mj) = (scene.instances[i].mesh, scene.instances[j].mesh);
    let first_vertex = |m: usize| {
        let mesh = &scene.meshes[m];
        mesh.triangles
            .first()
            .map(|t| mesh.positions[t[0] as usize])
    };
    if cache.closed(mi)
        && let Some(p) = first_vertex(mj)
        && inside_closed(&accel.blas[mi], xi.point_to_object(xj.point_to_world(p)))
    {
        return true;
    }
    cache.closed(mj)
        && first_vertex(mi)
            .is_some_and(|p| inside_closed(cache.bvh(mj), xj.point_to_object(xi.point_to_world(p))))
}

/// Every instance that uses an estimator for a see-through object another
/// instance crosses, fills or holds (see the module's doc), with the first
/// such other instance. Instances are tested against those whose world
/// boxes overlap theirs, so a scene of many separate objects costs little.
pub fn find_obstructed(scene: &Scene, accel: &Accel, ests: &Estimators) -> Vec<Obstruction> {
    use rayon::prelude::*;
    let cache = MeshCache::new(scene, accel);
    // In parallel: 2,025 glass knots on a floor test each against it.
    (0..scene.instances.len())
        .into_par_iter()
        .filter(|&i| ests.per_instance()[i].is_some() && see_through(scene, i))
        .filter_map(|i| {
            let bi = accel.instance_bounds[i];
            (0..scene.instances.len())
                .find(|&j| {
                    j != i
                        && boxes_overlap(bi, accel.instance_bounds[j])
                        && cache.spheres_meet(i, j)
                        && obstructs(&cache, i, j)
                })
                .map(|other| Obstruction { instance: i, other })
        })
        .collect()
}
