//! Ray queries against the scene: a bottom-level BVH per mesh (obvhs' CWBVH)
//! and a top-level BVH over instances with rigid transforms and uniform scale.
//!
//! Instances only reference their mesh's BLAS, so a mesh instanced thousands
//! of times is stored once. Rays are moved into object space per instance;
//! because scale is uniform and directions stay unit, a world-space distance
//! is the object-space distance times the scale.

use glam::{Quat, Vec3, Vec3A};
use nppp_scene::{Mesh, Transform};
use obvhs::{BvhBuildParams, aabb::Aabb, cwbvh::CwBvh, ray::Ray as BvhRay, ray::RayHit, triangle::Triangle};
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
        if t > tmin && t < tmax { Some((t, b1, b2)) } else { None }
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
        let (mut lo, mut hi) = (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN));
        for p in &mesh.positions {
            lo = lo.min(*p);
            hi = hi.max(*p);
        }
        if tris.is_empty() {
            return Self { bvh: None, tris: vec![], prim_index: vec![], bounds: (Vec3::ZERO, Vec3::ZERO) };
        }
        let bvh = obvhs::cwbvh::builder::build_cwbvh_from_tris(&tris, BvhBuildParams::medium_build(), &mut Duration::default());
        // Reorder once so leaves index triangles directly (no indirection per test).
        let prim_index: Vec<u32> = bvh.primitive_indices.clone();
        let stored = prim_index
            .iter()
            .map(|&i| {
                let t = &tris[i as usize];
                TriEdges { v0: t.v0, e1: t.v1 - t.v0, e2: t.v2 - t.v0 }
            })
            .collect();
        Self { bvh: Some(bvh), tris: stored, prim_index, bounds: (lo, hi) }
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
        bvh.ray_traverse(ray, &mut hit, |r, id| match self.tris[id].intersect(r.origin, r.direction, r.tmin, r.tmax) {
            Some((t, b1, b2)) => {
                best = Some(ObjectHit { t, prim: self.prim_index[id], b1, b2 });
                t
            }
            None => f32::INFINITY,
        });
        best
    }

    /// True if anything lies in (tmin, tmax); stops at the first hit.
    #[inline]
    pub fn occluded(&self, o: Vec3A, d: Vec3A, tmin: f32, tmax: f32) -> bool {
        let Some(bvh) = self.bvh.as_ref() else { return false };
        let ray = BvhRay::new(o, d, tmin, tmax);
        !bvh.ray_traverse_miss(ray, |r, id| {
            self.tris[id].intersect(r.origin, r.direction, r.tmin, r.tmax).map_or(f32::INFINITY, |h| h.0)
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

/// The top level over all instances.
pub struct Accel {
    pub blas: Vec<Blas>,
    pub instances: Vec<InstanceXform>,
    pub(crate) tlas: Option<CwBvh>,
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
    let pad = (b - a).max_element().max(a.abs().max_element()).max(b.abs().max_element()) * 1e-6;
    (a - pad, b + pad)
}

impl Accel {
    /// Builds one BLAS per mesh (in parallel) and the TLAS over instances.
    pub fn build(meshes: &[Mesh], instances: &[(usize, Transform)]) -> Self {
        use rayon::prelude::*;
        let blas: Vec<Blas> = meshes.par_iter().map(Blas::build).collect();
        let xforms: Vec<InstanceXform> = instances.iter().map(|(m, t)| InstanceXform::new(*m as u32, t)).collect();
        let instance_bounds: Vec<(Vec3, Vec3)> = xforms
            .iter()
            .map(|x| {
                let (lo, hi) = blas[x.blas as usize].bounds;
                transformed_bounds(x, lo, hi)
            })
            .collect();
        let aabbs: Vec<Aabb> = instance_bounds.iter().map(|(a, b)| Aabb::new((*a).into(), (*b).into())).collect();
        let tlas = if aabbs.is_empty() {
            None
        } else {
            Some(obvhs::cwbvh::builder::build_cwbvh(&aabbs, BvhBuildParams::medium_build(), &mut Duration::default()))
        };
        Self { blas, instances: xforms, tlas, instance_bounds }
    }

    /// Closest hit along a world ray (unit direction) with t in (0, tmax).
    #[inline]
    pub fn intersect(&self, o: Vec3, d: Vec3, tmax: f32) -> Option<SceneHit> {
        self.intersect_skipping(o, d, tmax, u32::MAX)
    }

    /// [`Self::intersect`] ignoring instance `skip` (the one a path has just
    /// left through its estimator).
    #[inline]
    pub fn intersect_skipping(&self, o: Vec3, d: Vec3, tmax: f32, skip: u32) -> Option<SceneHit> {
        let tlas = self.tlas.as_ref()?;
        let ray = BvhRay::new(o.into(), d.into(), 0.0, tmax);
        let mut hit = RayHit::none();
        let mut best: Option<SceneHit> = None;
        tlas.ray_traverse(ray, &mut hit, |r, id| {
            let inst_id = tlas.primitive_indices[id];
            if inst_id == skip {
                return f32::INFINITY;
            }
            let x = &self.instances[inst_id as usize];
            let oo = x.point_to_object(o);
            let od = x.dir_to_object(d);
            let tmax_obj = r.tmax * x.inv_scale;
            match self.blas[x.blas as usize].intersect(oo.into(), od.into(), 0.0, tmax_obj) {
                Some(h) => {
                    let t = h.t * x.scale;
                    best = Some(SceneHit { t, instance: inst_id, prim: h.prim, b1: h.b1, b2: h.b2 });
                    t
                }
                None => f32::INFINITY,
            }
        });
        best
    }

    /// True if any geometry lies along the segment (0, tmax).
    #[inline]
    pub fn occluded(&self, o: Vec3, d: Vec3, tmax: f32) -> bool {
        let Some(tlas) = self.tlas.as_ref() else { return false };
        let ray = BvhRay::new(o.into(), d.into(), 0.0, tmax);
        !tlas.ray_traverse_miss(ray, |r, id| {
            let x = &self.instances[tlas.primitive_indices[id] as usize];
            let oo = x.point_to_object(o);
            let od = x.dir_to_object(d);
            if self.blas[x.blas as usize].occluded(oo.into(), od.into(), 0.0, r.tmax * x.inv_scale) { 0.0 } else { f32::INFINITY }
        })
    }

    /// The largest coordinate magnitude in the scene: ray offsets are relative to it.
    pub fn scene_extent(&self) -> f32 {
        self.instance_bounds.iter().map(|(a, b)| a.abs().max(b.abs()).max_element()).fold(0.0, f32::max)
    }
}
