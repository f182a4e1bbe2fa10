//! Scene loading: JSON text to a validated, resolved [`Scene`].
//!
//! Validation is by hand over our own JSON tree rather than through serde
//! derives, because docs/scene-format.md requires every error to name its key
//! path (`instances[3].material`), and derive errors only give a line and
//! column. Everything the contract leaves undefined is rejected, never
//! guessed: the renderer must not silently render something else.

use crate::error::SceneError;
use crate::json::{self, Json, Num, join_index, join_key};
use crate::procedural::count_text;
use crate::{Camera, Instance, Material, Mesh, RenderSettings, Scene, Transform};
use glam::{DQuat, DVec3, Vec3};
use std::collections::HashMap;
use std::path::Path;

mod mesh;

/// The largest image side the renderer accepts (docs/scene-format.md: "an image
/// over 16384 x 16384 pixels" cannot be rendered).
pub const MAX_IMAGE_SIDE: u32 = 16384;
/// Largest world-space coordinate of any vertex (after its instance's
/// transform) or of the camera. The renderer works in 32-bit floats: BVH
/// surface areas, squared distances and ray offsets must stay finite and
/// meaningful, and past this they do not (a box at 3e38 scaled by 2 used to
/// reach the BVH builder as infinity), and the ray-triangle test's
/// determinants (products of three lengths) must not overflow: the Cornell
/// box scaled to 8e12 rendered 16% dark and at 3e13 black.
pub const MAX_WORLD_COORD: f64 = 1e12;
/// Smallest world-space size (the longest side of its box) of an instance:
/// below about 1e-13 the ray-triangle test's products of three lengths
/// leave the 32-bit float range (the Cornell box scaled to 6e-14 rendered
/// 13% dark, at 6e-16 black).
pub const MIN_WORLD_SIZE: f64 = 1e-9;
/// An instance must span at least this many 32-bit float steps at its
/// distance from the origin: below it its vertices round together (a knot
/// scaled to 2e-4 at x = 278 spans 7; its shape is gone, and building its
/// tree took minutes).
pub const MIN_FLOAT_STEPS: f64 = 8.0;

/// Memory the loaded meshes take per triangle (vertices, triangles, the
/// generators' working copies). Measured peak resident memory of `nppp
/// mesh` on four icospheres of 1.3 M triangles: 29 bytes a triangle;
/// rounded up. Rendering takes more (nppp-render's
/// `RENDER_BYTES_PER_TRIANGLE`, checked by the commands that render).
pub const MESH_BYTES_PER_TRIANGLE: u64 = 48;
/// Memory the loader holds per byte of a scene file while it parses it:
/// measured 9.4 (a 45 MB file of 400,000 instances peaked at 425 MB),
/// rounded up.
pub const JSON_BYTES_PER_BYTE: u64 = 10;

/// What makes an object spanning `lo..hi` (world space) too small for
/// 32-bit float geometry, if anything: its size ([`MIN_WORLD_SIZE`]), the
/// float steps it spans at its place ([`MIN_FLOAT_STEPS`]), or a medium's
/// mean free path `free_path` (world units) under one float step.
pub fn precision_problem(lo: DVec3, hi: DVec3, free_path: Option<f64>) -> Option<String> {
    let size = (hi - lo).max_element();
    let reach = lo.abs().max(hi.abs()).max_element();
    if !(size.is_finite() && reach.is_finite()) {
        return None;
    }
    // One float step of the farthest coordinate, in f32.
    let step = f64::from(nppp_geom::float_step((reach as f32).max(f32::MIN_POSITIVE)));
    if size > 0.0 && size < MIN_WORLD_SIZE {
        return Some(format!(
            "is {size:.3e} across, below {MIN_WORLD_SIZE:e} (32-bit float intersection tests \
             lose it); scale the scene up"
        ));
    }
    if size > 0.0 && size < MIN_FLOAT_STEPS * step {
        return Some(format!(
            "is {size:.3e} across at {reach:.3e} from the origin, only {:.1} steps of a 32-bit \
             float there (at least {MIN_FLOAT_STEPS} are needed): its vertices round together; \
             scale it up or move the scene nearer the origin",
            size / step
        ));
    }
    match free_path {
        Some(f) if f < step => Some(format!(
            "has a mean free path of {f:.3e}, below one step of a 32-bit float at {reach:.3e} \
             from the origin ({step:.3e}): its walks cannot move; lower its sigma_s and sigma_a \
             or move the object nearer the origin"
        )),
        _ => None,
    }
}

/// What makes `mesh` unfit for 32-bit float geometry in its own units,
/// where the renderer intersects it and `nppp gen` walks it: beyond
/// [`MAX_WORLD_COORD`], or a [`precision_problem`] (with a medium's mean
/// free path `free_path` in mesh units, where one applies).
pub fn mesh_units_problem(mesh: &Mesh, free_path: Option<f64>) -> Option<String> {
    let (lo, hi) = mesh.bounds()?;
    let far = lo.abs().max(hi.abs()).max_element();
    if far > MAX_WORLD_COORD {
        return Some(format!(
            "reaches {far:.3e} from the origin in its own units, beyond {MAX_WORLD_COORD:e} \
             (32-bit float geometry); scale the mesh down and its instances up"
        ));
    }
    precision_problem(lo, hi, free_path).map(|w| format!("in its own units {w}"))
}

/// Reads and validates a scene file. Relative OBJ and estimator paths are
/// resolved against the file's folder.
pub fn load_scene(path: &Path) -> Result<Scene, SceneError> {
    let read_error = |error| SceneError::Read {
        file: path.to_path_buf(),
        error,
    };
    // Parsing holds the JSON as a tree, about ten times the text (a 45 MB
    // file of 400,000 instances peaked at 425 MB).
    if let (Ok(meta), Some(available)) = (std::fs::metadata(path), nppp_files::available_memory())
        && meta.len().saturating_mul(JSON_BYTES_PER_BYTE) > available
    {
        return Err(read_error(std::io::Error::new(
            std::io::ErrorKind::OutOfMemory,
            format!(
                "it is {}; reading it takes about {} (about {JSON_BYTES_PER_BYTE} bytes a byte of \
                 JSON), more than the {} of memory available",
                nppp_files::format_bytes(meta.len()),
                nppp_files::format_bytes(meta.len().saturating_mul(JSON_BYTES_PER_BYTE)),
                nppp_files::format_bytes(available)
            ),
        )));
    }
    let text = nppp_files::read_regular_to_string(path).map_err(read_error)?;
    // A byte-order mark (Windows editors write one) is not JSON.
    parse_scene(text.strip_prefix('\u{feff}').unwrap_or(&text), path)
}

/// Validates scene JSON that was read from `path` (or pretends to be: the
/// path is only used to resolve relative OBJ/estimator paths and to name the
/// file in messages, so tests can parse strings).
pub fn parse_scene(json: &str, path: &Path) -> Result<Scene, SceneError> {
    let root = parse_json(json, path)?;
    let cx = Cx {
        file: path,
        dir: path.parent().unwrap_or(Path::new("")),
    };
    cx.scene(&root)
}

/// One material in the scene format's JSON on its own (a command-line flag,
/// say), validated exactly as inside a scene file. `source` stands where a
/// scene's errors name the file (e.g. `--material`); key paths start inside
/// the material (`albedo`).
pub fn parse_material(json: &str, source: &str) -> Result<Material, SceneError> {
    let file = Path::new(source);
    let root = parse_json(json, file)?;
    Cx {
        file,
        dir: Path::new(""),
    }
    .material(&root, "")
}

/// One mesh object in the scene format's JSON on its own (`{"obj": ...}`,
/// `{"icosphere": {...}}`, ...), validated exactly as inside a scene file;
/// a relative OBJ path is read from the current folder. `source` as in
/// [`parse_material`].
pub fn parse_mesh(json: &str, source: &str) -> Result<Mesh, SceneError> {
    parse_mesh_charged(json, source, MESH_BYTES_PER_TRIANGLE)
}

/// [`parse_mesh`] for a caller that will hold `charge` bytes a triangle in
/// all, the mesh included (`nppp gen`: the mesh and its BVH): refused
/// before the mesh is built where the triangle count is known from the
/// JSON (shapes and procedural objects) and that would not fit.
pub fn parse_mesh_charged(json: &str, source: &str, charge: u64) -> Result<Mesh, SceneError> {
    let file = Path::new(source);
    let root = parse_json(json, file)?;
    // The scene loader's memory check, as for a scene of this one mesh.
    let mut meshes = Cx {
        file,
        dir: Path::new(""),
    }
    .meshes_within_memory(
        &[(String::new(), root)],
        "",
        MESH_BYTES_PER_TRIANGLE.max(charge),
    )?;
    Ok(meshes.remove(0))
}

fn parse_json(json: &str, file: &Path) -> Result<Json, SceneError> {
    json::parse(json).map_err(|f| SceneError::Json {
        file: file.to_path_buf(),
        line: f.line,
        column: f.column,
        key: f.key,
        message: f.message,
    })
}

type Res<T> = Result<T, SceneError>;

/// A vector as a message shows it: a component that is huge or tiny in
/// e-notation (glam's `Display` printed 2e19 as twenty digits), any other
/// as written.
fn vec_text(v: Vec3) -> String {
    let c = |x: f32| {
        if x != 0.0 && x.is_finite() && !(1e-3..1e6).contains(&x.abs()) {
            format!("{x:e}")
        } else {
            format!("{x}")
        }
    };
    format!("[{}, {}, {}]", c(v.x), c(v.y), c(v.z))
}

/// The file being loaded, for messages and relative paths.
struct Cx<'a> {
    file: &'a Path,
    dir: &'a Path,
}

/// A JSON object whose keys have been checked against the allowed set.
struct Fields<'j> {
    entries: &'j [(String, Json)],
    path: String,
}

impl<'j> Fields<'j> {
    fn get(&self, key: &str) -> Option<(&'j Json, String)> {
        self.entries
            .iter()
            .find(|(k, _)| k == key)
            .map(|(_, v)| (v, join_key(&self.path, key)))
    }

    fn req(&self, cx: &Cx, key: &str) -> Res<(&'j Json, String)> {
        self.get(key).ok_or_else(|| {
            cx.invalid(
                &join_key(&self.path, key),
                "required key is missing".to_string(),
            )
        })
    }
}

/// A short list of names for "unknown name" messages, bounded so a scene
/// with 10,000 meshes does not produce a 10,000-name message.
fn name_list(names: &[String]) -> String {
    const SHOWN: usize = 12;
    let mut out: Vec<String> = names
        .iter()
        .take(SHOWN)
        .map(|n| format!("\"{n}\""))
        .collect();
    if names.len() > SHOWN {
        out.push(format!("and {} more", names.len() - SHOWN));
    }
    if out.is_empty() {
        "none are defined".to_string()
    } else {
        format!("defined: {}", out.join(", "))
    }
}

const TOP_KEYS: &[&str] = &["camera", "materials", "meshes", "instances", "render"];
const CAMERA_KEYS: &[&str] = &["position", "look_at", "up", "fov_y_deg", "width", "height"];
const INSTANCE_KEYS: &[&str] = &["mesh", "material", "transform", "estimator"];
const TRANSFORM_KEYS: &[&str] = &["scale", "rotate", "translate"];
const ROTATE_KEYS: &[&str] = &["axis", "deg"];
const RENDER_KEYS: &[&str] = &["spp", "max_bounces", "estimator_min_bounces", "seed"];

impl Cx<'_> {
    fn invalid(&self, key: &str, message: String) -> SceneError {
        SceneError::Invalid {
            file: self.file.to_path_buf(),
            // Only the document itself has the empty path.
            key: if key.is_empty() {
                "(top level)".to_string()
            } else {
                key.to_string()
            },
            message,
        }
    }

    fn wrong_type(&self, key: &str, expected: &str, found: &Json) -> SceneError {
        self.invalid(key, format!("expected {expected}, found {}", found.kind()))
    }

    fn object<'j>(&self, v: &'j Json, path: &str, allowed: &[&str]) -> Res<Fields<'j>> {
        let Json::Obj(entries) = v else {
            return Err(self.wrong_type(path, "an object", v));
        };
        if let Some((k, _)) = entries.iter().find(|(k, _)| !allowed.contains(&k.as_str())) {
            return Err(self.invalid(
                &join_key(path, k),
                format!("unknown key \"{k}\" (allowed here: {})", allowed.join(", ")),
            ));
        }
        Ok(Fields {
            entries,
            path: path.to_string(),
        })
    }

    /// An object whose required `type` key decides which other keys it may
    /// have: its entries and its type.
    fn typed_object<'j>(&self, v: &'j Json, path: &str) -> Res<(&'j [(String, Json)], &'j str)> {
        let Json::Obj(entries) = v else {
            return Err(self.wrong_type(path, "an object", v));
        };
        let type_path = join_key(path, "type");
        let ty = match entries.iter().find(|(k, _)| k == "type") {
            Some((_, t)) => self.string(t, &type_path)?,
            None => return Err(self.invalid(&type_path, "required key is missing".into())),
        };
        Ok((entries, ty))
    }

    fn string<'j>(&self, v: &'j Json, path: &str) -> Res<&'j str> {
        match v {
            Json::Str(s) => Ok(s),
            _ => Err(self.wrong_type(path, "a string", v)),
        }
    }

    fn boolean(&self, v: &Json, path: &str) -> Res<bool> {
        match v {
            Json::Bool(b) => Ok(*b),
            _ => Err(self.wrong_type(path, "true or false", v)),
        }
    }

    /// A number that is finite as an f32 (everything downstream is f32, and
    /// e.g. `1e39` would silently become infinity there). Returned as f64
    /// for the few places (rotations) that compute in double precision.
    fn number(&self, v: &Json, path: &str) -> Res<f64> {
        let Json::Num(n) = v else {
            return Err(self.wrong_type(path, "a number", v));
        };
        let x = n.as_f64();
        if !(x as f32).is_finite() {
            return Err(self.invalid(
                path,
                format!("{n} is not finite as a 32-bit float (magnitude above 3.4e38)"),
            ));
        }
        Ok(x)
    }

    fn float(&self, v: &Json, path: &str) -> Res<f32> {
        self.number(v, path).map(|x| x as f32)
    }

    fn vec3_f64(&self, v: &Json, path: &str) -> Res<DVec3> {
        let Json::Arr(items) = v else {
            return Err(self.wrong_type(path, "an array of 3 numbers", v));
        };
        if items.len() != 3 {
            return Err(self.invalid(
                path,
                format!(
                    "expected an array of 3 numbers, found {} elements",
                    items.len()
                ),
            ));
        }
        let mut out = [0f64; 3];
        for (i, (slot, item)) in out.iter_mut().zip(items).enumerate() {
            *slot = self.number(item, &join_index(path, i))?;
        }
        Ok(DVec3::from_array(out))
    }

    fn vec3(&self, v: &Json, path: &str) -> Res<Vec3> {
        self.vec3_f64(v, path).map(|d| d.as_vec3())
    }

    /// A non-negative integer. `64.0` counts (some JSON writers emit every
    /// number as a float), `64.5` and `-1` do not; floats beyond 2^53 are
    /// rejected because their decimal digits were already rounded away.
    fn uint(&self, v: &Json, path: &str) -> Res<u64> {
        let Json::Num(n) = v else {
            return Err(self.wrong_type(path, "a non-negative integer", v));
        };
        match *n {
            Num::U(u) => Ok(u),
            Num::I(i) => {
                Err(self.invalid(path, format!("must be a non-negative integer, found {i}")))
            }
            Num::F(f) => {
                if f < 0.0 {
                    Err(self.invalid(path, format!("must be a non-negative integer, found {f}")))
                } else if f.fract() != 0.0 {
                    Err(self.invalid(path, format!("must be an integer, found {f}")))
                } else if f >= 18_446_744_073_709_551_616.0 {
                    Err(self.invalid(
                        path,
                        format!("{f:e} is above 2^64 - 1, the largest integer accepted here"),
                    ))
                } else if f > 9_007_199_254_740_992.0 {
                    Err(self.invalid(
                        path,
                        format!(
                            "{f} is not exactly representable as written; write the integer without a decimal point or exponent"
                        ),
                    ))
                } else {
                    Ok(f as u64)
                }
            }
        }
    }

    fn uint_in(&self, v: &Json, path: &str, min: u64, max: u64, why: &str) -> Res<u64> {
        let n = self.uint(v, path)?;
        if n < min {
            Err(self.invalid(path, format!("must be at least {min}, found {n}{why}")))
        } else if n > max {
            Err(self.invalid(path, format!("must be at most {max}, found {n}{why}")))
        } else {
            Ok(n)
        }
    }

    fn u32_in(&self, v: &Json, path: &str, min: u32, max: u32, why: &str) -> Res<u32> {
        // The bounds keep the value inside u32.
        self.uint_in(v, path, min.into(), max.into(), why)
            .map(|n| n as u32)
    }

    fn scene(&self, root: &Json) -> Res<Scene> {
        let top = self.object(root, "", TOP_KEYS)?;
        let camera = {
            let (v, p) = top.req(self, "camera")?;
            self.camera(v, &p)?
        };
        let (materials, material_names) = {
            let (v, p) = top.req(self, "materials")?;
            self.materials(v, &p)?
        };
        let render = match top.get("render") {
            Some((v, p)) => self.render(v, &p)?,
            None => RenderSettings::default(),
        };
        // Instances are checked before meshes are built, so a typo in an
        // instance is reported without first reading a large OBJ.
        let (mesh_values, mesh_path) = {
            let (v, p) = top.req(self, "meshes")?;
            let Json::Obj(entries) = v else {
                return Err(self.wrong_type(&p, "an object of named meshes", v));
            };
            (entries, p)
        };
        let mesh_names: Vec<String> = mesh_values.iter().map(|(k, _)| k.clone()).collect();
        let instances = {
            let (v, p) = top.req(self, "instances")?;
            self.instances(v, &p, &mesh_names, &material_names)?
        };
        let meshes = self.meshes_within_memory(mesh_values, &mesh_path, MESH_BYTES_PER_TRIANGLE)?;
        self.check_world_extent(
            &camera,
            &meshes,
            &mesh_names,
            &materials,
            &material_names,
            &instances,
        )?;
        self.check_translucent_closed(
            &meshes,
            &mesh_names,
            &materials,
            &material_names,
            &instances,
        )?;
        // Validated above: every "obj" value is a non-empty string.
        let obj_files = mesh_values
            .iter()
            .filter_map(|(_, v)| match v {
                Json::Obj(fields) => fields.iter().find_map(|(k, v)| match (k.as_str(), v) {
                    ("obj", Json::Str(rel)) => Some(self.dir.join(rel)),
                    _ => None,
                }),
                _ => None,
            })
            .collect();
        Ok(Scene {
            path: self.file.to_path_buf(),
            obj_files,
            camera,
            materials,
            material_names,
            meshes,
            mesh_names,
            instances,
            render,
        })
    }

    /// Builds the meshes, refusing a scene whose meshes would not fit in
    /// the memory available (`per_triangle` bytes a triangle: the scene
    /// loader's [`MESH_BYTES_PER_TRIANGLE`], or a caller's total with what
    /// it builds from a mesh) with a message instead of an allocation
    /// failure: first from the triangle counts known without building
    /// (shapes and procedural objects), before any mesh is made, then as
    /// each OBJ is read.
    fn meshes_within_memory(
        &self,
        entries: &[(String, Json)],
        path: &str,
        per_triangle: u64,
    ) -> Res<Vec<Mesh>> {
        let available = nppp_files::available_memory();
        // A mesh given alone (`parse_mesh`) is named by its source.
        let lone = path.is_empty();
        let keys: Vec<String> = entries
            .iter()
            .map(|(name, _)| match (path, name.as_str()) {
                ("", "") => String::new(),
                _ => join_key(path, name),
            })
            .collect();
        let predicted: Vec<u64> = entries
            .iter()
            .zip(&keys)
            .map(|((_, v), key)| self.predicted_triangles(v, key).unwrap_or(0))
            .collect();
        let too_much =
            |triangles: u64| available.filter(|&a| triangles.saturating_mul(per_triangle) > a);
        let message = |triangles: u64, available: u64, largest: &str| {
            let need = nppp_files::format_bytes(triangles.saturating_mul(per_triangle));
            let available = nppp_files::format_bytes(available);
            if lone {
                format!(
                    "the mesh has {} triangles; it takes about {need} with what is built from \
                     it, more than the {available} of memory available: use a coarser mesh",
                    count_text(triangles)
                )
            } else {
                format!(
                    "the scene's meshes have {} triangles{largest}; loading them takes about \
                     {need} (about {per_triangle} bytes a triangle), more than the {available} of \
                     memory available: use fewer or coarser meshes (instances of one mesh share \
                     its triangles)",
                    count_text(triangles)
                )
            }
        };
        let mut remaining: u64 = predicted.iter().fold(0, |a, &b| a.saturating_add(b));
        if let Some(a) = too_much(remaining) {
            let (k, &most) = predicted
                .iter()
                .enumerate()
                .max_by_key(|(_, t)| **t)
                .unwrap_or((0, &0));
            let largest = format!(", the largest {} with {}", keys[k], count_text(most));
            return Err(self.invalid(path, message(remaining, a, &largest)));
        }
        let mut meshes = Vec::with_capacity(entries.len());
        let mut built: u64 = 0;
        for (((_, v), key), &guess) in entries.iter().zip(&keys).zip(&predicted) {
            let mesh = self.mesh(v, key)?;
            built = built.saturating_add(mesh.triangles.len() as u64);
            remaining -= guess;
            if let Some(a) = too_much(built.saturating_add(remaining)) {
                let this = format!(
                    ", {} of them in this one",
                    count_text(mesh.triangles.len() as u64)
                );
                return Err(self.invalid(key, message(built.saturating_add(remaining), a, &this)));
            }
            meshes.push(mesh);
        }
        Ok(meshes)
    }

    /// A translucent material's medium is "inside" its mesh: the mesh must
    /// bound a volume. The error names the mesh, the material and one open edge.
    fn check_translucent_closed(
        &self,
        meshes: &[Mesh],
        mesh_names: &[String],
        materials: &[Material],
        material_names: &[String],
        instances: &[Instance],
    ) -> Res<()> {
        let mut checked = vec![false; meshes.len()];
        for inst in instances {
            if !matches!(materials[inst.material], Material::Translucent { .. })
                || checked[inst.mesh]
            {
                continue;
            }
            checked[inst.mesh] = true;
            if let Some(edge) = crate::open_edge(&meshes[inst.mesh]) {
                return Err(self.invalid(
                    &join_key("meshes", &mesh_names[inst.mesh]),
                    format!(
                        "is used with the translucent material \"{}\" but is not a closed mesh: {edge}; \
                         a medium needs a watertight, consistently oriented boundary",
                        material_names[inst.material]
                    ),
                ));
            }
        }
        Ok(())
    }

    /// Every instance's vertices, transformed to world space (in f64, so an
    /// overflow is seen rather than produced), and the camera lie within
    /// `MAX_WORLD_COORD`; every instance is at least `MIN_WORLD_SIZE` across
    /// and `MIN_FLOAT_STEPS` float steps at its place, and a medium's mean
    /// free path is at least one. The check uses each mesh's bounding box
    /// corners: a rotation maps the box to one containing the vertices'
    /// images.
    fn check_world_extent(
        &self,
        camera: &Camera,
        meshes: &[Mesh],
        mesh_names: &[String],
        materials: &[Material],
        material_names: &[String],
        instances: &[Instance],
    ) -> Res<()> {
        let too_far = |v: DVec3| !v.is_finite() || v.abs().max_element() > MAX_WORLD_COORD;
        if too_far(camera.position.as_dvec3()) {
            return Err(self.invalid(
                "camera.position",
                format!(
                    "[{:.3e}, {:.3e}, {:.3e}] is farther than {MAX_WORLD_COORD:e} from the origin (32-bit float geometry)",
                    camera.position.x, camera.position.y, camera.position.z
                ),
            ));
        }
        let bounds: Vec<Option<(DVec3, DVec3)>> = meshes.iter().map(Mesh::bounds).collect();
        for (i, inst) in instances.iter().enumerate() {
            let Some((lo, hi)) = bounds[inst.mesh] else {
                continue;
            };
            let t = &inst.transform;
            let rot = t.rotation.as_dquat();
            let far = (0..8).map(|k| {
                let c = DVec3::new(
                    if k & 1 == 0 { lo.x } else { hi.x },
                    if k & 2 == 0 { lo.y } else { hi.y },
                    if k & 4 == 0 { lo.z } else { hi.z },
                );
                rot * (c * t.scale as f64) + t.translation.as_dvec3()
            });
            let (wlo, whi) = far.clone().fold(
                (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
                |(a, b), c| (a.min(c), b.max(c)),
            );
            if let Some(c) = far.clone().find(|&c| too_far(c)) {
                return Err(self.invalid(
                    &format!("instances[{i}].transform"),
                    format!(
                        "places mesh \"{}\" out to [{:.3e}, {:.3e}, {:.3e}] in world space, beyond {MAX_WORLD_COORD:e} (32-bit float geometry); scale the scene down",
                        mesh_names[inst.mesh],
                        c.x,
                        c.y,
                        c.z
                    ),
                ));
            }
            let sigma_t = materials[inst.material].densest_sigma_t();
            if let Some(why) = precision_problem(wlo, whi, sigma_t.map(|s| t.scale as f64 / s)) {
                return Err(self.invalid(
                    &format!("instances[{i}].transform"),
                    format!(
                        "mesh \"{}\"{} {why}",
                        mesh_names[inst.mesh],
                        match sigma_t {
                            Some(_) =>
                                format!(" with material \"{}\"", material_names[inst.material]),
                            None => String::new(),
                        }
                    ),
                ));
            }
        }
        // The meshes in their own units too: the renderer intersects each
        // in its object space (and `gen` walks it there).
        for (m, mesh) in meshes.iter().enumerate() {
            if !instances.iter().any(|inst| inst.mesh == m) {
                continue;
            }
            if let Some(why) = mesh_units_problem(mesh, None) {
                return Err(self.invalid(&join_key("meshes", &mesh_names[m]), why));
            }
        }
        Ok(())
    }

    fn camera(&self, v: &Json, path: &str) -> Res<Camera> {
        let f = self.object(v, path, CAMERA_KEYS)?;
        let (pv, pp) = f.req(self, "position")?;
        let position = self.vec3(pv, &pp)?;
        let (lv, lp) = f.req(self, "look_at")?;
        let look_at = self.vec3(lv, &lp)?;
        let (up, up_path) = match f.get("up") {
            Some((uv, upth)) => (self.vec3(uv, &upth)?, upth),
            None => (Vec3::Y, join_key(path, "up")),
        };
        let (fv, fp) = f.req(self, "fov_y_deg")?;
        let fov_y_deg = self.float(fv, &fp)?;
        if !(fov_y_deg > 0.0 && fov_y_deg < 180.0) {
            return Err(self.invalid(
                &fp,
                format!("the vertical field of view must be strictly between 0 and 180 degrees, found {fov_y_deg}"),
            ));
        }
        let side = |key: &str| -> Res<u32> {
            let (v, p) = f.req(self, key)?;
            self.u32_in(
                v,
                &p,
                1,
                MAX_IMAGE_SIDE,
                " pixels (images are 1 to 16384 pixels on a side)",
            )
        };
        let width = side("width")?;
        let height = side("height")?;

        // The renderer's own formulas (docs/scene-format.md, Camera), in f32 as it
        // computes them, must give finite unit vectors.
        let delta = look_at - position;
        let Some(forward) = delta.try_normalize() else {
            let message = if delta == Vec3::ZERO {
                format!(
                    "equals camera.position {}, so there is no viewing direction",
                    vec_text(position)
                )
            } else {
                format!(
                    "look_at - position = {} cannot be normalized in 32-bit floats",
                    vec_text(delta)
                )
            };
            return Err(self.invalid(&lp, message));
        };
        // Only the direction of `up` matters: scaled by a power of two to a
        // largest component in [1, 2), the renderer's products (a cross
        // product, its squared length) are in range at any length f32
        // holds. Exact: the image is the same bit for bit as with `up` as
        // written wherever that worked (1e-19 or 2e19 long did not).
        let given_up = up;
        let up = match up.abs().max_element() {
            m if m > 0.0 && m.is_finite() => {
                let scale = (-f64::from(m).log2().floor()).exp2();
                (up.as_dvec3() * scale).as_vec3()
            }
            _ => up,
        };
        let Some(up_unit) = up.try_normalize() else {
            return Err(self.invalid(&up_path, format!("{} has no direction", vec_text(given_up))));
        };
        let parallel =
            forward.cross(up_unit).length() < 1e-6 || forward.cross(up).try_normalize().is_none();
        if parallel {
            return Err(self.invalid(
                &up_path,
                format!(
                    "{} is parallel to the viewing direction {}, so the image has no defined right or up",
                    vec_text(given_up),
                    vec_text(forward)
                ),
            ));
        }
        Ok(Camera {
            position,
            look_at,
            up,
            fov_y_deg,
            width,
            height,
        })
    }

    fn materials(&self, v: &Json, path: &str) -> Res<(Vec<Material>, Vec<String>)> {
        let Json::Obj(entries) = v else {
            return Err(self.wrong_type(path, "an object of named materials", v));
        };
        let mut materials = Vec::with_capacity(entries.len());
        let mut names = Vec::with_capacity(entries.len());
        for (name, mv) in entries {
            let mp = join_key(path, name);
            materials.push(self.material(mv, &mp)?);
            names.push(name.clone());
        }
        Ok((materials, names))
    }

    fn material(&self, v: &Json, path: &str) -> Res<Material> {
        // The type decides which keys are allowed, so read it first.
        let (_, ty) = self.typed_object(v, path)?;
        let type_path = join_key(path, "type");
        let allowed: &[&str] = match ty {
            "diffuse" => &["type", "albedo"],
            "conductor" => &["type", "reflectance", "roughness"],
            "dielectric" => &["type", "ior"],
            "emitter" => &["type", "radiance"],
            "translucent" => &["type", "ior", "sigma_s", "sigma_a", "g"],
            other => {
                return Err(self.invalid(
                    &type_path,
                    format!("unknown material type \"{other}\" (known: diffuse, conductor, dielectric, translucent, emitter)"),
                ));
            }
        };
        let f = self.object(v, path, allowed)?;
        let unit_rgb = |key: &str| -> Res<Vec3> {
            let (cv, cp) = f.req(self, key)?;
            let c = self.vec3(cv, &cp)?;
            for (i, x) in c.to_array().into_iter().enumerate() {
                if !(0.0..=1.0).contains(&x) {
                    return Err(self.invalid(
                        &join_index(&cp, i),
                        format!("{x} is outside [0, 1]: a surface cannot reflect more light than it receives"),
                    ));
                }
            }
            Ok(c)
        };
        let ior = || -> Res<f32> {
            let (iv, ip) = f.req(self, "ior")?;
            let ior = self.float(iv, &ip)?;
            if ior <= 0.0 {
                return Err(self.invalid(
                    &ip,
                    format!("index of refraction must be positive, found {ior}"),
                ));
            }
            Ok(ior)
        };
        Ok(match ty {
            "diffuse" => Material::Diffuse {
                albedo: unit_rgb("albedo")?,
            },
            "conductor" => {
                let reflectance = unit_rgb("reflectance")?;
                let (rv, rp) = f.req(self, "roughness")?;
                let roughness = self.float(rv, &rp)?;
                if !(0.0..=1.0).contains(&roughness) {
                    return Err(self.invalid(
                        &rp,
                        format!("{roughness} is outside [0, 1] (GGX alpha; 0 is a perfect mirror)"),
                    ));
                }
                Material::Conductor {
                    reflectance,
                    roughness,
                }
            }
            "dielectric" => Material::Dielectric { ior: ior()? },
            "translucent" => {
                let coefficient = |key: &str| -> Res<Vec3> {
                    let (cv, cp) = f.req(self, key)?;
                    let c = self.vec3(cv, &cp)?;
                    for (i, x) in c.to_array().into_iter().enumerate() {
                        if !(x >= 0.0 && x.is_finite()) {
                            return Err(self.invalid(
                                &join_index(&cp, i),
                                format!("{x}: a medium coefficient (per unit length) must be finite and >= 0"),
                            ));
                        }
                    }
                    Ok(c)
                };
                let sigma_s = coefficient("sigma_s")?;
                let sigma_a = coefficient("sigma_a")?;
                let g = match f.get("g") {
                    Some((gv, gp)) => {
                        let written = self.number(gv, &gp)?;
                        let g = written as f32;
                        if g.is_nan() || g.abs() >= 1.0 {
                            // Say what the file wrote, and what it rounds to
                            // where that is what fails (0.99999999 is 1 in f32).
                            let rounded = if (written.abs() < 1.0) && g.abs() >= 1.0 {
                                format!(" (in single precision, the renderer's, {g})")
                            } else {
                                String::new()
                            };
                            return Err(self.invalid(
                                &gp,
                                format!("{written} is outside (-1, 1){rounded}: the Henyey-Greenstein mean cosine g must satisfy |g| < 1"),
                            ));
                        }
                        g
                    }
                    None => 0.0,
                };
                Material::Translucent {
                    ior: ior()?,
                    sigma_s,
                    sigma_a,
                    g,
                }
            }
            _ => {
                let (rv, rp) = f.req(self, "radiance")?;
                let radiance = self.vec3(rv, &rp)?;
                for (i, x) in radiance.to_array().into_iter().enumerate() {
                    if x < 0.0 {
                        return Err(self.invalid(
                            &join_index(&rp, i),
                            format!("radiance must not be negative, found {x}"),
                        ));
                    }
                }
                Material::Emitter { radiance }
            }
        })
    }

    fn render(&self, v: &Json, path: &str) -> Res<RenderSettings> {
        let f = self.object(v, path, RENDER_KEYS)?;
        let mut r = RenderSettings::default();
        if let Some((v, p)) = f.get("spp") {
            r.spp = self.u32_in(v, &p, 1, u32::MAX, " samples per pixel")?;
        }
        if let Some((v, p)) = f.get("max_bounces") {
            r.max_bounces = self.u32_in(v, &p, 0, u32::MAX, "")?;
        }
        if let Some((v, p)) = f.get("estimator_min_bounces") {
            r.estimator_min_bounces = self.u32_in(v, &p, 0, u32::MAX, "")?;
        }
        if let Some((v, p)) = f.get("seed") {
            r.seed = self.uint(v, &p)?;
        }
        Ok(r)
    }

    fn instances(
        &self,
        v: &Json,
        path: &str,
        mesh_names: &[String],
        material_names: &[String],
    ) -> Res<Vec<Instance>> {
        let Json::Arr(items) = v else {
            return Err(self.wrong_type(path, "an array of instances", v));
        };
        let mesh_index: HashMap<&str, usize> = mesh_names
            .iter()
            .enumerate()
            .map(|(i, n)| (n.as_str(), i))
            .collect();
        let material_index: HashMap<&str, usize> = material_names
            .iter()
            .enumerate()
            .map(|(i, n)| (n.as_str(), i))
            .collect();
        items
            .iter()
            .enumerate()
            .map(|(i, iv)| {
                let ip = join_index(path, i);
                let f = self.object(iv, &ip, INSTANCE_KEYS)?;
                let lookup = |key: &str,
                              what: &str,
                              index: &HashMap<&str, usize>,
                              names: &[String]|
                 -> Res<usize> {
                    let (nv, np) = f.req(self, key)?;
                    let name = self.string(nv, &np)?;
                    index.get(name).copied().ok_or_else(|| {
                        self.invalid(
                            &np,
                            format!("unknown {what} \"{name}\" ({})", name_list(names)),
                        )
                    })
                };
                let mesh = lookup("mesh", "mesh", &mesh_index, mesh_names)?;
                let material = lookup("material", "material", &material_index, material_names)?;
                let transform = match f.get("transform") {
                    Some((tv, tp)) => self.transform(tv, &tp)?,
                    None => Transform::default(),
                };
                let estimator = match f.get("estimator") {
                    Some((ev, ep)) => {
                        let rel = self.string(ev, &ep)?;
                        if rel.is_empty() {
                            return Err(self.invalid(&ep, "the estimator path is empty".into()));
                        }
                        Some(self.dir.join(rel))
                    }
                    None => None,
                };
                Ok(Instance {
                    mesh,
                    material,
                    transform,
                    estimator,
                })
            })
            .collect()
    }

    fn transform(&self, v: &Json, path: &str) -> Res<Transform> {
        let f = self.object(v, path, TRANSFORM_KEYS)?;
        let mut t = Transform::default();
        if let Some((sv, sp)) = f.get("scale") {
            let s = self.float(sv, &sp)?;
            // Checked after rounding to f32: 1e-50 is positive but becomes 0.
            if s <= 0.0 {
                let given = self.number(sv, &sp)?;
                return Err(self.invalid(
                    &sp,
                    format!("scale must be positive (as a 32-bit float), found {given}"),
                ));
            }
            t.scale = s;
        }
        if let Some((rv, rp)) = f.get("rotate") {
            let r = self.object(rv, &rp, ROTATE_KEYS)?;
            let (av, ap) = r.req(self, "axis")?;
            let axis = self.vec3_f64(av, &ap)?;
            let (dv, dp) = r.req(self, "deg")?;
            let deg = self.number(dv, &dp)?;
            // Only its direction matters: an axis whose squared length
            // leaves f64's normal range (1e-200 long) is divided
            // by its largest component first; others are used as written.
            let len2 = axis.length_squared();
            let m = axis.abs().max_element();
            let axis = if (len2 < f64::MIN_POSITIVE || !len2.is_finite()) && m > 0.0 {
                axis / m
            } else {
                axis
            };
            let Some(axis) = axis.try_normalize() else {
                return Err(self.invalid(&ap, "rotation axis [0, 0, 0] has zero length".into()));
            };
            // Double precision so that 90 degrees about an axis gives the
            // exactly rounded quaternion, the same as other implementations.
            t.rotation = DQuat::from_axis_angle(axis, deg.to_radians()).as_quat();
        }
        if let Some((tv, tp)) = f.get("translate") {
            t.translation = self.vec3(tv, &tp)?;
        }
        Ok(t)
    }
}
