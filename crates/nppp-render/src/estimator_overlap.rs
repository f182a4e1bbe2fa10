//! Other geometry inside an estimator's see-through object.
//!
//! An estimator learns its object alone, in vacuum. The walks through a
//! glass or translucent object go everywhere inside it, so another instance
//! that crosses its surface or lies inside it (a lamp in a jade ball, glass
//! balls in a medium, a knot sunk into the floor) makes every answer of
//! that estimator wrong, not only those of rays whose straight chord meets
//! the other geometry (those are traced for real already). Such an instance
//! is traced for real instead: [`find_obstructed`] names it and the first
//! other instance found in the way, and the renderer says so.
//!
//! Two surfaces cross where an edge of one passes through a face of the
//! other (two triangles that intersect, not coplanar, always have such an
//! edge), tested both ways. Touching is not crossing: an edge that grazes
//! a face, ends on it, or meets it at its border within a hair (a
//! millionth of the object's size) does not count, so a glass box standing
//! exactly on a floor keeps its estimator whatever the floor's
//! triangulation. Geometry around the object (a room, a glass case) does
//! not change its walks: indices of refraction do not nest (each surface
//! refracts with its own index against vacuum), and a path inside another
//! object's medium traces every object for real.
//!
//! An opaque object's walk stays outside the object: other geometry near it
//! inside its sphere (a floor under a knot) is left to the exit rule (exit
//! rays start from the plane through the sphere's centre) and to the
//! ambiguous-chord test, as before.

use crate::accel::{Accel, Blas, InstanceXform, mapped_box};
use crate::estimator::Estimators;
use glam::{Vec3, Vec3A};
use nppp_geom::BoundingSphere;
use nppp_scene::Scene;
use std::sync::OnceLock;

/// An estimator instance whose object another instance crosses or lies
/// inside.
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
            "{}.estimator is not used: {} crosses or lies inside its see-through object, \
             which the estimator learned alone, so the instance is traced for real \
             (move the geometry out of the object or remove the instance's `estimator` key)",
            name(self.instance),
            name(self.other)
        )
    }
}

/// The warnings for `obstructed`, one line each for the first few and one
/// line counting the rest (a room of 2,025 knots sunk into its floor would
/// print 1,304 lines).
pub fn describe_all(obstructed: &[Obstruction], scene: &Scene) -> Vec<String> {
    const NAMED: usize = 3;
    let mut lines: Vec<String> = obstructed
        .iter()
        .take(NAMED)
        .map(|o| o.describe(scene))
        .collect();
    if obstructed.len() > NAMED {
        lines.push(format!(
            "and {} more instances' estimators are not used for the same reason",
            obstructed.len() - NAMED
        ));
    }
    lines
}

fn boxes_overlap(a: (Vec3, Vec3), b: (Vec3, Vec3)) -> bool {
    a.0.cmple(b.1).all() && b.0.cmple(a.1).all()
}

/// Per mesh, what the tests need, made once on first use and shared by
/// the threads.
struct MeshCache<'s> {
    scene: &'s Scene,
    accel: &'s Accel,
    closed: Vec<OnceLock<bool>>,
    /// Object-space box of each triangle.
    triangle_boxes: Vec<OnceLock<Vec<(Vec3, Vec3)>>>,
    /// Object-space box of each run of [`TRIANGLE_RUN`] consecutive triangles.
    triangle_runs: Vec<OnceLock<Vec<(Vec3, Vec3)>>>,
    sphere: Vec<OnceLock<BoundingSphere>>,
}

/// Triangles per box of [`MeshCache::triangle_runs`]: meshes list
/// neighbouring triangles together (procedural ones by construction, OBJ
/// exports mostly), so a run's box is small and a face far from most of
/// an object skips most runs.
const TRIANGLE_RUN: usize = 32;

impl<'s> MeshCache<'s> {
    fn new(scene: &'s Scene, accel: &'s Accel) -> Self {
        let n = scene.meshes.len();
        Self {
            scene,
            accel,
            closed: (0..n).map(|_| OnceLock::new()).collect(),
            triangle_boxes: (0..n).map(|_| OnceLock::new()).collect(),
            triangle_runs: (0..n).map(|_| OnceLock::new()).collect(),
            sphere: (0..n).map(|_| OnceLock::new()).collect(),
        }
    }

    fn sphere(&self, mesh: usize) -> BoundingSphere {
        *self.sphere[mesh]
            .get_or_init(|| BoundingSphere::around(&self.scene.meshes[mesh].positions, 1e-3))
    }

    /// Whether the bounding spheres of instances `i` and `j` meet: unlike
    /// their world boxes (a rotated object's box is loose), a sphere
    /// stays tight under rotation, so neighbours in a dense layout are
    /// told apart without a triangle test.
    fn spheres_meet(&self, i: usize, j: usize) -> bool {
        let world = |k: usize| {
            let s = self.sphere(self.scene.instances[k].mesh);
            let x = &self.accel.instances[k];
            (x.point_to_world(s.center), s.radius * x.scale)
        };
        let ((ci, ri), (cj, rj)) = (world(i), world(j));
        ci.distance(cj) <= ri + rj
    }

    fn triangle(&self, mesh: usize, t: usize) -> [Vec3; 3] {
        let m = &self.scene.meshes[mesh];
        m.triangles[t].map(|v| m.positions[v as usize])
    }

    /// The object-space triangles of `mesh` whose boxes overlap `region`
    /// (object space): one box test per triangle, no transform.
    fn triangles_in(&self, mesh: usize, region: (Vec3, Vec3)) -> Vec<[Vec3; 3]> {
        let boxes = self.triangle_boxes[mesh].get_or_init(|| {
            (0..self.scene.meshes[mesh].triangles.len())
                .map(|t| {
                    let [a, b, c] = self.triangle(mesh, t);
                    (a.min(b).min(c), a.max(b).max(c))
                })
                .collect()
        });
        (0..boxes.len())
            .filter(|&t| boxes_overlap(boxes[t], region))
            .map(|t| self.triangle(mesh, t))
            .collect()
    }

    fn triangle_runs(&self, mesh: usize) -> &[(Vec3, Vec3)] {
        self.triangle_runs[mesh].get_or_init(|| {
            let n = self.scene.meshes[mesh].triangles.len();
            (0..n)
                .step_by(TRIANGLE_RUN)
                .map(|start| {
                    (start..(start + TRIANGLE_RUN).min(n)).fold(
                        (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
                        |(lo, hi), t| {
                            let [a, b, c] = self.triangle(mesh, t);
                            (lo.min(a).min(b).min(c), hi.max(a).max(b).max(c))
                        },
                    )
                })
                .collect()
        })
    }

    /// Whether `mesh` is closed (it has an inside).
    fn closed(&self, mesh: usize) -> bool {
        *self.closed[mesh].get_or_init(|| nppp_scene::open_edge(&self.scene.meshes[mesh]).is_none())
    }
}

/// A triangle with its unit normal, for the crossing tests.
struct Face {
    p: [Vec3; 3],
    n: Vec3,
}

impl Face {
    /// `None` for a triangle without area (nothing can cross it).
    fn new(p: [Vec3; 3]) -> Option<Self> {
        let n = (p[1] - p[0]).cross(p[2] - p[0]);
        let len = n.length();
        (len > 0.0 && len.is_finite()).then(|| Self { p, n: n / len })
    }

    /// Signed distance of `x` from the face's plane.
    fn height(&self, x: Vec3) -> f32 {
        self.n.dot(x - self.p[0])
    }

    /// Whether all of `points` lie more than `tol` on one side of the
    /// plane: then no edge between them crosses the face.
    fn clear_of(&self, points: &[Vec3; 3], tol: f32) -> bool {
        let h = points.map(|x| self.height(x));
        h.iter().all(|&v| v > tol) || h.iter().all(|&v| v < -tol)
    }

    /// Whether the segment from `a` to `b` crosses the face through its
    /// inside: its ends lie on either side of the plane, each more than
    /// `tol` from it, and it meets the plane more than `tol` inside the
    /// face's edges. Grazing, ending on the face and touching its border
    /// are contact, not crossing.
    fn crossed_by(&self, a: Vec3, b: Vec3, tol: f32) -> bool {
        let (da, db) = (self.height(a), self.height(b));
        if !(da > tol && db < -tol || da < -tol && db > tol) {
            return false;
        }
        let x = a + (b - a) * (da / (da - db));
        let [p0, p1, p2] = self.p;
        // Distance inside each edge, in the face's plane.
        [(p0, p1), (p1, p2), (p2, p0)].iter().all(|&(u, v)| {
            let inward = self.n.cross(v - u).normalize_or_zero();
            inward.dot(x - u) > tol
        })
    }

    /// Whether an edge of `other` crosses this face.
    fn crossed_by_edges_of(&self, other: &[Vec3; 3], tol: f32) -> bool {
        !self.clear_of(other, tol)
            && [(0, 1), (1, 2), (2, 0)]
                .iter()
                .any(|&(u, v)| self.crossed_by(other[u], other[v], tol))
    }
}

/// Whether the segment from `a` to `b` passes through the box (slab test).
fn segment_meets_box(a: Vec3, b: Vec3, (lo, hi): (Vec3, Vec3)) -> bool {
    let d = b - a;
    let (mut t0, mut t1) = (0.0f32, 1.0f32);
    for k in 0..3 {
        if d[k] == 0.0 {
            if a[k] < lo[k] || a[k] > hi[k] {
                return false;
            }
        } else {
            let (u, v) = ((lo[k] - a[k]) / d[k], (hi[k] - a[k]) / d[k]);
            t0 = t0.max(u.min(v));
            t1 = t1.min(u.max(v));
        }
    }
    t0 <= t1
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
    let (lo, hi) = mapped_box(region.0, region.1, |c| x.point_to_object(c));
    // The rotation's rounding: a hair more, never less.
    let pad = (hi - lo).max_element() * 1e-5 + 1e-30;
    (lo - pad, hi + pad)
}

/// Whether instance `j`'s geometry crosses instance `i`'s object's surface
/// or lies inside it. Everything is tested in `i`'s object space.
fn obstructs(cache: &MeshCache, i: usize, j: usize) -> bool {
    let (scene, accel) = (cache.scene, cache.accel);
    let (xi, xj) = (&accel.instances[i], &accel.instances[j]);
    let (mi, mj) = (scene.instances[i].mesh, scene.instances[j].mesh);
    let (bi, bj) = (accel.instance_bounds[i], accel.instance_bounds[j]);
    // A millionth of the object's size: closer than this is contact.
    let tol = cache.sphere(mi).radius * 1e-6;
    // Only the triangles where the two boxes meet can cross.
    let both = (bi.0.max(bj.0), bi.1.min(bj.1));
    let tris_j: Vec<[Vec3; 3]> = cache
        .triangles_in(mj, box_to_object(xj, both))
        .into_iter()
        .map(|t| t.map(|p| xi.point_to_object(xj.point_to_world(p))))
        .collect();
    if tris_j.is_empty() {
        return false;
    }
    let runs = cache.triangle_runs(mi);
    // `i`'s own bounds, in its object space.
    let (lo, hi) = accel.blas[mi].bounds;
    let bounds_i = (lo - Vec3::splat(tol), hi + Vec3::splat(tol));
    // Each face of `j` against the edges of `i`'s triangles near it, and
    // each face of `i` there against the edges of `j`'s: the runs of `i`'s
    // triangles whose boxes meet the face's box.
    let crossing = tris_j.iter().any(|tj| {
        let Some(fj) = Face::new(*tj) else {
            return false;
        };
        // The edges of `tj` that pass by the object at all (a floor's
        // border never does).
        let live: Vec<(Vec3, Vec3)> = [(tj[0], tj[1]), (tj[1], tj[2]), (tj[2], tj[0])]
            .into_iter()
            .filter(|&(a, b)| segment_meets_box(a, b, bounds_i))
            .collect();
        let reach = (
            tj[0].min(tj[1]).min(tj[2]) - Vec3::splat(tol),
            tj[0].max(tj[1]).max(tj[2]) + Vec3::splat(tol),
        );
        // A run whose box lies off the face's plane holds no triangle that
        // crosses the face (a floor under an object: only the runs at its
        // bottom are tested).
        let meets_plane = |(lo, hi): (Vec3, Vec3)| {
            let centre = fj.height((lo + hi) * 0.5);
            centre.abs() <= fj.n.abs().dot((hi - lo) * 0.5) + tol
        };
        let n = scene.meshes[mi].triangles.len();
        runs.iter().enumerate().any(|(r, &run)| {
            boxes_overlap(run, reach)
                && meets_plane(run)
                && (r * TRIANGLE_RUN..((r + 1) * TRIANGLE_RUN).min(n)).any(|t| {
                    let ti = cache.triangle(mi, t);
                    fj.crossed_by_edges_of(&ti, tol)
                        || !live.is_empty()
                            && Face::new(ti).is_some_and(|fi| {
                                !fi.clear_of(tj, tol)
                                    && live.iter().any(|&(a, b)| fi.crossed_by(a, b, tol))
                            })
                })
        })
    });
    // No surfaces cross: each connected part of `j` there lies inside the
    // object whole, or outside it. A vertex per triangle decides (a part
    // has no vertex outside the region of its own triangles).
    crossing || cache.closed(mi) && tris_j.iter().any(|t| inside_closed(&accel.blas[mi], t[0]))
}

/// Leaves the estimators of the `obstructed` instances unused: they are
/// traced for real.
pub fn release(ests: &mut Estimators, obstructed: &[Obstruction]) {
    if obstructed.is_empty() {
        return;
    }
    let mut per_instance = ests.per_instance().to_vec();
    for o in obstructed {
        per_instance[o.instance] = None;
    }
    ests.set_per_instance(per_instance);
}

/// Every instance that uses an estimator for a see-through object another
/// instance crosses or lies inside (see the module's doc), with the first
/// such other instance. Instances are tested against those whose world
/// boxes overlap theirs, so a scene of many separate objects costs little.
pub fn find_obstructed(scene: &Scene, accel: &Accel, ests: &Estimators) -> Vec<Obstruction> {
    use rayon::prelude::*;
    let cache = MeshCache::new(scene, accel);
    // In parallel: 2,025 glass knots on a floor test each against it.
    (0..scene.instances.len())
        .into_par_iter()
        .filter(|&i| ests.per_instance()[i].is_some_and(|e| ests.list[e as usize].walks_inside()))
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
