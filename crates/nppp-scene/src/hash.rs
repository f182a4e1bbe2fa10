//! Content hashes that bind a baked estimator to the exact mesh and material
//! it was trained on (docs/scene-format.md: an estimator "is only valid for the
//! mesh and material it was trained on"). Names are deliberately not hashed:
//! renaming a mesh in a scene must not invalidate its estimator, while moving
//! one vertex or changing one roughness value must.
//!
//! FNV-1a 64 over little-endian bytes is tiny, has no dependencies and is
//! fully specified, so any tool (e.g. a Python trainer) can reproduce it:
//! f32 values are hashed by their IEEE bits (so `-0.0` and `0.0` differ,
//! which is fine for an exact-identity check), counts as u64, indices as u32.

use crate::{Material, Mesh, Scene};
use glam::Vec3;

const FNV_OFFSET: u64 = 0xcbf2_9ce4_8422_2325;
const FNV_PRIME: u64 = 0x0000_0100_0000_01b3;

/// FNV-1a 64, the project's one stable hash (content hashes here, the
/// bench's reference cache, render parts' estimator files).
pub struct Fnv1a(u64);

impl Default for Fnv1a {
    fn default() -> Self {
        Self::new()
    }
}

impl Fnv1a {
    pub fn new() -> Self {
        Fnv1a(FNV_OFFSET)
    }
    pub fn finish(&self) -> u64 {
        self.0
    }
    pub fn bytes(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 ^= u64::from(b);
            self.0 = self.0.wrapping_mul(FNV_PRIME);
        }
    }
    pub fn u32(&mut self, x: u32) {
        self.bytes(&x.to_le_bytes());
    }
    pub fn u64(&mut self, x: u64) {
        self.bytes(&x.to_le_bytes());
    }
    pub fn f32(&mut self, x: f32) {
        self.u32(x.to_bits());
    }
    pub fn vec3(&mut self, v: Vec3) {
        self.f32(v.x);
        self.f32(v.y);
        self.f32(v.z);
    }
}

/// Hash of a mesh's geometry, in object space.
///
/// Byte stream: vertex count (u64), every position as x, y, z (f32 bits);
/// triangle count (u64), every index (u32); then a u8 flag 0, or 1 followed
/// by every triangle's three shading normals (f32 bits), because an
/// estimator trained with smooth shading has learned a different response
/// than one trained on flat facets of the same triangles. Lengths are
/// included so that no two different meshes share a byte stream.
pub fn mesh_content_hash(mesh: &Mesh) -> u64 {
    let mut h = Fnv1a::new();
    h.u64(mesh.positions.len() as u64);
    for &p in &mesh.positions {
        h.vec3(p);
    }
    h.u64(mesh.triangles.len() as u64);
    for t in &mesh.triangles {
        for &i in t {
            h.u32(i);
        }
    }
    match &mesh.shading_normals {
        None => h.bytes(&[0]),
        Some(normals) => {
            h.bytes(&[1]);
            for tri in normals {
                for &n in tri {
                    h.vec3(n);
                }
            }
        }
    }
    h.0
}

/// Hash of a material: a one-byte type tag (diffuse 0, conductor 1,
/// dielectric 2, emitter 3, translucent 4), then its parameters as f32 bits
/// in declaration order (conductor: reflectance r, g, b, then roughness;
/// translucent: ior, sigma_s, sigma_a, g).
pub fn material_content_hash(m: &Material) -> u64 {
    let mut h = Fnv1a::new();
    match *m {
        Material::Diffuse { albedo } => {
            h.bytes(&[0]);
            h.vec3(albedo);
        }
        Material::Conductor {
            reflectance,
            roughness,
        } => {
            h.bytes(&[1]);
            h.vec3(reflectance);
            h.f32(roughness);
        }
        Material::Dielectric { ior } => {
            h.bytes(&[2]);
            h.f32(ior);
        }
        Material::Emitter { radiance } => {
            h.bytes(&[3]);
            h.vec3(radiance);
        }
        Material::Translucent {
            ior,
            sigma_s,
            sigma_a,
            g,
        } => {
            h.bytes(&[4]);
            h.f32(ior);
            h.vec3(sigma_s);
            h.vec3(sigma_a);
            h.f32(g);
        }
    }
    h.0
}

/// Hash of what a scene renders, names and file paths aside: the camera
/// (with its image size), every material and mesh by content, and every
/// instance (mesh and material indices, transform bits, whether it has an
/// estimator; the estimator files are hashed by whoever loads them). Render
/// settings (spp, M, seed, P) are not included: a render records those
/// itself. Two render parts of one image must agree on it.
pub fn scene_content_hash(scene: &Scene) -> u64 {
    let mut h = Fnv1a::new();
    let c = &scene.camera;
    h.vec3(c.position);
    h.vec3(c.look_at);
    h.vec3(c.up);
    h.f32(c.fov_y_deg);
    h.u32(c.width);
    h.u32(c.height);
    h.u64(scene.materials.len() as u64);
    for m in &scene.materials {
        h.u64(material_content_hash(m));
    }
    h.u64(scene.meshes.len() as u64);
    for m in &scene.meshes {
        h.u64(mesh_content_hash(m));
    }
    h.u64(scene.instances.len() as u64);
    for i in &scene.instances {
        h.u32(i.mesh as u32);
        h.u32(i.material as u32);
        h.f32(i.transform.scale);
        for x in i.transform.rotation.to_array() {
            h.f32(x);
        }
        h.vec3(i.transform.translation);
        h.bytes(&[i.estimator.is_some() as u8]);
    }
    h.0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fnv1a_matches_reference_vectors() {
        // Published FNV-1a 64 test vectors.
        let mut h = Fnv1a::new();
        h.bytes(b"");
        assert_eq!(h.0, 0xcbf2_9ce4_8422_2325);
        let mut h = Fnv1a::new();
        h.bytes(b"a");
        assert_eq!(h.0, 0xaf63_dc4c_8601_ec8c);
        let mut h = Fnv1a::new();
        h.bytes(b"foobar");
        assert_eq!(h.0, 0x8594_4171_f739_67e8);
    }

    #[test]
    fn material_hash_tells_types_and_values_apart() {
        let a = Material::Diffuse {
            albedo: Vec3::splat(0.5),
        };
        let b = Material::Emitter {
            radiance: Vec3::splat(0.5),
        };
        let c = Material::Diffuse {
            albedo: Vec3::new(0.5, 0.5, 0.50001),
        };
        assert_ne!(material_content_hash(&a), material_content_hash(&b));
        assert_ne!(material_content_hash(&a), material_content_hash(&c));
        assert_eq!(material_content_hash(&a), material_content_hash(&a.clone()));
        let g1 = Material::Conductor {
            reflectance: Vec3::ONE,
            roughness: 0.2,
        };
        let g2 = Material::Conductor {
            reflectance: Vec3::ONE,
            roughness: 0.3,
        };
        assert_ne!(material_content_hash(&g1), material_content_hash(&g2));
    }

    #[test]
    fn mesh_hash_sees_positions_indices_and_normals() {
        let m = crate::shapes::box_mesh(Vec3::ZERO, Vec3::ONE);
        let h = mesh_content_hash(&m);
        assert_eq!(h, mesh_content_hash(&m.clone()));

        let mut moved = m.clone();
        moved.positions[3].x += 1e-3;
        assert_ne!(h, mesh_content_hash(&moved));

        let mut rewound = m.clone();
        rewound.triangles[0].swap(1, 2);
        assert_ne!(h, mesh_content_hash(&rewound));

        let mut smooth = m.clone();
        smooth.shading_normals = Some(vec![[Vec3::Y; 3]; m.triangles.len()]);
        assert_ne!(h, mesh_content_hash(&smooth));

        assert_ne!(mesh_content_hash(&Mesh::default()), h);
    }
}
