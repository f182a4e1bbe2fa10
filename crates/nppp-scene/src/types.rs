//! The resolved scene: every name replaced by an index, every mesh turned into
//! triangles, every default filled in. The renderer reads only these types.

use glam::{Quat, Vec3};
use std::path::PathBuf;

/// A pinhole camera exactly as docs/scene-format.md defines it.
#[derive(Clone, Debug, PartialEq)]
pub struct Camera {
    pub position: Vec3,
    pub look_at: Vec3,
    pub up: Vec3,
    pub fov_y_deg: f32,
    pub width: u32,
    pub height: u32,
}

impl Camera {
    /// Sets the image size from the command line's overrides, keeping the
    /// framing: `scale` multiplies both sides; a `width` or `height` alone
    /// sets that side and scales the other to keep the aspect ratio; both
    /// set both (the vertical field of view is kept). Sides are rounded,
    /// at least 1 and at most [`crate::MAX_IMAGE_SIDE`]; `Err` names the
    /// flag that is out of range.
    pub fn resize(
        &mut self,
        scale: Option<f64>,
        width: Option<u32>,
        height: Option<u32>,
    ) -> Result<(), String> {
        let max = crate::MAX_IMAGE_SIDE;
        for (flag, v) in [("--width", width), ("--height", height)] {
            if v == Some(0) {
                return Err(format!("{flag} 0: an image is at least 1 pixel on a side"));
            }
        }
        let (w0, h0) = (self.width as f64, self.height as f64);
        let (w, h) = match (scale, width, height) {
            (Some(_), Some(_), _) | (Some(_), _, Some(_)) => {
                return Err("--scale and --width/--height: give one or the other".into());
            }
            (Some(s), None, None) => {
                if !(s.is_finite() && s > 0.0) {
                    return Err(format!("--scale {s}: must be a positive number"));
                }
                (w0 * s, h0 * s)
            }
            (None, Some(w), None) => (w as f64, h0 * w as f64 / w0),
            (None, None, Some(h)) => (w0 * h as f64 / h0, h as f64),
            (None, Some(w), Some(h)) => (w as f64, h as f64),
            (None, None, None) => return Ok(()),
        };
        // The flag that made the image too large, named in the error.
        let given = match (scale, width, height) {
            (Some(s), _, _) => format!("--scale {s}"),
            (None, Some(w), None) => format!("--width {w}"),
            (None, None, Some(h)) => format!("--height {h}"),
            (None, Some(w), Some(h)) => format!("--width {w} --height {h}"),
            (None, None, None) => String::new(),
        };
        let (w_scene, h_scene) = (self.width, self.height);
        let side = |x: f64, what: &str| -> Result<u32, String> {
            let r = x.round().max(1.0);
            if r > max as f64 {
                // Exact up to 1e15, then in e-notation (--scale 1e300 printed
                // a 300-digit width).
                let r = if r < 1e15 {
                    format!("{r}")
                } else {
                    format!("{r:.3e}")
                };
                return Err(format!(
                    "{given}: the image would be {r} pixels {what} ({}x{} in the scene); images are 1 to {max} pixels on a side",
                    w_scene, h_scene
                ));
            }
            Ok(r as u32)
        };
        self.width = side(w, "wide")?;
        self.height = side(h, "high")?;
        Ok(())
    }
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
    /// A smooth dielectric boundary (as `Dielectric`) around a homogeneous
    /// medium. `sigma_s`, `sigma_a` are per unit length in the mesh's own
    /// coordinates (an instance scaled by s has world coefficients sigma / s,
    /// so one estimator serves every instance); `g` is the Henyey-Greenstein
    /// mean cosine. The mesh must be closed.
    Translucent {
        ior: f32,
        sigma_s: Vec3,
        sigma_a: Vec3,
        g: f32,
    },
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

impl Mesh {
    /// The box around the vertices, in f64 (`None` without vertices).
    pub fn bounds(&self) -> Option<(glam::DVec3, glam::DVec3)> {
        let mut it = self.positions.iter().map(|p| p.as_dvec3());
        let first = it.next()?;
        Some(it.fold((first, first), |(lo, hi), p| (lo.min(p), hi.max(p))))
    }
}

impl Material {
    /// A translucent material's densest channel, sigma_s + sigma_a per unit
    /// length in mesh units (`None` for other materials and a vacuum).
    pub fn densest_sigma_t(&self) -> Option<f64> {
        match self {
            Material::Translucent {
                sigma_s, sigma_a, ..
            } => Some(f64::from((*sigma_s + *sigma_a).max_element())).filter(|&s| s > 0.0),
            _ => None,
        }
    }
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
    /// The OBJ files its meshes were read from: inputs no command may
    /// overwrite (estimator files are in `instances[i].estimator`).
    pub obj_files: Vec<PathBuf>,
    pub camera: Camera,
    pub materials: Vec<Material>,
    pub material_names: Vec<String>,
    pub meshes: Vec<Mesh>,
    pub mesh_names: Vec<String>,
    pub instances: Vec<Instance>,
    pub render: RenderSettings,
}

impl Scene {
    /// Every file this scene was read from, named for a message: the scene
    /// file, its OBJ meshes and its instances' estimator files. Commands
    /// refuse to write an output over any of them.
    pub fn input_files(&self) -> Vec<(String, PathBuf)> {
        let mut v = vec![("the scene file".to_string(), self.path.clone())];
        for f in &self.obj_files {
            v.push((format!("a mesh of the scene ({})", f.display()), f.clone()));
        }
        for (i, inst) in self.instances.iter().enumerate() {
            if let Some(e) = &inst.estimator {
                v.push((format!("instances[{i}].estimator"), e.clone()));
            }
        }
        v
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cam(w: u32, h: u32) -> Camera {
        Camera {
            position: Vec3::ZERO,
            look_at: Vec3::Z,
            up: Vec3::Y,
            fov_y_deg: 40.0,
            width: w,
            height: h,
        }
    }

    #[test]
    fn resize_keeps_the_aspect_ratio() {
        let mut c = cam(256, 128);
        c.resize(Some(0.5), None, None).unwrap();
        assert_eq!((c.width, c.height), (128, 64));
        let mut c = cam(256, 128);
        c.resize(None, Some(100), None).unwrap();
        assert_eq!((c.width, c.height), (100, 50));
        let mut c = cam(256, 128);
        c.resize(None, None, Some(300)).unwrap();
        assert_eq!((c.width, c.height), (600, 300));
        let mut c = cam(256, 128);
        c.resize(None, Some(7), Some(9)).unwrap();
        assert_eq!((c.width, c.height), (7, 9));
        let mut c = cam(3, 3);
        c.resize(Some(1e-9), None, None).unwrap();
        assert_eq!((c.width, c.height), (1, 1));
        let mut c = cam(256, 128);
        c.resize(None, None, None).unwrap();
        assert_eq!((c.width, c.height), (256, 128));
    }

    #[test]
    fn resize_refuses_what_cannot_render() {
        for (s, w, h, needle) in [
            (Some(0.0), None, None, "--scale"),
            (Some(f64::NAN), None, None, "--scale"),
            (Some(1e9), None, None, "pixels wide"),
            (None, Some(0), None, "--width 0"),
            (None, None, Some(0), "--height 0"),
            (None, Some(16385), Some(4), "pixels wide"),
            (Some(2.0), Some(4), None, "one or the other"),
        ] {
            let mut c = cam(256, 128);
            let e = c.resize(s, w, h).unwrap_err();
            assert!(e.contains(needle), "{e}");
            assert_eq!((c.width, c.height), (256, 128));
        }
    }
}
