//! Mesh sources: the `meshes` entries of a scene file. Owns the choice of
//! exactly one source per mesh (`quad`, `box`, `icosphere`, `obj`,
//! `procedural`) and the `smooth` flag, the validation of each source's
//! keys, and building the [`Mesh`] from it (the built-in shapes, an OBJ
//! file relative to the scene, or a procedural generator with the standard
//! object's parameters as defaults).

use super::{Cx, Fields, Res};
use crate::Mesh;
use crate::error::SceneError;
use crate::json::{Json, join_index, join_key};
use crate::obj::parse_obj;
use crate::procedural::{Procedural, ProceduralError};
use crate::shapes::{MAX_ICOSPHERE_SUBDIVISIONS, box_mesh, icosphere_mesh, quad_mesh};
use glam::{DVec3, Vec3};

const MESH_SOURCES: &[&str] = &["quad", "box", "icosphere", "obj", "procedural"];
const MESH_KEYS: &[&str] = &["quad", "box", "icosphere", "obj", "procedural", "smooth"];

impl Cx<'_> {
    pub(super) fn mesh(&self, v: &Json, path: &str) -> Res<Mesh> {
        let f = self.object(v, path, MESH_KEYS)?;
        let sources: Vec<(&str, &Json, String)> = MESH_SOURCES
            .iter()
            .filter_map(|&s| f.get(s).map(|(v, p)| (s, v, p)))
            .collect();
        let (source, sv, sp) = match sources.as_slice() {
            [one] => one,
            [] => {
                return Err(self.invalid(
                    path,
                    format!(
                        "a mesh needs one source key, one of: {}",
                        MESH_SOURCES.join(", ")
                    ),
                ));
            }
            many => {
                let names: Vec<&str> = many.iter().map(|(s, _, _)| *s).collect();
                return Err(self.invalid(
                    path,
                    format!(
                        "a mesh has exactly one source, found {}",
                        names.join(" and ")
                    ),
                ));
            }
        };
        let smooth = match f.get("smooth") {
            Some((smv, smp)) => {
                if *source != "obj" {
                    return Err(self.invalid(
                        &smp,
                        format!("\"smooth\" applies only to obj meshes (this one is a {source}): the built-in shapes are flat shaded"),
                    ));
                }
                self.boolean(smv, &smp)?
            }
            None => false,
        };
        match *source {
            "quad" => self.quad(sv, sp),
            "box" => self.box_source(sv, sp),
            "icosphere" => self.icosphere(sv, sp),
            "obj" => self.obj(sv, sp, smooth),
            _ => self.procedural(sv, sp),
        }
    }

    fn quad(&self, v: &Json, path: &str) -> Res<Mesh> {
        let Json::Arr(items) = v else {
            return Err(self.wrong_type(path, "an array of 4 points", v));
        };
        if items.len() != 4 {
            return Err(self.invalid(
                path,
                format!("a quad needs exactly 4 points, found {}", items.len()),
            ));
        }
        let mut p = [Vec3::ZERO; 4];
        for (i, (slot, item)) in p.iter_mut().zip(items).enumerate() {
            *slot = self.vec3(item, &join_index(path, i))?;
        }
        // Checked in f64 on the f32 points the renderer will use.
        let d: Vec<DVec3> = p.iter().map(|x| x.as_dvec3()).collect();
        let tri_normal = |a: DVec3, b: DVec3, c: DVec3| -> Option<DVec3> {
            let (e1, e2) = (b - a, c - a);
            let n = e1.cross(e2);
            // Zero area, or sides so close to collinear (sine below 1e-6)
            // that the normal is rounding noise.
            (n.length() > 1e-6 * e1.length() * e2.length()).then_some(n)
        };
        let n1 = tri_normal(d[0], d[1], d[2]);
        let n2 = tri_normal(d[0], d[2], d[3]);
        match (n1, n2) {
            (Some(n1), Some(n2)) if n1.dot(n2) > 0.0 => Ok(quad_mesh(p)),
            (Some(_), Some(_)) => Err(self.invalid(
                path,
                "the quad is folded: its triangles (0,1,2) and (0,2,3) face opposite ways (are the points in order around the quad?)".into(),
            )),
            (None, _) => Err(self.invalid(
                path,
                "degenerate quad: points 0, 1, 2 are collinear or coincide, so triangle (0,1,2) has no area".into(),
            )),
            (_, None) => Err(self.invalid(
                path,
                "degenerate quad: points 0, 2, 3 are collinear or coincide, so triangle (0,2,3) has no area".into(),
            )),
        }
    }

    fn box_source(&self, v: &Json, path: &str) -> Res<Mesh> {
        let f = self.object(v, path, &["min", "max"])?;
        let (minv, minp) = f.req(self, "min")?;
        let min = self.vec3(minv, &minp)?;
        let (maxv, maxp) = f.req(self, "max")?;
        let max = self.vec3(maxv, &maxp)?;
        for (axis, (lo, hi)) in ["x", "y", "z"]
            .into_iter()
            .zip(min.to_array().into_iter().zip(max.to_array()))
        {
            if lo >= hi {
                return Err(self.invalid(
                    path,
                    format!("min {min} is not below max {max} on the {axis} axis ({lo} >= {hi})"),
                ));
            }
        }
        Ok(box_mesh(min, max))
    }

    fn icosphere(&self, v: &Json, path: &str) -> Res<Mesh> {
        let f = self.object(v, path, &["center", "radius", "subdivisions"])?;
        let (cv, cp) = f.req(self, "center")?;
        let center = self.vec3(cv, &cp)?;
        let (rv, rp) = f.req(self, "radius")?;
        let radius = self.float(rv, &rp)?;
        if radius <= 0.0 {
            return Err(self.invalid(&rp, format!("radius must be positive, found {radius}")));
        }
        let (sv, sp) = f.req(self, "subdivisions")?;
        let subdivisions = self.u32_in(
            sv,
            &sp,
            0,
            MAX_ICOSPHERE_SUBDIVISIONS,
            " levels (level 8 already has 1,310,720 triangles)",
        )?;
        let mesh = icosphere_mesh(center, radius, subdivisions);
        // A radius tiny against the centre's coordinates rounds vertices
        // together in f32: the sphere would lose faces or vanish.
        let collapsed = mesh.triangles.iter().any(|t| {
            let [a, b, c] = t.map(|i| mesh.positions[i as usize]);
            (b - a).cross(c - a) == Vec3::ZERO
        });
        if collapsed {
            return Err(self.invalid(
                &rp,
                format!(
                    "radius {radius} is too small for a sphere centred at {center} in 32-bit \
                     floats: its vertices round together and triangles lose their area; \
                     give a larger radius, or centre the sphere at the origin and place it \
                     with the instance's transform"
                ),
            ));
        }
        Ok(mesh)
    }

    fn obj(&self, v: &Json, path: &str, smooth: bool) -> Res<Mesh> {
        let rel = self.string(v, path)?;
        if rel.is_empty() {
            return Err(self.invalid(path, "the OBJ path is empty".into()));
        }
        let file = self.dir.join(rel);
        let obj_err = |line: Option<usize>, message: String| SceneError::Obj {
            file: self.file.to_path_buf(),
            key: path.to_string(),
            obj: file.clone(),
            line,
            message,
        };
        let bytes = nppp_files::read_regular(&file)
            .map_err(|e| obj_err(None, format!("cannot read: {e}")))?;
        // Lossy: a stray Latin-1 byte in a comment must not reject a mesh.
        let text = String::from_utf8_lossy(&bytes);
        // Reading holds the text (twice, if it was not UTF-8) beside what
        // it builds.
        let text_bytes = (bytes.len() + text.len() * usize::from(bytes.len() != text.len())) as u64;
        let budget = nppp_files::available_memory().map(|a| a.saturating_sub(text_bytes));
        parse_obj(&text, smooth, budget).map_err(|e| obj_err(e.line, e.message))
    }

    /// How many triangles the mesh at `v` will have, where that is known
    /// without building it (the built-in shapes and procedural objects; not
    /// an OBJ) and `v` is valid (else the build reports the error).
    pub(super) fn predicted_triangles(&self, v: &Json, path: &str) -> Option<u64> {
        let f = self.object(v, path, MESH_KEYS).ok()?;
        if f.get("quad").is_some() {
            Some(2)
        } else if f.get("box").is_some() {
            Some(12)
        } else if let Some((iv, ip)) = f.get("icosphere") {
            let f = self
                .object(iv, &ip, &["center", "radius", "subdivisions"])
                .ok()?;
            let (sv, sp) = f.get("subdivisions")?;
            let n = self
                .u32_in(sv, &sp, 0, MAX_ICOSPHERE_SUBDIVISIONS, "")
                .ok()?;
            Some(20 * 4u64.pow(n))
        } else if let Some((pv, pp)) = f.get("procedural") {
            // One that will not build says why itself, naming its parameter.
            let proc = self.procedural_spec(pv, &pp).ok()?;
            proc.validate().ok()?;
            Some(proc.triangle_count()).filter(|&t| t <= crate::procedural::MAX_TRIANGLES)
        } else {
            None
        }
    }

    fn procedural(&self, v: &Json, path: &str) -> Res<Mesh> {
        let (entries, _) = self.typed_object(v, path)?;
        let proc = self.procedural_spec(v, path)?;
        let mesh = proc.build().map_err(|e| {
            // Point at the parameter when the generator names one of ours.
            let key = match &e {
                ProceduralError::InvalidParameter { parameter, .. }
                    if entries.iter().any(|(k, _)| k == parameter) =>
                {
                    join_key(path, parameter)
                }
                _ => path.to_string(),
            };
            self.invalid(&key, e.to_string())
        })?;
        Ok(Mesh {
            positions: mesh.positions,
            triangles: mesh.triangles,
            shading_normals: None,
        })
    }

    /// The procedural object `v` describes (its parameters checked, the
    /// project's standard object's values where one is missing), not built.
    fn procedural_spec(&self, v: &Json, path: &str) -> Res<Procedural> {
        let (_, ty) = self.typed_object(v, path)?;
        let type_path = join_key(path, "type");
        // Missing parameters take the values of the project's standard
        // object of that kind, so `{"type": "torus_knot"}` is the usual knot.
        let Some(standard) = Procedural::defaults()
            .into_iter()
            .find(|p| procedural_type(p) == ty)
        else {
            return Err(self.invalid(
                &type_path,
                format!(
                    "unknown procedural type \"{ty}\" (known: displaced_sphere, torus_knot, menger_sponge)"
                ),
            ));
        };
        let u32_param = |f: &Fields, key: &str, default: u32| -> Res<u32> {
            match f.get(key) {
                Some((v, p)) => self.u32_in(v, &p, 0, u32::MAX, ""),
                None => Ok(default),
            }
        };
        let f32_param = |f: &Fields, key: &str, default: f32| -> Res<f32> {
            match f.get(key) {
                Some((v, p)) => self.float(v, &p),
                None => Ok(default),
            }
        };
        Ok(match standard {
            Procedural::DisplacedSphere {
                subdivisions,
                amplitude,
                frequency,
                seed,
            } => {
                let f = self.object(
                    v,
                    path,
                    &["type", "subdivisions", "amplitude", "frequency", "seed"],
                )?;
                Procedural::DisplacedSphere {
                    subdivisions: u32_param(&f, "subdivisions", subdivisions)?,
                    amplitude: f32_param(&f, "amplitude", amplitude)?,
                    frequency: f32_param(&f, "frequency", frequency)?,
                    seed: match f.get("seed") {
                        Some((v, p)) => self.uint(v, &p)?,
                        None => seed,
                    },
                }
            }
            Procedural::TorusKnot {
                p,
                q,
                tube_radius,
                segments,
                sides,
            } => {
                let f = self.object(
                    v,
                    path,
                    &["type", "p", "q", "tube_radius", "segments", "sides"],
                )?;
                Procedural::TorusKnot {
                    p: u32_param(&f, "p", p)?,
                    q: u32_param(&f, "q", q)?,
                    tube_radius: f32_param(&f, "tube_radius", tube_radius)?,
                    segments: u32_param(&f, "segments", segments)?,
                    sides: u32_param(&f, "sides", sides)?,
                }
            }
            Procedural::MengerSponge { level } => {
                let f = self.object(v, path, &["type", "level"])?;
                Procedural::MengerSponge {
                    level: u32_param(&f, "level", level)?,
                }
            }
        })
    }
}

/// The scene-file spelling of a procedural object's kind.
fn procedural_type(p: &Procedural) -> &'static str {
    match p {
        Procedural::DisplacedSphere { .. } => "displaced_sphere",
        Procedural::TorusKnot { .. } => "torus_knot",
        Procedural::MengerSponge { .. } => "menger_sponge",
    }
}
