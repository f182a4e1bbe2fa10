//! Ray queries against the scene: a bottom-level BVH per mesh and a
//! top-level BVH over instances with rigid transforms and uniform scale
//! (both [`crate::bvh`] layouts), plus one world-space BLAS of everything
//! that need not be instanced.
//!
//! Instances only reference their mesh's BLAS, so a mesh instanced thousands
//! of times is stored once. Rays are moved into object space per instance;
//! because scale is uniform and directions stay unit, a world-space distance
//! is the object-space distance times the scale.

use crate::bvh::{InstanceBvh, MeshBvh, Visit};
use glam::{Quat, Vec3, Vec3A};
use nppp_scene::{Mesh, Transform};
use obvhs::triangle::Triangle;

/// The bottom level: one mesh's triangles in an 8-wide BVH.
pub struct Blas {
    bvh: MeshBvh,
    triangles: usize,
    pub bounds: (Vec3, Vec3),
}

/// A closest hit in object space.
#[derive(Clone, Copy, Debug)]
pub struct ObjectHit {
    pub t: f32,
    /// Triangle index in the mesh's own order.
    pub prim: u32,
    pub b1: f32,
    pub b2: f32,
    /// Unit geometric normal (e1 x e2), object space.
    pub ng: Vec3,
}

/// Bounds of the triangles that can be hit, not of every position: a vertex
/// no triangle uses (common in OBJ exports), or one only a zero-area
/// triangle uses, must not grow the scene's extent, which sets the ray-offset
/// floor (a stray vertex at 1e9 made the Cornell box 24% brighter through
/// light leaks). A mesh with no such triangle has the empty box at its origin.
fn hit_bounds(mesh: &Mesh) -> (Vec3, Vec3) {
    let (mut lo, mut hi) = (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN));
    for t in &mesh.triangles {
        let [a, b, c] = t.map(|i| mesh.positions[i as usize]);
        if (b - a).cross(c - a) != Vec3::ZERO {
            lo = lo.min(a.min(b).min(c));
            hi = hi.max(a.max(b).max(c));
        }
    }
    if lo.x > hi.x {
        (Vec3::ZERO, Vec3::ZERO)
    } else {
        (lo, hi)
    }
}

impl Blas {
    pub fn build(mesh: &Mesh) -> Self {
        let tris: Vec<Triangle> = mesh
            .triangles
            .iter()
            .map(|t| Triangle {
                v0: mesh.positions[t[0] as usize].into(),
                v1: mesh.positions[t[1] as usize].into(),
                v2: mesh.positions[t[2] as usize].into(),
            })
            .collect();
        Self {
            bvh: MeshBvh::build(&tris),
            triangles: tris.len(),
            bounds: hit_bounds(mesh),
        }
    }

    /// A mesh that only lives in the merged BLAS: its bounds, no BVH.
    pub fn bounds_only(mesh: &Mesh) -> Self {
        Self {
            bvh: MeshBvh::build(&[]),
            triangles: 0,
            bounds: hit_bounds(mesh),
        }
    }

    pub fn triangle_count(&self) -> usize {
        self.triangles
    }

    /// Closest hit along an object-space ray with unit direction, in (tmin, tmax).
    #[inline]
    pub fn intersect(&self, o: Vec3A, d: Vec3A, tmin: f32, tmax: f32) -> Option<ObjectHit> {
        self.bvh.intersect(o, d, tmin, tmax).map(|h| ObjectHit {
            t: h.t,
            prim: h.prim,
            b1: h.b1,
            b2: h.b2,
            ng: nppp_geom::unit_normal(h.ng),
        })
    }

    /// False when the ray (t > 0) certainly misses the mesh: it enters none
    /// of its BVH root's child boxes.
    #[inline]
    pub fn may_hit(&self, o: Vec3A, d: Vec3A) -> bool {
        self.bvh.may_hit(o, d)
    }

    /// True if anything lies in (tmin, tmax); stops at the first hit.
    #[inline]
    pub fn occluded(&self, o: Vec3A, d: Vec3A, tmin: f32, tmax: f32) -> bool {
        self.bvh.occluded(o, d, tmin, tmax)
    }

    /// The corners of each triangle that reaches inside the ball of
    /// `center` and `radius` (object space), to `f`. For building scenes.
    pub fn for_each_triangle_in_ball(
        &self,
        center: Vec3,
        radius: f32,
        mut f: impl FnMut([Vec3; 3]),
    ) {
        let r2 = radius * radius;
        self.bvh.visit_triangles(
            |lo, hi| ball_meets_box(center, radius, lo, hi),
            |[a, b, c]| {
                let (p, _, _) =
                    nppp_geom::closest_point::closest_point_on_triangle(center, a, b, c);
                if p.distance_squared(center) <= r2 {
                    f([a, b, c]);
                }
                true
            },
        );
    }
}

/// An instance as the traversal needs it: the inverse transform precomputed.
#[derive(Clone, Copy, Debug)]
pub struct InstanceXform {
    pub blas: u32,
    pub rotation: Quat,
    pub inv_rotation: Quat,
    pub scale: f32,
    pub inv_scale: f32,
    pub translation: Vec3,
}

impl InstanceXform {
    pub fn new(blas: u32, t: &Transform) -> Self {
        Self {
            blas,
            rotation: t.rotation,
            inv_rotation: t.rotation.inverse(),
            scale: t.scale,
            inv_scale: 1.0 / t.scale,
            translation: t.translation,
        }
    }
    #[inline(always)]
    pub fn point_to_object(&self, p: Vec3) -> Vec3 {
        (self.inv_rotation * (p - self.translation)) * self.inv_scale
    }
    #[inline(always)]
    pub fn dir_to_object(&self, d: Vec3) -> Vec3 {
        self.inv_rotation * d
    }
    #[inline(always)]
    pub fn point_to_world(&self, p: Vec3) -> Vec3 {
        self.rotation * (p * self.scale) + self.translation
    }
    #[inline(always)]
    pub fn dir_to_world(&self, d: Vec3) -> Vec3 {
        self.rotation * d
    }
}

/// A closest hit in the scene.
#[derive(Clone, Copy, Debug)]
pub struct SceneHit {
    pub t: f32,
    pub instance: u32,
    pub prim: u32,
    pub b1: f32,
    pub b2: f32,
    /// Unit geometric normal, world space (the front side is the mesh's
    /// counter-clockwise side; scale is positive, so transforms keep it).
    pub ng: Vec3,
}

/// "Skip no instance" for [`Accel::intersect_skipping`].
pub const NO_SKIP: u32 = u32::MAX - 1;

/// The top level over all instances.
///
/// Instances whose mesh is used only once (walls, a single hero object) are
/// merged into one world-space BLAS: one traversal instead of one per
/// overlapping instance box, and no transform per ray. Meshes used several
/// times, and instances that must stay separate (estimators), are instanced
/// under the TLAS. The merged BLAS sits beside the TLAS, not under it: a ray
/// traverses it first and then the TLAS up to its hit, so a scene with
/// nothing instanced (the common case) pays no TLAS traversal at all.
pub struct Accel {
    pub blas: Vec<Blas>,
    /// Every instance of the scene, merged or not (normals and lights use them).
    pub instances: Vec<InstanceXform>,
    /// Over the instanced (unmerged) instances' world boxes; empty if none.
    pub(crate) tlas: InstanceBvh,
    /// Per TLAS item: its instance (never a merged one).
    pub(crate) tlas_items: Vec<u32>,
    /// Per instance: lives in the merged world BLAS.
    merged_flags: Vec<bool>,
    merged: Option<Blas>,
    /// Per merged instance, in merge order: (its first merged triangle,
    /// instance). A hit's instance is a binary search in this short, cached
    /// table, not a load from a per-triangle table (a cache miss per hit).
    merged_ranges: Vec<(u32, u32)>,
    /// World-space bounds of every instance (for the scene's scale and the TLAS).
    pub instance_bounds: Vec<(Vec3, Vec3)>,
}

/// The box around the eight corners of box `lo`..`hi` moved by `map` (a
/// rigid transform: the box of the moved box), unpadded.
pub(crate) fn mapped_box(lo: Vec3, hi: Vec3, map: impl Fn(Vec3) -> Vec3) -> (Vec3, Vec3) {
    let (mut a, mut b) = (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN));
    for i in 0..8 {
        let c = Vec3::new(
            if i & 1 == 0 { lo.x } else { hi.x },
            if i & 2 == 0 { lo.y } else { hi.y },
            if i & 4 == 0 { lo.z } else { hi.z },
        );
        let w = map(c);
        a = a.min(w);
        b = b.max(w);
    }
    (a, b)
}

/// Whether the ball of `center` and `radius` meets the box `lo`..`hi`: the
/// box's point closest to the centre is inside the ball.
#[inline]
pub(crate) fn ball_meets_box(center: Vec3, radius: f32, lo: Vec3, hi: Vec3) -> bool {
    center.clamp(lo, hi).distance_squared(center) <= radius * radius
}

fn transformed_bounds(x: &InstanceXform, lo: Vec3, hi: Vec3) -> (Vec3, Vec3) {
    let (a, b) = mapped_box(lo, hi, |c| x.point_to_world(c));
    // Rotation rounding can shave the last ulp off a corner: pad a little.
    let pad = (b - a)
        .max_element()
        .max(a.abs().max_element())
        .max(b.abs().max_element())
        * 1e-6;
    (a - pad, b + pad)
}

impl Accel {
    /// Which instances [`Self::build`] merges into the world BLAS: those of
    /// meshes used once, unless `keep_separate` says otherwise (a mesh used
    /// by many instances keeps one shared BLAS).
    pub fn merge_plan(
        mesh_count: usize,
        instances: &[(usize, Transform)],
        keep_separate: &[bool],
    ) -> Vec<bool> {
        let mut uses = vec![0usize; mesh_count];
        for (m, _) in instances {
            uses[*m] += 1;
        }
        instances
            .iter()
            .enumerate()
            .map(|(i, (m, _))| uses[*m] == 1 && !keep_separate.get(i).copied().unwrap_or(false))
            .collect()
    }

    /// Builds the BLASes (in parallel) and the TLAS. `keep_separate[i]` keeps
    /// instance `i` out of the merged BLAS.
    pub fn build(
        meshes: &[Mesh],
        instances: &[(usize, Transform)],
        keep_separate: &[bool],
    ) -> Self {
        use rayon::prelude::*;
        let xforms: Vec<InstanceXform> = instances
            .iter()
            .map(|(m, t)| InstanceXform::new(*m as u32, t))
            .collect();
        let merge = Self::merge_plan(meshes.len(), instances, keep_separate);
        // A mesh whose only instance is merged needs no BLAS of its own.
        let needs_blas: Vec<bool> = (0..meshes.len())
            .map(|m| {
                instances
                    .iter()
                    .zip(&merge)
                    .any(|((mi, _), mg)| *mi == m && !mg)
            })
            .collect();
        let blas: Vec<Blas> = meshes
            .par_iter()
            .zip(needs_blas.par_iter())
            .map(|(m, need)| {
                if *need {
                    Blas::build(m)
                } else {
                    Blas::bounds_only(m)
                }
            })
            .collect();
        let mut world = Mesh::default();
        let mut merged_ranges = Vec::new();
        for (i, (m, _)) in instances.iter().enumerate() {
            if !merge[i] {
                continue;
            }
            let mesh = &meshes[*m];
            let base = world.positions.len() as u32;
            world
                .positions
                .extend(mesh.positions.iter().map(|p| xforms[i].point_to_world(*p)));
            merged_ranges.push((world.triangles.len() as u32, i as u32));
            for t in &mesh.triangles {
                world
                    .triangles
                    .push([t[0] + base, t[1] + base, t[2] + base]);
            }
        }
        let instance_bounds: Vec<(Vec3, Vec3)> = xforms
            .iter()
            .map(|x| {
                let (lo, hi) = blas[x.blas as usize].bounds;
                transformed_bounds(x, lo, hi)
            })
            .collect();
        let tlas_items: Vec<u32> = (0..instances.len() as u32)
            .filter(|i| !merge[*i as usize])
            .collect();
        let boxes: Vec<(Vec3, Vec3)> = tlas_items
            .iter()
            .map(|&i| instance_bounds[i as usize])
            .collect();
        let merged = (!world.triangles.is_empty()).then(|| Blas::build(&world));
        let tlas = InstanceBvh::build(&boxes);
        Self {
            blas,
            instances: xforms,
            tlas,
            tlas_items,
            merged_flags: merge,
            merged,
            merged_ranges,
            instance_bounds,
        }
    }

    /// Closest hit in the merged world-space BLAS in (0, tmax).
    #[inline(always)]
    pub(crate) fn merged_hit(&self, o: Vec3, d: Vec3, tmax: f32) -> Option<SceneHit> {
        let h = self
            .merged
            .as_ref()?
            .intersect(o.into(), d.into(), 0.0, tmax)?;
        // The last range starting at or before the hit triangle (ranges of
        // empty meshes share a start; the later one holds the triangles).
        let r =
            crate::prefix::partition_point(&self.merged_ranges, |&(first, _)| first <= h.prim) - 1;
        let (first, instance) = self.merged_ranges[r];
        let prim = h.prim - first;
        Some(SceneHit {
            t: h.t,
            instance,
            prim,
            b1: h.b1,
            b2: h.b2,
            ng: h.ng,
        })
    }

    /// Closest hit of one instanced (TLAS) instance in (0, tmax), world space.
    #[inline(always)]
    pub(crate) fn item_hit(&self, item: u32, o: Vec3, d: Vec3, tmax: f32) -> Option<SceneHit> {
        let x = &self.instances[item as usize];
        let oo = x.point_to_object(o);
        let od = x.dir_to_object(d);
        let h =
            self.blas[x.blas as usize].intersect(oo.into(), od.into(), 0.0, tmax * x.inv_scale)?;
        Some(SceneHit {
            t: h.t * x.scale,
            instance: item,
            prim: h.prim,
            b1: h.b1,
            b2: h.b2,
            ng: x.dir_to_world(h.ng),
        })
    }

    /// Closest hit along a world ray (unit direction) with t in (0, tmax).
    #[inline]
    pub fn intersect(&self, o: Vec3, d: Vec3, tmax: f32) -> Option<SceneHit> {
        self.intersect_skipping(o, d, tmax, NO_SKIP)
    }

    /// [`Self::intersect`] ignoring instance `skip` (the one a path has just
    /// left through its estimator; such instances are never merged).
    #[inline]
    pub fn intersect_skipping(&self, o: Vec3, d: Vec3, tmax: f32, skip: u32) -> Option<SceneHit> {
        let mut best = self.merged_hit(o, d, tmax);
        let tmax = best.map_or(tmax, |h| h.t);
        self.tlas
            .traverse(o.into(), d.into(), tmax, true, |item, tmax| {
                let instance = self.tlas_items[item as usize];
                if instance != skip
                    && let Some(h) = self.item_hit(instance, o, d, *tmax)
                {
                    best = Some(h);
                    *tmax = h.t;
                }
                Visit::Continue
            });
        best
    }

    /// True if any geometry lies along the segment (0, tmax).
    #[inline]
    pub fn occluded(&self, o: Vec3, d: Vec3, tmax: f32) -> bool {
        if self
            .merged
            .as_ref()
            .is_some_and(|b| b.occluded(o.into(), d.into(), 0.0, tmax))
        {
            return true;
        }
        let mut blocked = false;
        self.tlas
            .traverse(o.into(), d.into(), tmax, false, |item, tmax| {
                let x = &self.instances[self.tlas_items[item as usize] as usize];
                blocked = self.blas[x.blas as usize].occluded(
                    x.point_to_object(o).into(),
                    x.dir_to_object(d).into(),
                    0.0,
                    *tmax * x.inv_scale,
                );
                if blocked {
                    Visit::Stop
                } else {
                    Visit::Continue
                }
            });
        blocked
    }

    /// The world box of the geometry of every instance but `skip` inside
    /// the ball of `center` and `radius` (world space), each triangle's
    /// box cut to the ball's; `None` where there is none. For building
    /// scenes: the merged BLAS and the BLAS of each instanced instance
    /// whose box meets the ball are searched by their BVHs.
    pub fn geometry_box_in_ball(
        &self,
        skip: usize,
        center: Vec3,
        radius: f32,
    ) -> Option<(Vec3, Vec3)> {
        let ball_box = (center - Vec3::splat(radius), center + Vec3::splat(radius));
        let mut found: Option<(Vec3, Vec3)> = None;
        let mut add = |[a, b, c]: [Vec3; 3]| {
            let lo = a.min(b).min(c).max(ball_box.0);
            let hi = a.max(b).max(c).min(ball_box.1);
            found = Some(found.map_or((lo, hi), |(l, h)| (l.min(lo), h.max(hi))));
        };
        if let Some(merged) = &self.merged {
            merged.for_each_triangle_in_ball(center, radius, &mut add);
        }
        for i in self.instances_meeting(|lo, hi| ball_meets_box(center, radius, lo, hi)) {
            if i == skip || self.is_merged(i) {
                continue;
            }
            let x = &self.instances[i];
            self.blas[x.blas as usize].for_each_triangle_in_ball(
                x.point_to_object(center),
                radius * x.inv_scale,
                |t| add(t.map(|p| x.point_to_world(p))),
            );
        }
        found
    }

    /// Every instance whose world box `keep` accepts (`keep(lo, hi)`, which
    /// must accept every box around one it accepts), in index order: the
    /// TLAS's items found by its BVH, the merged ones by a scan. For
    /// building scenes (40,000 estimator instances, each checked against
    /// every other instance, took 2.3 s).
    pub fn instances_meeting(&self, keep: impl Fn(Vec3, Vec3) -> bool) -> Vec<usize> {
        let mut found = Vec::new();
        self.tlas.visit_items(&keep, |item| {
            let i = self.tlas_items[item as usize] as usize;
            let (lo, hi) = self.instance_bounds[i];
            if keep(lo, hi) {
                found.push(i);
            }
        });
        found.extend(
            self.merged_ranges
                .iter()
                .map(|&(_, i)| i as usize)
                .filter(|&i| {
                    let (lo, hi) = self.instance_bounds[i];
                    keep(lo, hi)
                }),
        );
        found.sort_unstable();
        found
    }

    /// Whether instance `i` was merged into the world BLAS (and so cannot be
    /// stood in for by an estimator).
    pub fn is_merged(&self, i: usize) -> bool {
        self.merged_flags.get(i).copied().unwrap_or(false)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nppp_scene::{box_mesh, quad_mesh};

    /// `instances_meeting` finds, in index order, exactly the instances
    /// whose world boxes a region meets, instanced (under the TLAS) or
    /// merged, and `geometry_box_in_ball` boxes the triangles in a ball
    /// from both kinds of instance, skipping the one it is asked to.
    #[test]
    fn region_queries_find_what_a_scan_finds() {
        let cube = box_mesh(Vec3::splat(-0.5), Vec3::splat(0.5));
        let floor = quad_mesh([
            Vec3::new(-50.0, 0.0, -50.0),
            Vec3::new(-50.0, 0.0, 50.0),
            Vec3::new(50.0, 0.0, 50.0),
            Vec3::new(50.0, 0.0, -50.0),
        ]);
        let meshes = vec![cube, floor];
        let mut rng = nppp_geom::SampleRng::from_seed(7);
        // A floor (merged: its mesh is used once) and 300 turned cubes
        // (instanced: one mesh, many uses).
        let mut instances = vec![(1, Transform::default())];
        for _ in 0..300 {
            let t = Transform {
                scale: 0.2 + rng.uniform(),
                rotation: Quat::from_axis_angle(
                    Vec3::new(rng.uniform(), rng.uniform(), 1.0).normalize(),
                    rng.uniform() * 6.0,
                ),
                translation: Vec3::new(rng.uniform(), rng.uniform(), rng.uniform()) * 40.0
                    - Vec3::new(20.0, 5.0, 20.0),
            };
            instances.push((0, t));
        }
        let accel = Accel::build(&meshes, &instances, &[]);
        assert!(accel.is_merged(0) && !accel.is_merged(1));
        for k in 0..40 {
            let c = Vec3::new(rng.uniform(), rng.uniform(), rng.uniform()) * 40.0
                - Vec3::new(20.0, 5.0, 20.0);
            let r = 0.5 + rng.uniform() * 4.0 * (k % 3) as f32;
            let meets = |lo: Vec3, hi: Vec3| ball_meets_box(c, r, lo, hi);
            let want: Vec<usize> = (0..instances.len())
                .filter(|&i| meets(accel.instance_bounds[i].0, accel.instance_bounds[i].1))
                .collect();
            assert_eq!(accel.instances_meeting(meets), want, "ball {c} {r}");
            // The triangles in the ball, by a scan of every instance's
            // world-space triangles but the skipped one.
            let skip = want.iter().copied().find(|&i| i > 0).unwrap_or(usize::MAX);
            let mut scan: Option<(Vec3, Vec3)> = None;
            for (i, (m, _)) in instances.iter().enumerate() {
                if i == skip {
                    continue;
                }
                let mesh = &meshes[*m];
                for t in &mesh.triangles {
                    let [a, b, q] =
                        t.map(|v| accel.instances[i].point_to_world(mesh.positions[v as usize]));
                    let (p, _, _) = nppp_geom::closest_point::closest_point_on_triangle(c, a, b, q);
                    if p.distance(c) < r * 0.999 {
                        let lo = a.min(b).min(q).max(c - r);
                        let hi = a.max(b).max(q).min(c + r);
                        scan = Some(scan.map_or((lo, hi), |(l, h)| (l.min(lo), h.max(hi))));
                    }
                }
            }
            let got = accel.geometry_box_in_ball(skip, c, r);
            match (scan, got) {
                (None, g) => assert!(
                    g.is_none_or(|(lo, hi)| (hi - lo).max_element() < 0.01 * r),
                    "{g:?}"
                ),
                (Some((lo, hi)), Some((glo, ghi))) => {
                    // The same box, within the rounding of the transforms
                    // (and of triangles within 0.1% of the ball's boundary).
                    let tol = 0.01 * r;
                    assert!(
                        glo.cmple(lo + tol).all() && ghi.cmpge(hi - tol).all(),
                        "{lo} {hi} vs {glo} {ghi}"
                    );
                    assert!(glo.cmpge(c - r - tol).all() && ghi.cmple(c + r + tol).all());
                }
                (s, None) => panic!("a scan found {s:?} in ball {c} {r}, the query nothing"),
            }
        }
    }
}
