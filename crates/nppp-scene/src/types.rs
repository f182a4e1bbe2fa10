//! The resolved scene: every name replaced by an index, every mesh turned into
//! triangles, every default filled in. The renderer reads only these types.

use glam::{Quat, Vec3};
use std::path::PathBuf;

/// A pinhole camera exactly as SCENE_FORMAT.md defines it.
#[derive(Clone, Debug, PartialEq)]
pub struct Camera {
    pub position: Vec3,
    pub look_at: Vec3,
    pub up: Vec3,
    pub fov_y_deg: f32,
    pub width: u32,
    pub height: u32,
}

/// A material; the set is closed so the integrator can match on it per bounce.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Material {
    /// Lambertian, two-sided.
    Diffuse { albedo: Vec3 },
    /// GGX (Trowbridge-Reitz) with alpha = roughness, Fresnel = reflectance at all angles, two-sided.
    Conductor { reflectance: Vec3, roughness: f32 },
    /// Smooth glass; `ior` inside (the back side of the mesh), 1.0 outside.
    Dielectric { ior: f32 },
    /// One-sided area light emitting from the front side, reflecting nothing.
    Emitter { radiance: Vec3 },
}

/// A triangle mesh in its own (object) space.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    pub positions: Vec<Vec3>,
    /// Counter-clockwise front faces.
    pub triangles: Vec<[u32; 3]>,
    /// Per-triangle vertex normals, present only for `"smooth": true` OBJ meshes.
    pub shading_normals: Option<Vec<[Vec3; 3]>>,
}

/// Scale (uniform), then rotate, then translate.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Transform {
    pub scale: f32,
    pub rotation: Quat,
    pub translation: Vec3,
}

impl Default for Transform {
    fn default() -> Self {
        Self {
            scale: 1.0,
            rotation: Quat::IDENTITY,
            translation: Vec3::ZERO,
        }
    }
}

impl Transform {
    pub fn point_to_world(&self, p: Vec3) -> Vec3 {
        self.rotation * (p * self.scale) + self.translation
    }
    pub fn point_to_object(&self, p: Vec3) -> Vec3 {
        (self.rotation.inverse() * (p - self.translation)) / self.scale
    }
    /// Directions are only rotated: uniform scale keeps unit vectors unit
    /// (up to the scale factor, which callers handle through `t`).
    pub fn dir_to_world(&self, d: Vec3) -> Vec3 {
        self.rotation * d
    }
    pub fn dir_to_object(&self, d: Vec3) -> Vec3 {
        self.rotation.inverse() * d
    }
}

#[derive(Clone, Debug, PartialEq)]
pub struct Instance {
    pub mesh: usize,
    pub material: usize,
    pub transform: Transform,
    /// Baked estimator file, resolved relative to the scene file's folder.
    pub estimator: Option<PathBuf>,
}

/// The `render` block with defaults filled in.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RenderSettings {
    pub spp: u32,
    pub max_bounces: u32,
    pub seed: u64,
    pub estimator_min_bounces: u32,
}

impl Default for RenderSettings {
    fn default() -> Self {
        Self {
            spp: 64,
            max_bounces: 5,
            seed: 0,
            estimator_min_bounces: 2,
        }
    }
}

#[derive(Clone, Debug)]
pub struct Scene {
    /// The file this scene was read from (for messages and relative paths).
    pub path: PathBuf,
    pub camera: Camera,
    pub materials: Vec<Material>,
    pub material_names: Vec<String>,
    pub meshes: Vec<Mesh>,
    pub mesh_names: Vec<String>,
    pub instances: Vec<Instance>,
    pub render: RenderSettings,
}
