//! The scene prepared for rendering: acceleration structure, per-instance
//! shading data and the light list, built once from a loaded [`Scene`].

use crate::accel::{Accel, SceneHit};
use crate::camera::PinholeCamera;
use crate::estimator::Estimator;
use crate::lights::{LightTriangle, Lights};
use crate::medium::Medium;
use crate::object_walk::ObjectTracer;
use crate::surface::{OFFSET_REL, SurfaceKind};
use glam::Vec3;
use nppp_scene::Scene;

/// Memory a render holds per triangle of the meshes its instances use: the
/// mesh, its BVH, and the world-space copies that merge the meshes used
/// once into one tree (and a second layout when estimators are in use).
/// Measured peak resident memory of `nppp render`: 330-340 bytes a triangle
/// with one to four icospheres of 1.3 M triangles; rounded up.
pub const RENDER_BYTES_PER_TRIANGLE: u64 = 400;
/// Memory a render holds per pixel: the image (the film's sums are kept a
/// band of tiles at a time, `render::render`), a reference image, the EXR's
/// rows and the preview. Measured above the scene's own peak: 16 bytes a
/// pixel at 4096 x 4096 with `--png`, 19 at 2048 x 2048 with `--reference`;
/// rounded up. (160 were charged until 2026-11-27, for a full film of sums
/// no plain render holds: a 4096 x 4096 render was refused under a 1.5 GB
/// limit it fits in.)
pub const RENDER_BYTES_PER_PIXEL: u64 = 48;
/// What `--estimators auto --auto-confirm` holds per pixel beyond
/// [`RENDER_BYTES_PER_PIXEL`] where its confirmation pass runs (images up
/// to `PilotOptions::confirm_max_pixels`): two films of exact sums at the
/// image's resolution, and its two halves' images.
pub const AUTO_CONFIRM_BYTES_PER_PIXEL: u64 = 2 * crate::render_part::PART_BYTES_PER_PIXEL + 2 * 12;
/// Memory a render holds per instance: its transforms and bounds, its
/// share of the TLAS, and the per-instance tables of shading, lights and
/// estimators. An upper bound: the peak resident memory of `nppp render`
/// from 100,000 to 400,000 instances of a 12-triangle box grew by 1,074
/// bytes an instance, and most of that peak is the scene file's parse,
/// over before the render starts; rounded up.
pub const RENDER_BYTES_PER_INSTANCE: u64 = 1200;
/// Memory a render holds per byte of each distinct estimator file it
/// loads: the file as read, its grids and decoders once parsed, the mask's
/// sign table and the surface snap grid. Measured peak resident memory of
/// `nppp render` at 64 x 64, neural over oracle (which loads no file): 61
/// MB for the knot's 16.8 MB file alone, 78 MB for three such files;
/// rounded up from 3.6x.
pub const RENDER_BYTES_PER_ESTIMATOR_FILE_BYTE: u64 = 4;

/// Why `scene` cannot be rendered in the memory available, if it cannot:
/// checked before the acceleration structures are built, so such a scene
/// gets a message instead of an allocation failure. `pixel_bytes`: what the
/// render holds per pixel ([`RENDER_BYTES_PER_PIXEL`], with
/// [`AUTO_CONFIRM_BYTES_PER_PIXEL`] added for `--auto-confirm`); `mode`:
/// which estimators it loads (the files of all but `Off` and `Oracle`).
pub fn render_memory_problem(
    scene: &Scene,
    pixel_bytes: u64,
    mode: crate::estimator::EstimatorMode,
) -> Option<String> {
    let available = nppp_files::available_memory()?;
    let estimator_bytes = estimator_file_bytes(scene, mode);
    render_memory_problem_within(scene, pixel_bytes, estimator_bytes, available)
}

/// The total size of the distinct estimator files a render in `mode`
/// loads (one file under several spellings once, as `Estimators::load`
/// keys them; files on emitters are not loaded). A file that cannot be
/// read counts 0: loading it reports that.
fn estimator_file_bytes(scene: &Scene, mode: crate::estimator::EstimatorMode) -> u64 {
    use crate::estimator::EstimatorMode;
    if matches!(mode, EstimatorMode::Off | EstimatorMode::Oracle) {
        return 0;
    }
    let files: std::collections::BTreeSet<std::path::PathBuf> = scene
        .instances
        .iter()
        .enumerate()
        .filter(|&(ii, _)| !crate::estimator::on_emitter(scene, ii))
        .filter_map(|(_, inst)| inst.estimator.as_ref())
        .map(|p| crate::estimator::estimator_file_key(p))
        .collect();
    files
        .iter()
        .filter_map(|p| std::fs::metadata(p).ok())
        .map(|m| m.len())
        .fold(0u64, u64::saturating_add)
}

/// [`render_memory_problem`] with `available` bytes and estimator files of
/// `estimator_bytes` in all.
fn render_memory_problem_within(
    scene: &Scene,
    pixel_bytes: u64,
    estimator_bytes: u64,
    available: u64,
) -> Option<String> {
    let mut used = vec![false; scene.meshes.len()];
    for i in &scene.instances {
        if let Some(u) = used.get_mut(i.mesh) {
            *u = true;
        }
    }
    let triangles: u64 = scene
        .meshes
        .iter()
        .zip(&used)
        .filter(|(_, u)| **u)
        .map(|(m, _)| m.triangles.len() as u64)
        .sum();
    let instances = scene.instances.len() as u64;
    let pixels = u64::from(scene.camera.width) * u64::from(scene.camera.height);
    let parts = [
        triangles.saturating_mul(RENDER_BYTES_PER_TRIANGLE),
        instances.saturating_mul(RENDER_BYTES_PER_INSTANCE),
        pixels.saturating_mul(pixel_bytes),
        estimator_bytes.saturating_mul(RENDER_BYTES_PER_ESTIMATOR_FILE_BYTE),
    ];
    let need = parts.iter().fold(0u64, |a, &b| a.saturating_add(b));
    (need > available).then(|| {
        let (w, h) = (scene.camera.width, scene.camera.height);
        format!(
            "rendering its {triangles} triangles (of the meshes its instances use, each once), \
             {instances} instances and a {w}x{h} image takes about {} ({} for the triangles at \
             about {RENDER_BYTES_PER_TRIANGLE} bytes each: the meshes, their trees and the merged \
             copies; {} for the instances; {} for the image{}), more than the {} of memory \
             available: use fewer or coarser meshes (instances of one mesh share its \
             triangles), fewer instances or a smaller image{}",
            nppp_files::format_bytes(need),
            nppp_files::format_bytes(parts[0]),
            nppp_files::format_bytes(parts[1]),
            nppp_files::format_bytes(parts[2]),
            if estimator_bytes > 0 {
                format!(
                    "; {} for {} of estimator files",
                    nppp_files::format_bytes(parts[3]),
                    nppp_files::format_bytes(estimator_bytes)
                )
            } else {
                String::new()
            },
            nppp_files::format_bytes(available),
            if estimator_bytes > 0 {
                ", or render with --estimators off"
            } else {
                ""
            }
        )
    })
}

/// Everything the integrator reads, immutable and shared by all threads.
pub struct RenderScene {
    /// The layout estimator queries need: instances with estimators keep
    /// their own BLAS under the TLAS.
    pub accel: Accel,
    /// Built by [`RenderScene::for_estimators`] where it differs from
    /// `accel`: the same scene with estimator instances merged into the world
    /// BLAS, as plain path tracing has it. Rays that cannot use an estimator
    /// (before P bounces, shadow rays, and where one instance has an
    /// estimator the rays that start inside its sphere or miss it:
    /// `Estimators::cannot_enter`) trace this one; at P = 3 on the
    /// default scene a render with estimators took 1.21x plain PT's time
    /// with one layout for all rays, most of it paid by rays no estimator
    /// could serve.
    pub plain_accel: Option<Accel>,
    pub camera: PinholeCamera,
    pub lights: Lights,
    /// Per instance: its surface.
    pub surface: Vec<SurfaceKind>,
    /// Per instance: index of its first triangle in `lights.triangles` (emitters only).
    pub light_base: Vec<u32>,
    /// Per mesh: per-triangle vertex normals of smooth meshes.
    pub(crate) shading_normals: Vec<Option<crate::huge_pages::HugeArray<[Vec3; 3]>>>,
    /// Per mesh: unit object-space geometric normal of each triangle.
    pub geo_normals: Vec<Vec<Vec3>>,
    /// Per instance: absolute floor for ray offsets off its surface, relative
    /// to the instance's own world-space size (its intersections' rounding
    /// error scales with its vertices), so the same scene at 1e-4 and 1e4 is
    /// offset alike and a huge ground plane does not push rays leaving a
    /// small object through its neighbours (a 1e7 floor did, with the old
    /// scene-wide floor: light leaked through a tube's walls).
    pub offset_floor: Vec<f32>,
    /// Per instance: the medium inside it (translucent objects), in world
    /// units (the mesh-space coefficients divided by the instance's scale).
    pub media: Vec<Option<Medium>>,
    /// Estimators attached to instances; `None` runs no estimator code at
    /// all. Only a scene built by [`RenderScene::for_estimators`] can use
    /// them (`render::render` checks).
    pub estimators: Option<crate::estimator::Estimators>,
    /// Instances whose estimator [`RenderScene::with_estimators`] left
    /// unused because other geometry reaches into their object's convex
    /// hull (see [`crate::estimator_overlap`]): they are
    /// traced for real, and the renderer says so.
    pub obstructed: Vec<crate::estimator_overlap::Obstruction>,
}

impl RenderScene {
    /// The scene as `mode` renders it: its estimators loaded and bound to
    /// their instances (none for `Off` or when no instance names one), and
    /// the BVH layout that goes with them, chosen here so that no caller can
    /// pair estimators with a layout that merged their instances away.
    /// Estimator files are read before the BVHs are built: a bad file fails
    /// at once.
    // Once per render, as `Estimators::load`: a large error value is no cost.
    #[allow(clippy::result_large_err)]
    pub fn with_estimators(
        scene: &Scene,
        mode: crate::estimator::EstimatorMode,
        min_bounces: u32,
    ) -> Result<Self, crate::estimator::EstimatorLoadError> {
        let mut estimators = crate::estimator::Estimators::load(scene, mode, min_bounces)?;
        let mut rs = Self::build(scene, estimators.is_some());
        if let Some(ests) = &mut estimators {
            rs.obstructed = rs.release_obstructed(scene, ests);
            ests.set_other_geometry_in_spheres(
                crate::estimator_overlap::find_other_geometry_in_spheres(scene, &rs.accel, ests),
            );
        }
        // Every instance released: a plain render.
        rs.estimators = estimators.filter(|e| e.any_in_use());
        Ok(rs)
    }

    /// Leaves unused the estimators of instances whose object's convex hull
    /// other geometry reaches into (see
    /// [`crate::estimator_overlap`]): those instances are traced for real.
    /// Returns them, for the caller to say so. `self` must be the
    /// estimator layout of `scene`.
    pub fn release_obstructed(
        &self,
        scene: &Scene,
        ests: &mut crate::estimator::Estimators,
    ) -> Vec<crate::estimator_overlap::Obstruction> {
        let obstructed = crate::estimator_overlap::find_obstructed(scene, &self.accel, ests);
        crate::estimator_overlap::release(ests, &obstructed);
        obstructed
    }

    /// For plain path tracing: every instance whose mesh is used once,
    /// estimator or not, is merged into the world BLAS (1.2x the samples/s of
    /// keeping the default scene's knot instanced, measured).
    pub fn new(scene: &Scene) -> Self {
        Self::build(scene, false)
    }

    /// For rendering with estimators: instances that name one keep their own
    /// BLAS under the TLAS, where the estimator query can stand in for it.
    pub fn for_estimators(scene: &Scene) -> Self {
        Self::build(scene, true)
    }

    /// The layout renders with estimators need, where it differs from the
    /// one [`Self::new`] builds for plain path tracing (`None`: that one
    /// serves both). For a caller that renders the same scene both ways and
    /// times each on its own layout (`nppp bench`).
    pub fn estimator_layout(scene: &Scene) -> Option<Self> {
        Self::layouts_differ(scene).then(|| Self::for_estimators(scene))
    }

    /// Whether keeping estimator instances apart changes what is merged
    /// into the world BLAS.
    fn layouts_differ(scene: &Scene) -> bool {
        let (inst, keep) = Self::instance_plan(scene, true);
        Accel::merge_plan(scene.meshes.len(), &inst, &keep)
            != Accel::merge_plan(scene.meshes.len(), &inst, &[])
    }

    /// Per instance: its (mesh, transform), and whether it keeps its own
    /// BLAS under the TLAS.
    fn instance_plan(
        scene: &Scene,
        keep_estimator_instances: bool,
    ) -> (Vec<(usize, nppp_scene::Transform)>, Vec<bool>) {
        let inst = scene
            .instances
            .iter()
            .map(|i| (i.mesh, i.transform))
            .collect();
        let keep = scene
            .instances
            .iter()
            .map(|i| keep_estimator_instances && i.estimator.is_some())
            .collect();
        (inst, keep)
    }

    fn build(scene: &Scene, keep_estimator_instances: bool) -> Self {
        let (inst, keep) = Self::instance_plan(scene, keep_estimator_instances);
        // Where keeping estimator instances apart changes what is merged,
        // rays that cannot use an estimator get the merged layout too.
        let layouts_differ = keep_estimator_instances && Self::layouts_differ(scene);
        let (accel, plain_accel) = if layouts_differ {
            let (a, p) = rayon::join(
                || Accel::build(&scene.meshes, &inst, &keep),
                || Accel::build(&scene.meshes, &inst, &[]),
            );
            (a, Some(p))
        } else {
            (Accel::build(&scene.meshes, &inst, &keep), None)
        };
        let geo_normals: Vec<Vec<Vec3>> = scene
            .meshes
            .iter()
            .map(|m| {
                m.triangles
                    .iter()
                    .map(|t| {
                        let p = |k: usize| m.positions[t[k] as usize];
                        nppp_geom::unit_normal((p(1) - p(0)).cross(p(2) - p(0)))
                    })
                    .collect()
            })
            .collect();
        let mut surface = Vec::with_capacity(scene.instances.len());
        let mut light_base = Vec::with_capacity(scene.instances.len());
        let offset_floor: Vec<f32> = accel
            .instance_bounds
            .iter()
            .map(|(a, b)| a.abs().max(b.abs()).max_element().max(f32::MIN_POSITIVE) * 1e-7)
            .collect();
        let mut light_tris = Vec::new();
        for (ii, i) in scene.instances.iter().enumerate() {
            let s = SurfaceKind::of(&scene.materials[i.material]);
            light_base.push(light_tris.len() as u32);
            if let SurfaceKind::Emitter { radiance } = s {
                let x = &accel.instances[ii];
                let mesh = &scene.meshes[i.mesh];
                for t in &mesh.triangles {
                    let p = |k: usize| x.point_to_world(mesh.positions[t[k] as usize]);
                    let (v0, v1, v2) = (p(0), p(1), p(2));
                    let c = (v1 - v0).cross(v2 - v0);
                    // In f64: the squared length overflows f32 for edges
                    // past about 4e9.
                    let area = (0.5 * c.as_dvec3().length()) as f32;
                    light_tris.push(LightTriangle {
                        v0,
                        e1: v1 - v0,
                        e2: v2 - v0,
                        normal: nppp_geom::unit_normal(c),
                        area,
                        radiance,
                        offset_floor: offset_floor[ii],
                    });
                }
            }
            surface.push(s);
        }
        Self {
            camera: PinholeCamera::new(&scene.camera),
            lights: Lights::new(light_tris),
            surface,
            light_base,
            shading_normals: scene
                .meshes
                .iter()
                .map(|m| {
                    m.shading_normals
                        .as_deref()
                        .map(crate::huge_pages::HugeArray::from_slice)
                })
                .collect(),
            geo_normals,
            accel,
            plain_accel,
            offset_floor,
            media: scene
                .instances
                .iter()
                .map(|i| {
                    Medium::of(&scene.materials[i.material]).map(|m| m.scaled(i.transform.scale))
                })
                .collect(),
            estimators: None,
            obstructed: Vec::new(),
        }
    }

    /// The real object behind estimator `est` alone, as the oracle walks it
    /// and as first-vertex NEE finds its vertex.
    pub fn object_tracer(&self, est: &Estimator, max_internal_bounces: u32) -> ObjectTracer<'_> {
        ObjectTracer {
            blas: &self.accel.blas[est.mesh],
            surface: est.surface,
            medium: est.medium,
            sphere: est.sphere,
            geo_normals: &self.geo_normals[est.mesh],
            shading_normals: self.shading_normals[est.mesh].as_deref(),
            max_internal_bounces,
        }
    }

    /// The layout for rays that cannot use an estimator (see `plain_accel`).
    /// Its hits name the same instances and primitives as `accel`'s.
    #[inline]
    pub fn plain(&self) -> &Accel {
        self.plain_accel.as_ref().unwrap_or(&self.accel)
    }

    /// World-space geometric and shading normals at a hit (both unit, same side).
    #[inline]
    pub fn normals_at(&self, h: &SceneHit) -> (Vec3, Vec3) {
        let x = &self.accel.instances[h.instance as usize];
        let mesh = x.blas as usize;
        let ng = h.ng;
        let ns = match &self.shading_normals[mesh] {
            Some(n) => {
                let [n0, n1, n2] = n[h.prim as usize];
                let b0 = 1.0 - h.b1 - h.b2;
                crate::surface::shading_normal_on_side(
                    x.dir_to_world(n0 * b0 + n1 * h.b1 + n2 * h.b2),
                    ng,
                )
            }
            None => ng,
        };
        (ng, ns)
    }

    /// How far to move a ray origin at world point `p` off its surface.
    #[inline]
    pub fn offset_at(&self, p: Vec3, instance: u32) -> f32 {
        let x = &self.accel.instances[instance as usize];
        let mag = p.abs().max_element().max(x.translation.abs().max_element());
        (mag * OFFSET_REL).max(self.offset_floor[instance as usize])
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::EstimatorMode;

    /// The meshes the instances use count once each (a shared mesh once,
    /// an unused one not at all), and the message says what and how much.
    #[test]
    fn render_memory_counts_used_meshes_once() {
        let scene = nppp_scene::parse_scene(
            r#"{"camera": {"position": [0, 0, -5], "look_at": [0, 0, 0], "fov_y_deg": 40, "width": 8, "height": 8},
                "materials": {"white": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}},
                "meshes": {"ball": {"icosphere": {"center": [0, 0, 0], "radius": 1, "subdivisions": 2}},
                           "unused": {"icosphere": {"center": [0, 0, 0], "radius": 1, "subdivisions": 4}}},
                "instances": [{"mesh": "ball", "material": "white"},
                              {"mesh": "ball", "material": "white", "transform": {"translate": [3, 0, 0]}}]}"#,
            std::path::Path::new("memory.json"),
        )
        .unwrap();
        // 320 triangles of "ball", once: 128,000 bytes; two instances,
        // 2,400; an 8x8 image, 3,072.
        let px = RENDER_BYTES_PER_PIXEL;
        assert_eq!(render_memory_problem_within(&scene, px, 0, 133_472), None);
        let msg = render_memory_problem_within(&scene, px, 0, 133_471).unwrap();
        assert!(msg.contains("rendering its 320 triangles"), "{msg}");
        assert!(msg.contains("2 instances and a 8x8 image"), "{msg}");
        assert!(
            msg.contains("130.34 KiB") && msg.contains("of memory available"),
            "{msg}"
        );
        // --auto-confirm's two films of exact sums: 280 bytes a pixel more.
        let confirm = px + AUTO_CONFIRM_BYTES_PER_PIXEL;
        assert_eq!(
            render_memory_problem_within(&scene, confirm, 0, 151_392),
            None
        );
        assert!(render_memory_problem_within(&scene, confirm, 0, 151_391).is_some());
        assert_eq!(
            render_memory_problem(&scene, px, EstimatorMode::Neural),
            None
        );
        // Estimator files: four bytes a byte of file (a 16.8 MB knot's
        // file took 61 MB more than the oracle, which loads none).
        assert_eq!(
            render_memory_problem_within(&scene, px, 1000, 137_472),
            None
        );
        let msg = render_memory_problem_within(&scene, px, 1000, 137_471).unwrap();
        assert!(
            msg.contains("3.91 KiB for 1000 B of estimator files")
                && msg.contains("or render with --estimators off"),
            "{msg}"
        );
    }

    /// The files a render loads, each once under any spelling; none for
    /// plain path tracing or the oracle, none on a lamp.
    #[test]
    fn estimator_files_count_once_each_and_only_where_loaded() {
        let dir = std::env::temp_dir().join(format!("nppp-est-bytes-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("a.nppp"), vec![0u8; 1000]).unwrap();
        std::fs::write(dir.join("b.nppp"), vec![0u8; 300]).unwrap();
        let d = dir.display().to_string().replace('\\', "/");
        let scene = nppp_scene::parse_scene(
            &format!(
                r#"{{"camera": {{"position": [0, 0, -5], "look_at": [0, 0, 0], "fov_y_deg": 40, "width": 8, "height": 8}},
                "materials": {{"white": {{"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}},
                              "lamp": {{"type": "emitter", "radiance": [1, 1, 1]}}}},
                "meshes": {{"ball": {{"icosphere": {{"center": [0, 0, 0], "radius": 1, "subdivisions": 1}}}}}},
                "instances": [{{"mesh": "ball", "material": "white", "estimator": "{d}/a.nppp"}},
                              {{"mesh": "ball", "material": "white", "estimator": "{d}/./a.nppp"}},
                              {{"mesh": "ball", "material": "white", "estimator": "{d}/missing.nppp"}},
                              {{"mesh": "ball", "material": "lamp", "estimator": "{d}/b.nppp"}}]}}"#
            ),
            std::path::Path::new("files.json"),
        )
        .unwrap();
        assert_eq!(estimator_file_bytes(&scene, EstimatorMode::Neural), 1000);
        assert_eq!(estimator_file_bytes(&scene, EstimatorMode::FreeExits), 1000);
        assert_eq!(estimator_file_bytes(&scene, EstimatorMode::Off), 0);
        assert_eq!(estimator_file_bytes(&scene, EstimatorMode::Oracle), 0);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
