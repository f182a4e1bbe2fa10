//! Ray queries against the scene: a bottom-level BVH per mesh (obvhs' CWBVH)
//! and a top-level BVH over instances with rigid transforms and uniform scale.
//!
//! Instances only reference their mesh's BLAS, so a mesh instanced thousands
//! of times is stored once. Rays are moved into object space per instance;
//! because scale is uniform and directions stay unit, a world-space distance
//! is the object-space distance times the scale.

use glam::{Quat, Vec3, Vec3A};
use nppp_scene::{Mesh, Transform};
use obvhs::{
    BvhBuildParams, aabb::Aabb, cwbvh::CwBvh, ray::Ray as BvhRay, ray::RayHit, triangle::Triangle,
};
use std::time::Duration;

/// A triangle stored for intersection: a vertex and two edges, full precision.
#[derive(Clone, Copy, Debug)]
struct TriEdges {
    v0: Vec3A,
    e1: Vec3A,
    e2: Vec3A,
}

impl TriEdges {
    /// Möller-Trumbore; returns (t, b1, b2) or None. Degenerate triangles
    /// (zero determinant) never hit.
    #[inline(always)]
    fn intersect(&self, o: Vec3A, d: Vec3A, tmin: f32, tmax: f32) -> Option<(f32, f32, f32)> {
        let p = d.cross(self.e2);
        let det = self.e1.dot(p);
        if det == 0.0 || !det.is_finite() {
            return None;
        }
        let inv = 1.0 / det;
        let s = o - self.v0;
        let b1 = s.dot(p) * inv;
        if !(0.0..=1.0).contains(&b1) {
            return None;
        }
        let q = s.cross(self.e1);
        let b2 = d.dot(q) * inv;
        if b2 < 0.0 || b1 + b2 > 1.0 {
            return None;
        }
        let t = self.e2.dot(q) * inv;
        if t > tmin && t < tmax {
            Some((t, b1, b2))
        } else {
            None
        }
    }
}

/// The bottom level: one mesh's triangles in BVH leaf order.
pub struct Blas {
    bvh: Option<CwBvh>,
    tris: Vec<TriEdges>,
    /// Original triangle index of each stored triangle.
    prim_index: Vec<u32>,
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
        let (lo, hi) = hit_bounds(mesh);
        if tris.is_empty() {
            return Self {
                bvh: None,
                tris: vec![],
                prim_index: vec![],
                bounds: (Vec3::ZERO, Vec3::ZERO),
            };
        }
        let bvh = obvhs::cwbvh::builder::build_cwbvh_from_tris(
            &tris,
            BvhBuildParams::medium_build(),
            &mut Duration::default(),
        );
        // Reorder once so leaves index triangles directly (no indirection per test).
        let prim_index: Vec<u32> = bvh.primitive_indices.clone();
        let stored = prim_index
            .iter()
            .map(|&i| {
                let t = &tris[i as usize];
                TriEdges {
                    v0: t.v0,
                    e1: t.v1 - t.v0,
                    e2: t.v2 - t.v0,
                }
            })
            .collect();
        Self {
            bvh: Some(bvh),
            tris: stored,
            prim_index,
            bounds: (lo, hi),
        }
    }

    /// A mesh that only lives in the merged BLAS: its bounds, no BVH.
    pub fn bounds_only(mesh: &Mesh) -> Self {
        Self {
            bvh: None,
            tris: vec![],
            prim_index: vec![],
            bounds: hit_bounds(mesh),
        }
    }

    pub fn triangle_count(&self) -> usize {
        self.tris.len()
    }

    /// Closest hit along an object-space ray with unit direction, in (tmin, tmax).
    #[inline]
    pub fn intersect(&self, o: Vec3A, d: Vec3A, tmin: f32, tmax: f32) -> Option<ObjectHit> {
        let bvh = self.bvh.as_ref()?;
        let ray = BvhRay::new(o, d, tmin, tmax);
        let mut hit = RayHit::none();
        let mut best: Option<ObjectHit> = None;
        bvh.ray_traverse(ray, &mut hit, |r, id| {
            match self.tris[id].intersect(r.origin, r.direction, r.tmin, r.tmax) {
                Some((t, b1, b2)) => {
                    best = Some(ObjectHit {
                        t,
                        prim: self.prim_index[id],
                        b1,
                        b2,
                    });
                    t
                }
                None => f32::INFINITY,
            }
        });
        best
    }

    /// True if anything lies in (tmin, tmax); stops at the first hit.
    #[inline]
    pub fn occluded(&self, o: Vec3A, d: Vec3A, tmin: f32, tmax: f32) -> bool {
        let Some(bvh) = self.bvh.as_ref() else {
            return false;
        };
        let ray = BvhRay::new(o, d, tmin, tmax);
        !bvh.ray_traverse_miss(ray, |r, id| {
            self.tris[id]
                .intersect(r.origin, r.direction, r.tmin, r.tmax)
                .map_or(f32::INFINITY, |h| h.0)
        })
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
}

/// TLAS item standing for the merged world-space BLAS.
pub const MERGED: u32 = u32::MAX;
/// "Skip no instance" for [`Accel::intersect_skipping`].
pub const NO_SKIP: u32 = u32::MAX - 1;

/// The top level over all instances.
///
/// Instances whose mesh is used only once (walls, a single hero object) are
/// merged into one world-space BLAS: one traversal instead of one per
/// overlapping instance box, and no transform per ray. Meshes used several
/// times, and instances that must stay separate (estimators), are instanced.
pub struct Accel {
    pub blas: Vec<Blas>,
    /// Every instance of the scene, merged or not (normals and lights use them).
    pub instances: Vec<InstanceXform>,
    pub(crate) tlas: Option<CwBvh>,
    /// Per TLAS primitive: an instance index, or [`MERGED`].
    pub(crate) tlas_items: Vec<u32>,
    merged: Option<Blas>,
    /// Per merged triangle: (instance, triangle of its mesh).
    merged_map: Vec<(u32, u32)>,
    /// World-space bounds of every instance (for the scene's scale and the TLAS).
    pub instance_bounds: Vec<(Vec3, Vec3)>,
}

fn transformed_bounds(x: &InstanceXform, lo: Vec3, hi: Vec3) -> (Vec3, Vec3) {
    let (mut a, mut b) = (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN));
    for i in 0..8 {
        let c = Vec3::new(
            if i & 1 == 0 { lo.x } else { hi.x },
            if i & 2 == 0 { lo.y } else { hi.y },
            if i & 4 == 0 { lo.z } else { hi.z },
        );
        let w = x.point_to_world(c);
        a = a.min(w);
        b = b.max(w);
    }
    // Rotation rounding can shave the last ulp off a corner: pad a little.
    let pad = (b - a)
        .max_element()
        .max(a.abs().max_element())
        .max(b.abs().max_element())
        * 1e-6;
    (a - pad, b + pad)
}

impl Accel {
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
        let mut uses = vec![0usize; meshes.len()];
        for (m, _) in instances {
            uses[*m] += 1;
        }
        let merge: Vec<bool> = instances
            .iter()
            .enumerate()
            .map(|(i, (m, _))| uses[*m] == 1 && !keep_separate.get(i).copied().unwrap_or(false))
            .collect();
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
        let mut merged_map = Vec::new();
        for (i, (m, _)) in instances.iter().enumerate() {
            if !merge[i] {
                continue;
            }
            let mesh = &meshes[*m];
            let base = world.positions.len() as u32;
            world
                .positions
                .extend(mesh.positions.iter().map(|p| xforms[i].point_to_world(*p)));
            for (k, t) in mesh.triangles.iter().enumerate() {
                world
                    .triangles
                    .push([t[0] + base, t[1] + base, t[2] + base]);
                merged_map.push((i as u32, k as u32));
            }
        }
        let instance_bounds: Vec<(Vec3, Vec3)> = xforms
            .iter()
            .map(|x| {
                let (lo, hi) = blas[x.blas as usize].bounds;
                transformed_bounds(x, lo, hi)
            })
            .collect();
        let mut tlas_items: Vec<u32> = (0..instances.len() as u32)
            .filter(|i| !merge[*i as usize])
            .collect();
        let mut aabbs: Vec<Aabb> = tlas_items
            .iter()
            .map(|&i| {
                let (a, b) = instance_bounds[i as usize];
                Aabb::new(a.into(), b.into())
            })
            .collect();
        let merged = if world.triangles.is_empty() {
            None
        } else {
            let b = Blas::build(&world);
            let pad = b.bounds.0.abs().max(b.bounds.1.abs()).max_element() * 1e-6;
            aabbs.push(Aabb::new(
                (b.bounds.0 - pad).into(),
                (b.bounds.1 + pad).into(),
            ));
            tlas_items.push(MERGED);
            Some(b)
        };
        let tlas = if aabbs.is_empty() {
            None
        } else {
            Some(obvhs::cwbvh::builder::build_cwbvh(
                &aabbs,
                BvhBuildParams::medium_build(),
                &mut Duration::default(),
            ))
        };
        Self {
            blas,
            instances: xforms,
            tlas,
            tlas_items,
            merged,
            merged_map,
            instance_bounds,
        }
    }

    /// Closest hit of one TLAS item (an instance or the merged BLAS) in (0, tmax), world space.
    #[inline(always)]
    pub(crate) fn item_hit(&self, item: u32, o: Vec3, d: Vec3, tmax: f32) -> Option<SceneHit> {
        if item == MERGED {
            let h = self
                .merged
                .as_ref()?
                .intersect(o.into(), d.into(), 0.0, tmax)?;
            let (instance, prim) = self.merged_map[h.prim as usize];
            return Some(SceneHit {
                t: h.t,
                instance,
                prim,
                b1: h.b1,
                b2: h.b2,
            });
        }
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
        let tlas = self.tlas.as_ref()?;
        let ray = BvhRay::new(o.into(), d.into(), 0.0, tmax);
        let mut hit = RayHit::none();
        let mut best: Option<SceneHit> = None;
        tlas.ray_traverse(ray, &mut hit, |r, id| {
            let item = self.tlas_items[tlas.primitive_indices[id] as usize];
            if item == skip {
                return f32::INFINITY;
            }
            match self.item_hit(item, o, d, r.tmax) {
                Some(h) => {
                    best = Some(h);
                    h.t
                }
                None => f32::INFINITY,
            }
        });
        best
    }

    /// True if any geometry lies along the segment (0, tmax).
    #[inline]
    pub fn occluded(&self, o: Vec3, d: Vec3, tmax: f32) -> bool {
        let Some(tlas) = self.tlas.as_ref() else {
            return false;
        };
        let ray = BvhRay::new(o.into(), d.into(), 0.0, tmax);
        !tlas.ray_traverse_miss(ray, |r, id| {
            let item = self.tlas_items[tlas.primitive_indices[id] as usize];
            let blocked = if item == MERGED {
                self.merged
                    .as_ref()
                    .is_some_and(|b| b.occluded(o.into(), d.into(), 0.0, r.tmax))
            } else {
                let x = &self.instances[item as usize];
                self.blas[x.blas as usize].occluded(
                    x.point_to_object(o).into(),
                    x.dir_to_object(d).into(),
                    0.0,
                    r.tmax * x.inv_scale,
                )
            };
            if blocked { 0.0 } else { f32::INFINITY }
        })
    }

    /// The largest coordinate magnitude in the scene: ray offsets are relative to it.
    pub fn scene_extent(&self) -> f32 {
        self.instance_bounds
            .iter()
            .map(|(a, b)| a.abs().max(b.abs()).max_element())
            .fold(0.0, f32::max)
    }
}
