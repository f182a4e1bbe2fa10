//! Other geometry within an estimator's object.
//!
//! An estimator learns its object alone, in vacuum. The object's walks go
//! everywhere inside its convex hull: through a glass or translucent
//! object's inside, and from one part of any object to another (a ray
//! leaving one strand of a knot crosses its hole to the next strand). So
//! another instance with geometry inside that hull (a lamp in a jade ball,
//! glass balls in a medium, a ball in a knot's hole, a knot sunk into the
//! floor or through another knot) makes every answer of that estimator
//! wrong, not only those of rays whose straight chord meets the other
//! geometry (those are traced for real already): an oracle with a lamp in
//! a glass knot's hole rendered 26% dark, a gold knot's 38%. Such an
//! instance is traced for real instead: [`find_obstructed`] names it and
//! the first other instance found in its way, and the renderer says so.
//!
//! The hull is the mesh's convex hull from the `quickhull` crate (which
//! may leave out vertices within about 1e-5 of the object's size of it),
//! within the mesh's box; a flat mesh has its box alone. A mesh of more
//! than 200,000 vertices is bounded by 2,000 planes touching it instead
//! (a little larger than its hull: see `EXACT_HULL_MAX_VERTICES`). A triangle of the
//! other instance meets it where clipping the triangle by every plane
//! leaves something. Touching is not meeting: the planes are moved in by
//! 1e-4 of the object's size first (well above the rounding of a rotated
//! floor mapped into the object's space), so a knot resting on a floor, or
//! a glass box standing exactly on one, keeps its estimator whatever the
//! floor's triangulation. Geometry around the hull (a room, a glass case,
//! a floor below the object that cuts its bounding sphere) is left to the
//! exit rule and to the ambiguous-chord test: [`find_other_geometry_in_spheres`]
//! boxes what lies inside each sphere, and an exit ray whose line meets
//! that box near the object starts at the object's last crossing of the
//! line instead of the thesis' plane through the sphere's centre.

use crate::accel::{Accel, InstanceXform, mapped_box};
use crate::estimator::Estimators;
use glam::Vec3;
use nppp_geom::BoundingSphere;
use nppp_scene::Scene;
use std::sync::OnceLock;

/// An estimator instance whose object's hull holds geometry of another
/// instance.
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
            "{}.estimator is not used: {} reaches into its object or between its parts \
             (the object's convex hull), where the estimator, which learned the object alone, \
             does not see it; the instance is traced for real (move the geometry out of the \
             hull or remove the instance's `estimator` key)",
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

/// A mesh's convex hull (object space, relative to `centre`): the points
/// `x` with `n.dot(x - centre) <= h` for every plane `(n, h)`.
struct Hull {
    planes: Vec<(Vec3, f32)>,
    /// The centre of the mesh's box.
    centre: Vec3,
    /// For directions from `centre` (a cube map of [`FACING_CELLS`]^2 cells
    /// per side), the plane facing that way most: the one a triangle that
    /// lies that way is tested against first, which usually dismisses it.
    facing: Vec<u32>,
}

/// Meshes with more vertices than this are bounded by
/// [`BOUNDING_DIRECTIONS`] planes instead of their exact convex hull.
/// `quickhull` takes time quadratic in the number of hull vertices (points
/// on a sphere: 40,000 in 0.12 s, 160,000 in 1.35 s, 320,000 in 4.3 s; an
/// icosphere of 655,362 vertices, all on its hull, made a scene take 17 s
/// to build), and a hull of a million faces would be as slow to test
/// triangles against. The committed knot's 163,840 vertices, most of them
/// inside its hull, take 0.03 s and keep the exact hull.
const EXACT_HULL_MAX_VERTICES: usize = 200_000;

/// Directions (spread evenly over the sphere) of the planes that bound a
/// mesh above [`EXACT_HULL_MAX_VERTICES`]: each touches the mesh, so the
/// polytope holds the hull and is looser by at most about 1 - cos(a / 2)
/// of the mesh's radius between neighbouring directions a apart (0.08%
/// for 2,000: a knot resting on a floor stays clear of it).
const BOUNDING_DIRECTIONS: usize = 2_000;

/// The planes of [`BOUNDING_DIRECTIONS`] directions, each through the
/// mesh's farthest vertex that way (relative to `centre`).
fn bounding_planes(positions: &[Vec3], centre: Vec3) -> Vec<(Vec3, f32)> {
    use rayon::prelude::*;
    let golden = std::f32::consts::PI * (3.0 - 5f32.sqrt());
    (0..BOUNDING_DIRECTIONS)
        .into_par_iter()
        .map(|k| {
            let y = 1.0 - 2.0 * (k as f32 + 0.5) / BOUNDING_DIRECTIONS as f32;
            let r = (1.0 - y * y).max(0.0).sqrt();
            let (s, c) = (k as f32 * golden).sin_cos();
            let n = Vec3::new(r * c, y, r * s);
            let h = positions
                .iter()
                .map(|&p| n.dot(p - centre))
                .fold(f32::NEG_INFINITY, f32::max);
            (n, h)
        })
        .collect()
}

/// Cells per cube-map side edge of [`Hull::facing`].
const FACING_CELLS: usize = 16;

/// The cube-map cell of direction `d`.
fn facing_cell(d: Vec3) -> usize {
    let a = d.abs();
    let (axis, u, v, m) = if a.x >= a.y && a.x >= a.z {
        (0, d.y, d.z, a.x)
    } else if a.y >= a.z {
        (1, d.x, d.z, a.y)
    } else {
        (2, d.x, d.y, a.z)
    };
    let side = axis * 2 + usize::from(d[axis] < 0.0);
    let m = m.max(f32::MIN_POSITIVE);
    let cell =
        |w: f32| (((w / m + 1.0) * 0.5 * FACING_CELLS as f32) as usize).min(FACING_CELLS - 1);
    (side * FACING_CELLS + cell(u)) * FACING_CELLS + cell(v)
}

impl Hull {
    fn of(positions: &[Vec3]) -> Self {
        let (lo, hi) = positions.iter().fold(
            (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
            |(lo, hi), &p| (lo.min(p), hi.max(p)),
        );
        let centre = (lo + hi) * 0.5;
        // The box's six planes always: the hull within them.
        let mut planes = Vec::new();
        for k in 0..3 {
            let e = Vec3::AXES[k];
            planes.push((e, hi[k] - centre[k]));
            planes.push((-e, centre[k] - lo[k]));
        }
        if positions.len() > EXACT_HULL_MAX_VERTICES {
            planes.extend(bounding_planes(positions, centre));
            return Self::with_planes(planes, centre);
        }
        // Relative to the box's centre: an OBJ need not be centred, and the
        // planes' offsets keep their precision.
        let points: Vec<glam_quickhull::Vec3A> = positions
            .iter()
            .map(|&p| glam_quickhull::Vec3A::from_array((p - centre).to_array()))
            .collect();
        // Only a hull with volume: quickhull returns a flat point set as a
        // two-sided fan, whose planes have no inside.
        let hull = quickhull::ConvexTriangleMesh::try_from_points(&points, None)
            .ok()
            .filter(|h| h.volume() > 1e-9 * (hi - lo).max_element().powi(3));
        if let Some(hull) = hull {
            let verts: Vec<Vec3> = hull
                .vertices()
                .iter()
                .map(|v| Vec3::from_array(v.to_array()))
                .collect();
            let inner = verts.iter().copied().sum::<Vec3>() / verts.len() as f32;
            for tri in hull.indices() {
                let [a, b, c] = tri.map(|k| verts[k as usize]);
                let Some(mut n) = (b - a).cross(c - a).try_normalize() else {
                    continue;
                };
                if n.dot(inner - a) > 0.0 {
                    n = -n;
                }
                // Through the face's farthest corner as rounded.
                planes.push((n, n.dot(a).max(n.dot(b)).max(n.dot(c))));
            }
        }
        Self::with_planes(planes, centre)
    }

    /// The hull of `planes` (relative to `centre`), with its table of the
    /// planes facing each direction.
    fn with_planes(planes: Vec<(Vec3, f32)>, centre: Vec3) -> Self {
        let mut facing = vec![0u32; 6 * FACING_CELLS * FACING_CELLS];
        for side in 0..6 {
            for a in 0..FACING_CELLS {
                for b in 0..FACING_CELLS {
                    let w = |k: usize| (k as f32 + 0.5) / FACING_CELLS as f32 * 2.0 - 1.0;
                    let sign = if side % 2 == 0 { 1.0 } else { -1.0 };
                    let d = match side / 2 {
                        0 => Vec3::new(sign, w(a), w(b)),
                        1 => Vec3::new(w(a), sign, w(b)),
                        _ => Vec3::new(w(a), w(b), sign),
                    };
                    let best = (0..planes.len())
                        .max_by(|&x, &y| planes[x].0.dot(d).total_cmp(&planes[y].0.dot(d)))
                        .unwrap_or(0);
                    facing[facing_cell(d)] = best as u32;
                }
            }
        }
        Self {
            planes,
            centre,
            facing,
        }
    }

    /// Whether the triangle `t` reaches more than `tol` inside the hull:
    /// clipped by every plane moved in by `tol`, something is left. The
    /// planes facing the triangle are tried first.
    fn holds_part_of(&self, t: &[Vec3; 3], tol: f32, buf: &mut [Vec<Vec3>; 2]) -> bool {
        let t = t.map(|x| x - self.centre);
        // The planes facing the triangle's centre and its corners: one of
        // them dismisses nearly every triangle outside (a knot's hull has
        // some 40,000 planes to scan otherwise).
        let outside = |k: u32| {
            let (n, h) = self.planes[k as usize];
            t.iter().all(|&x| n.dot(x) >= h - tol)
        };
        let centre = (t[0] + t[1] + t[2]) / 3.0;
        if [centre, t[0], t[1], t[2]]
            .iter()
            .any(|&d| outside(self.facing[facing_cell(d)]))
        {
            return false;
        }
        // A plane with the whole triangle outside: no clipping needed.
        if self
            .planes
            .iter()
            .any(|&(n, h)| t.iter().all(|&x| n.dot(x) >= h - tol))
        {
            return false;
        }
        let [poly, next] = buf;
        poly.clear();
        poly.extend_from_slice(&t);
        for &(n, h) in &self.planes {
            let side = |x: Vec3| n.dot(x) - (h - tol);
            if poly.iter().all(|&x| side(x) >= 0.0) {
                return false;
            }
            if poly.iter().all(|&x| side(x) < 0.0) {
                continue;
            }
            // Sutherland-Hodgman: keep the part inside this plane.
            next.clear();
            for e in 0..poly.len() {
                let (a, b) = (poly[e], poly[(e + 1) % poly.len()]);
                let (da, db) = (side(a), side(b));
                if da < 0.0 {
                    next.push(a);
                }
                if (da < 0.0) != (db < 0.0) {
                    next.push(a + (b - a) * (da / (da - db)));
                }
            }
            std::mem::swap(poly, next);
            if poly.is_empty() {
                return false;
            }
        }
        true
    }
}

/// Per mesh, what the tests need, made once on first use and shared by
/// the threads.
struct MeshCache<'s> {
    scene: &'s Scene,
    accel: &'s Accel,
    /// Object-space box of each triangle.
    triangle_boxes: Vec<OnceLock<Vec<(Vec3, Vec3)>>>,
    sphere: Vec<OnceLock<BoundingSphere>>,
    hull: Vec<OnceLock<Hull>>,
}

impl<'s> MeshCache<'s> {
    fn new(scene: &'s Scene, accel: &'s Accel) -> Self {
        let n = scene.meshes.len();
        Self {
            scene,
            accel,
            triangle_boxes: (0..n).map(|_| OnceLock::new()).collect(),
            sphere: (0..n).map(|_| OnceLock::new()).collect(),
            hull: (0..n).map(|_| OnceLock::new()).collect(),
        }
    }

    fn sphere(&self, mesh: usize) -> BoundingSphere {
        *self.sphere[mesh]
            .get_or_init(|| BoundingSphere::around(&self.scene.meshes[mesh].positions, 1e-3))
    }

    fn hull(&self, mesh: usize) -> &Hull {
        self.hull[mesh].get_or_init(|| Hull::of(&self.scene.meshes[mesh].positions))
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
    /// (object space): one box test per triangle, no transform. (A grid of
    /// the boxes made 2,025 knots rotated into each other take 32 s to
    /// check instead of 9-14 s: the time is in the hull tests of the
    /// triangles found, not in finding them.)
    fn triangles_in(&self, mesh: usize, region: (Vec3, Vec3)) -> impl Iterator<Item = [Vec3; 3]> {
        let boxes = self.triangle_boxes[mesh].get_or_init(|| {
            (0..self.scene.meshes[mesh].triangles.len())
                .map(|t| {
                    let [a, b, c] = self.triangle(mesh, t);
                    (a.min(b).min(c), a.max(b).max(c))
                })
                .collect()
        });
        (0..boxes.len())
            .filter(move |&t| boxes_overlap(boxes[t], region))
            .map(move |t| self.triangle(mesh, t))
    }
}

/// The box around `region` (world space) in the object space of `x`.
fn box_to_object(x: &InstanceXform, region: (Vec3, Vec3)) -> (Vec3, Vec3) {
    let (lo, hi) = mapped_box(region.0, region.1, |c| x.point_to_object(c));
    // The rotation's rounding: a hair more, never less.
    let pad = (hi - lo).max_element() * 1e-5 + 1e-30;
    (lo - pad, hi + pad)
}

/// Whether instance `j`'s geometry reaches inside instance `i`'s object's
/// convex hull. Everything is tested in `i`'s object space.
fn obstructs(cache: &MeshCache, i: usize, j: usize) -> bool {
    let (scene, accel) = (cache.scene, cache.accel);
    let (xi, xj) = (&accel.instances[i], &accel.instances[j]);
    let (mi, mj) = (scene.instances[i].mesh, scene.instances[j].mesh);
    let (bi, bj) = (accel.instance_bounds[i], accel.instance_bounds[j]);
    // Closer than 1e-4 of the object's size is contact: above the rounding
    // of a rotated floor's triangle mapped into the object's space (about
    // 5e-5 of a knot's size 300 units from the origin), far below anything
    // a walk could notice.
    let tol = cache.sphere(mi).radius * 1e-4;
    // `i`'s own bounds, in its object space.
    let (lo, hi) = accel.blas[mi].bounds;
    let bounds_i = (lo + Vec3::splat(tol), hi - Vec3::splat(tol));
    let mut buf = [Vec::new(), Vec::new()];
    // Only `j`'s triangles where the two boxes meet can reach in.
    let both = (bi.0.max(bj.0), bi.1.min(bj.1));
    cache.triangles_in(mj, box_to_object(xj, both)).any(|t| {
        let t = t.map(|p| xi.point_to_object(xj.point_to_world(p)));
        let tbox = (t[0].min(t[1]).min(t[2]), t[0].max(t[1]).max(t[2]));
        boxes_overlap(tbox, bounds_i) && cache.hull(mi).holds_part_of(&t, tol, &mut buf)
    })
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

/// Every instance that uses an estimator whose object's convex hull holds
/// geometry of another instance (see the module's doc), with the first
/// such other instance. Instances are tested against those whose world
/// boxes overlap theirs (found by the TLAS), so a scene of many separate
/// objects costs little.
pub fn find_obstructed(scene: &Scene, accel: &Accel, ests: &Estimators) -> Vec<Obstruction> {
    use rayon::prelude::*;
    let cache = MeshCache::new(scene, accel);
    // In parallel: 2,025 glass knots on a floor test each against it.
    (0..scene.instances.len())
        .into_par_iter()
        .filter(|&i| ests.per_instance()[i].is_some())
        .filter_map(|i| {
            let bi = accel.instance_bounds[i];
            accel
                .instances_meeting(|lo, hi| boxes_overlap(bi, (lo, hi)))
                .into_iter()
                .find(|&j| j != i && cache.spheres_meet(i, j) && obstructs(&cache, i, j))
                .map(|other| Obstruction { instance: i, other })
        })
        .collect()
}

/// Per instance: the world box around the other instances' geometry
/// inside the sphere of the estimator the instance uses (`None` for
/// instances without one, and where nothing else is inside). Such
/// geometry is outside the object's convex hull ([`find_obstructed`]
/// releases the rest), but can lie on an exit line between the object
/// and the chord's middle, where the thesis' rule starts the exit ray: a
/// tube lying on a floor, a knot's sphere cutting the floor below it. An
/// exit line that meets this box near the object starts at the object's
/// last crossing instead (`Estimators::exit_origin`). The instances whose
/// world boxes meet the sphere are found through the TLAS and their
/// triangles through their BVHs (`Accel::geometry_box_in_ball`: 3.5 ms
/// for the room's 2,025 knots). The box is padded by 1e-4 of the
/// sphere's radius, far above the rounding of the tests that use it.
pub fn find_other_geometry_in_spheres(
    scene: &Scene,
    accel: &Accel,
    ests: &Estimators,
) -> Vec<Option<(Vec3, Vec3)>> {
    use rayon::prelude::*;
    (0..scene.instances.len())
        .into_par_iter()
        .map(|i| {
            let e = ests.per_instance()[i]?;
            let sphere = ests.list[e as usize].sphere;
            let x = &accel.instances[i];
            let (c, r) = (x.point_to_world(sphere.center), sphere.radius * x.scale);
            let pad = Vec3::splat(r * 1e-4);
            accel
                .geometry_box_in_ball(i, c, r)
                .map(|(lo, hi)| (lo - pad, hi + pad))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Above the exact hull's vertex budget the mesh is bounded by planes
    /// that each touch it: every vertex inside, none of the planes farther
    /// than 0.1% of the radius from a sphere's points, a point 0.5% out of
    /// the sphere outside, and a triangle across the middle held while one
    /// 0.3% of the radius away is not.
    #[test]
    fn large_meshes_are_bounded_by_touching_planes() {
        let n = EXACT_HULL_MAX_VERTICES + 1;
        let golden = std::f32::consts::PI * (3.0 - 5f32.sqrt());
        let (c, r) = (Vec3::new(3.0, -1.0, 2.0), 2.0);
        let points: Vec<Vec3> = (0..n)
            .map(|k| {
                let y = 1.0 - 2.0 * (k as f32 + 0.5) / n as f32;
                let s = (1.0 - y * y).max(0.0).sqrt();
                let a = k as f32 * golden * 1.37;
                c + r * Vec3::new(s * a.cos(), y, s * a.sin())
            })
            .collect();
        let hull = Hull::of(&points);
        assert_eq!(hull.planes.len(), 6 + BOUNDING_DIRECTIONS);
        let worst_gap = hull
            .planes
            .iter()
            .map(|&(_, h)| h - r)
            .fold(0.0f32, f32::max);
        assert!(worst_gap < 1e-3 * r, "{worst_gap}");
        for &p in points.iter().step_by(997) {
            let x = p - hull.centre;
            assert!(
                hull.planes.iter().all(|&(n, h)| n.dot(x) <= h + 1e-5),
                "{p} outside"
            );
        }
        let mut buf = [Vec::new(), Vec::new()];
        let tol = r * 1e-4;
        let across = [c - Vec3::X, c + Vec3::X, c + Vec3::Y];
        assert!(hull.holds_part_of(&across, tol, &mut buf));
        let d = r * 1.003;
        let away = [
            c + Vec3::new(-1.0, 0.0, d),
            c + Vec3::new(1.0, 0.0, d),
            c + Vec3::new(0.0, 1.0, d),
        ];
        assert!(!hull.holds_part_of(&away, tol, &mut buf));
        let p_out = c + Vec3::new(0.3, 0.8, 0.5).normalize() * r * 1.005;
        let x = p_out - hull.centre;
        assert!(hull.planes.iter().any(|&(n, h)| n.dot(x) > h));
    }
}
