//! One test per error class of docs/scene-format.md ("Errors") and of the
//! loader's own strictness, each asserting the exact key path it names.

mod common;

use common::{FILE, base, check, expect_error, load_with_obj, parse};
use nppp_scene::{SceneError, parse_scene};
use serde_json::{Value, json};
use std::path::Path;

fn obj_of<'a>(v: &'a mut Value, path: &[&str]) -> &'a mut serde_json::Map<String, Value> {
    let mut cur = v;
    for k in path {
        cur = match k.parse::<usize>() {
            Ok(i) if cur.is_array() => &mut cur[i],
            _ => &mut cur[*k],
        };
    }
    cur.as_object_mut().expect("object")
}

// ---------------------------------------------------------------- sanity

#[test]
fn base_scene_is_valid() {
    let s = parse(&base()).expect("base scene loads");
    assert_eq!(s.instances.len(), 3);
    assert_eq!(s.meshes.len(), 3);
    assert_eq!(s.materials.len(), 4);
}

// ---------------------------------------------------------------- JSON level

#[test]
fn invalid_json_names_file_line_and_column() {
    let text = "{\n  \"camera\": {\"position\": [1, 2, 3],\n  }\n}";
    let err = parse_scene(text, Path::new(FILE)).unwrap_err();
    let msg = err.to_string();
    match &err {
        SceneError::Json {
            line, column, key, ..
        } => {
            assert_eq!(*line, 3, "{msg}");
            assert!(*column > 0, "{msg}");
            assert_eq!(key, "camera", "{msg}");
        }
        other => panic!("expected a JSON error, got {other}"),
    }
    assert!(msg.starts_with(&format!("{FILE}:3:")), "{msg}");
    assert!(msg.contains("invalid JSON"), "{msg}");
}

#[test]
fn truncated_and_empty_json_are_errors() {
    for text in ["", "   ", "{", "{\"camera\": [1, 2", "null", "[]", "42"] {
        let err = parse_scene(text, Path::new(FILE)).unwrap_err();
        assert!(err.to_string().contains(FILE), "{err}");
    }
}

#[test]
fn top_level_must_be_an_object() {
    let err = parse_scene("[1, 2, 3]", Path::new(FILE)).unwrap_err();
    assert!(matches!(err, SceneError::Invalid { .. }), "{err}");
    assert_eq!(err.key_path(), Some("(top level)"));
    assert_eq!(
        err.to_string(),
        format!("{FILE}: (top level): expected an object, found an array")
    );
}

#[test]
fn trailing_characters_are_an_error() {
    let text = format!("{} x", base());
    let err = parse_scene(&text, Path::new(FILE)).unwrap_err();
    assert!(matches!(err, SceneError::Json { .. }), "{err}");
    assert!(err.to_string().contains("trailing"), "{err}");
}

#[test]
fn number_overflowing_f64_names_its_key_path() {
    // JSON cannot write NaN, but 1e400 reads as infinity in most parsers.
    let text = base()
        .to_string()
        .replace("\"roughness\":0.2", "\"roughness\":1e400");
    assert!(text.contains("1e400"));
    let err = parse_scene(&text, Path::new(FILE)).unwrap_err();
    let msg = err.to_string();
    assert!(matches!(err, SceneError::Json { .. }), "{msg}");
    assert_eq!(err.key_path(), Some("materials.gold.roughness"), "{msg}");
    assert!(msg.contains("out of range"), "{msg}");
}

#[test]
fn duplicate_keys_are_an_error() {
    let text = base()
        .to_string()
        .replace("\"ior\":1.5", "\"ior\":1.5,\"ior\":1.2");
    let err = parse_scene(&text, Path::new(FILE)).unwrap_err();
    let msg = err.to_string();
    assert_eq!(err.key_path(), Some("materials.glass.ior"), "{msg}");
    assert!(msg.contains("duplicate key"), "{msg}");
}

#[test]
fn scene_file_unreadable_names_the_file() {
    let missing = Path::new("/nonexistent/nppp/scene.json");
    let err = nppp_scene::load_scene(missing).unwrap_err();
    assert!(matches!(err, SceneError::Read { .. }));
    assert!(
        err.to_string().contains("/nonexistent/nppp/scene.json"),
        "{err}"
    );
    assert_eq!(err.key_path(), None);
}

// ---------------------------------------------------------------- unknown keys

#[test]
fn unknown_top_level_key() {
    expect_error(
        |v| {
            v["name"] = json!("cornell");
        },
        "name",
        "unknown key",
    );
}

#[test]
fn unknown_camera_key() {
    expect_error(
        |v| {
            v["camera"]["fov"] = json!(40);
        },
        "camera.fov",
        "unknown key",
    );
}

#[test]
fn unknown_material_keys_depend_on_type() {
    // Each key is valid for some other type, so the check is per type.
    expect_error(
        |v| {
            v["materials"]["white"]["roughness"] = json!(0.1);
        },
        "materials.white.roughness",
        "unknown key",
    );
    expect_error(
        |v| {
            v["materials"]["gold"]["ior"] = json!(1.1);
        },
        "materials.gold.ior",
        "unknown key",
    );
    expect_error(
        |v| {
            v["materials"]["glass"]["albedo"] = json!([1, 1, 1]);
        },
        "materials.glass.albedo",
        "unknown key",
    );
    expect_error(
        |v| {
            v["materials"]["lamp"]["reflectance"] = json!([1, 1, 1]);
        },
        "materials.lamp.reflectance",
        "unknown key",
    );
}

#[test]
fn unknown_mesh_keys() {
    expect_error(
        |v| {
            v["meshes"]["floor"]["flip"] = json!(true);
        },
        "meshes.floor.flip",
        "unknown key",
    );
    expect_error(
        |v| {
            v["meshes"]["block"]["box"]["center"] = json!([0, 0, 0]);
        },
        "meshes.block.box.center",
        "unknown key",
    );
    expect_error(
        |v| {
            v["meshes"]["ball"]["icosphere"]["smooth"] = json!(true);
        },
        "meshes.ball.icosphere.smooth",
        "unknown key",
    );
}

#[test]
fn unknown_instance_transform_rotate_render_keys() {
    expect_error(
        |v| {
            v["instances"][0]["materal"] = json!("white");
        },
        "instances[0].materal",
        "unknown key",
    );
    expect_error(
        |v| {
            v["instances"][1]["transform"]["rotation"] = json!(3);
        },
        "instances[1].transform.rotation",
        "unknown key",
    );
    expect_error(
        |v| {
            v["instances"][1]["transform"]["rotate"]["angle"] = json!(3);
        },
        "instances[1].transform.rotate.angle",
        "unknown key",
    );
    expect_error(
        |v| {
            v["render"]["samples"] = json!(3);
        },
        "render.samples",
        "unknown key",
    );
}

#[test]
fn names_that_are_not_identifiers_are_quoted_in_key_paths() {
    expect_error(
        |v| {
            let m = v["materials"]["white"].clone();
            obj_of(v, &["materials"]).insert("a.b c".into(), m);
            v["materials"]["a.b c"]["albedo"] = json!([2, 0, 0]);
        },
        "materials[\"a.b c\"].albedo[0]",
        "outside [0, 1]",
    );
}

// ---------------------------------------------------------------- missing keys

#[test]
fn missing_top_level_keys() {
    for key in ["camera", "materials", "meshes", "instances"] {
        expect_error(
            |v| {
                obj_of(v, &[]).remove(key);
            },
            key,
            "required key is missing",
        );
    }
}

#[test]
fn missing_camera_keys() {
    for key in ["position", "look_at", "fov_y_deg", "width", "height"] {
        expect_error(
            |v| {
                obj_of(v, &["camera"]).remove(key);
            },
            &format!("camera.{key}"),
            "missing",
        );
    }
}

#[test]
fn missing_material_keys() {
    expect_error(
        |v| {
            obj_of(v, &["materials", "white"]).remove("type");
        },
        "materials.white.type",
        "missing",
    );
    expect_error(
        |v| {
            obj_of(v, &["materials", "white"]).remove("albedo");
        },
        "materials.white.albedo",
        "missing",
    );
    expect_error(
        |v| {
            obj_of(v, &["materials", "gold"]).remove("reflectance");
        },
        "materials.gold.reflectance",
        "missing",
    );
    expect_error(
        |v| {
            obj_of(v, &["materials", "gold"]).remove("roughness");
        },
        "materials.gold.roughness",
        "missing",
    );
    expect_error(
        |v| {
            obj_of(v, &["materials", "glass"]).remove("ior");
        },
        "materials.glass.ior",
        "missing",
    );
    expect_error(
        |v| {
            obj_of(v, &["materials", "lamp"]).remove("radiance");
        },
        "materials.lamp.radiance",
        "missing",
    );
}

#[test]
fn missing_mesh_source_keys() {
    expect_error(
        |v| {
            obj_of(v, &["meshes", "block", "box"]).remove("min");
        },
        "meshes.block.box.min",
        "missing",
    );
    expect_error(
        |v| {
            obj_of(v, &["meshes", "block", "box"]).remove("max");
        },
        "meshes.block.box.max",
        "missing",
    );
    for key in ["center", "radius", "subdivisions"] {
        expect_error(
            |v| {
                obj_of(v, &["meshes", "ball", "icosphere"]).remove(key);
            },
            &format!("meshes.ball.icosphere.{key}"),
            "missing",
        );
    }
}

#[test]
fn missing_instance_and_rotate_keys() {
    expect_error(
        |v| {
            v["instances"][0].as_object_mut().unwrap().remove("mesh");
        },
        "instances[0].mesh",
        "missing",
    );
    expect_error(
        |v| {
            v["instances"][2]
                .as_object_mut()
                .unwrap()
                .remove("material");
        },
        "instances[2].material",
        "missing",
    );
    expect_error(
        |v| {
            obj_of(v, &["instances", "1", "transform", "rotate"]).remove("axis");
        },
        "instances[1].transform.rotate.axis",
        "missing",
    );
    expect_error(
        |v| {
            obj_of(v, &["instances", "1", "transform", "rotate"]).remove("deg");
        },
        "instances[1].transform.rotate.deg",
        "missing",
    );
}

// ---------------------------------------------------------------- wrong types

#[test]
fn wrong_types_name_expected_and_found() {
    expect_error(
        |v| {
            v["camera"]["width"] = json!("256");
        },
        "camera.width",
        "found a string",
    );
    expect_error(
        |v| {
            v["camera"]["position"] = json!([1, 2]);
        },
        "camera.position",
        "3 numbers, found 2 elements",
    );
    expect_error(
        |v| {
            v["camera"]["up"] = json!([0, "1", 0]);
        },
        "camera.up[1]",
        "expected a number, found a string",
    );
    expect_error(
        |v| {
            v["camera"]["up"] = json!(null);
        },
        "camera.up",
        "found null",
    );
    expect_error(
        |v| {
            v["materials"] = json!([]);
        },
        "materials",
        "found an array",
    );
    expect_error(
        |v| {
            v["materials"]["white"] = json!("diffuse");
        },
        "materials.white",
        "expected an object",
    );
    expect_error(
        |v| {
            v["materials"]["white"]["type"] = json!(1);
        },
        "materials.white.type",
        "expected a string",
    );
    expect_error(
        |v| {
            v["meshes"] = json!(null);
        },
        "meshes",
        "found null",
    );
    expect_error(
        |v| {
            v["instances"] = json!({});
        },
        "instances",
        "found an object",
    );
    expect_error(
        |v| {
            v["instances"][0] = json!("floor");
        },
        "instances[0]",
        "expected an object",
    );
    expect_error(
        |v| {
            v["instances"][0]["mesh"] = json!(0);
        },
        "instances[0].mesh",
        "expected a string",
    );
    expect_error(
        |v| {
            v["instances"][1]["estimator"] = json!(5);
        },
        "instances[1].estimator",
        "expected a string",
    );
    expect_error(
        |v| {
            v["instances"][1]["transform"]["scale"] = json!([1, 1, 1]);
        },
        "instances[1].transform.scale",
        "expected a number",
    );
    expect_error(
        |v| {
            v["render"] = json!(64);
        },
        "render",
        "expected an object",
    );
    expect_error(
        |v| {
            v["meshes"]["floor"]["quad"] = json!({});
        },
        "meshes.floor.quad",
        "expected an array",
    );
}

// ---------------------------------------------------------------- numbers

#[test]
fn numbers_not_finite_as_f32_are_rejected() {
    // 1e39 is a fine f64 but infinite as the f32 the renderer computes with.
    expect_error(
        |v| {
            v["camera"]["position"][0] = json!(1e39);
        },
        "camera.position[0]",
        "not finite",
    );
    expect_error(
        |v| {
            v["materials"]["glass"]["ior"] = json!(-1e300);
        },
        "materials.glass.ior",
        "not finite",
    );
    expect_error(
        |v| {
            v["instances"][1]["transform"]["translate"][2] = json!(4e38);
        },
        "instances[1].transform.translate[2]",
        "not finite",
    );
    expect_error(
        |v| {
            v["meshes"]["floor"]["quad"][2][1] = json!(1e100);
        },
        "meshes.floor.quad[2][1]",
        "not finite",
    );
}

// ---------------------------------------------------------------- materials

#[test]
fn albedo_outside_unit_interval() {
    expect_error(
        |v| {
            v["materials"]["white"]["albedo"][1] = json!(1.01);
        },
        "materials.white.albedo[1]",
        "outside [0, 1]",
    );
    expect_error(
        |v| {
            v["materials"]["white"]["albedo"][2] = json!(-0.1);
        },
        "materials.white.albedo[2]",
        "outside [0, 1]",
    );
}

#[test]
fn reflectance_outside_unit_interval() {
    expect_error(
        |v| {
            v["materials"]["gold"]["reflectance"][0] = json!(2);
        },
        "materials.gold.reflectance[0]",
        "outside [0, 1]",
    );
    expect_error(
        |v| {
            v["materials"]["gold"]["reflectance"][2] = json!(-1);
        },
        "materials.gold.reflectance[2]",
        "outside [0, 1]",
    );
}

#[test]
fn roughness_outside_unit_interval() {
    expect_error(
        |v| {
            v["materials"]["gold"]["roughness"] = json!(1.5);
        },
        "materials.gold.roughness",
        "outside [0, 1]",
    );
    expect_error(
        |v| {
            v["materials"]["gold"]["roughness"] = json!(-0.01);
        },
        "materials.gold.roughness",
        "outside [0, 1]",
    );
    // The bounds themselves are valid (0 is a mirror).
    for ok in [0.0, 1.0] {
        let mut v = base();
        v["materials"]["gold"]["roughness"] = json!(ok);
        parse(&v).expect("roughness bound is valid");
    }
}

#[test]
fn negative_radiance() {
    expect_error(
        |v| {
            v["materials"]["lamp"]["radiance"][1] = json!(-0.5);
        },
        "materials.lamp.radiance[1]",
        "negative",
    );
}

#[test]
fn ior_not_positive() {
    expect_error(
        |v| {
            v["materials"]["glass"]["ior"] = json!(0);
        },
        "materials.glass.ior",
        "positive",
    );
    expect_error(
        |v| {
            v["materials"]["glass"]["ior"] = json!(-1.5);
        },
        "materials.glass.ior",
        "positive",
    );
}

#[test]
fn unknown_material_type() {
    expect_error(
        |v| {
            v["materials"]["white"]["type"] = json!("lambert");
        },
        "materials.white.type",
        "unknown material type \"lambert\"",
    );
}

#[test]
fn translucent_loads_with_its_medium() {
    let mut v = base();
    v["materials"]["jade"] = json!({"type": "translucent", "ior": 1.6,
        "sigma_s": [90, 110, 95], "sigma_a": [1.5, 0.4, 1.2], "g": 0.2});
    v["instances"][2]["material"] = json!("jade");
    let s = parse(&v).expect("a translucent closed mesh loads");
    let jade = s.material_names.iter().position(|n| n == "jade").unwrap();
    assert_eq!(
        s.materials[jade],
        nppp_scene::Material::Translucent {
            ior: 1.6,
            sigma_s: glam::Vec3::new(90.0, 110.0, 95.0),
            sigma_a: glam::Vec3::new(1.5, 0.4, 1.2),
            g: 0.2
        }
    );
    // g is optional (isotropic).
    v["materials"]["jade"].as_object_mut().unwrap().remove("g");
    let s = parse(&v).unwrap();
    assert!(matches!(s.materials[jade], nppp_scene::Material::Translucent { g, .. } if g == 0.0));
}

#[test]
fn translucent_bad_coefficients_phase_and_ior() {
    let jade = || json!({"type": "translucent", "ior": 1.5, "sigma_s": [1, 1, 1], "sigma_a": [0, 0, 0], "g": 0});
    let cases: [(&str, Value, &str, &str); 6] = [
        (
            "sigma_s",
            json!([1, -2, 1]),
            "materials.jade.sigma_s[1]",
            ">= 0",
        ),
        (
            "sigma_a",
            json!([1e39, 0, 0]),
            "materials.jade.sigma_a[0]",
            "finite",
        ),
        ("g", json!(1.0), "materials.jade.g", "|g| < 1"),
        ("g", json!(-1.5), "materials.jade.g", "|g| < 1"),
        ("ior", json!(0), "materials.jade.ior", "positive"),
        ("sigma_s", json!([1, 1]), "materials.jade.sigma_s", "3"),
    ];
    for (key, value, path, needle) in cases {
        expect_error(
            |v| {
                let mut m = jade();
                m[key] = value;
                v["materials"]["jade"] = m;
            },
            path,
            needle,
        );
    }
    expect_error(
        |v| {
            let mut m = jade();
            m["colour"] = json!([1, 1, 1]);
            v["materials"]["jade"] = m;
        },
        "materials.jade.colour",
        "unknown key",
    );
    expect_error(
        |v| {
            let mut m = jade();
            m.as_object_mut().unwrap().remove("sigma_a");
            v["materials"]["jade"] = m;
        },
        "materials.jade.sigma_a",
        "missing",
    );
}

#[test]
fn translucent_on_an_open_mesh_names_mesh_and_material() {
    // The floor quad has a border: no inside for a medium.
    let err = expect_error(
        |v| {
            v["materials"]["jade"] = json!({"type": "translucent", "ior": 1.5, "sigma_s": [1, 1, 1], "sigma_a": [0, 0, 0]});
            v["instances"][0]["material"] = json!("jade");
        },
        "meshes.floor",
        "not a closed mesh",
    );
    let msg = err.to_string();
    assert!(msg.contains("\"jade\"") && msg.contains("border"), "{msg}");
    // The same open mesh with a surface material is fine.
    assert!(parse(&base()).is_ok());
}

// ---------------------------------------------------------------- meshes

#[test]
fn box_min_not_below_max() {
    expect_error(
        |v| {
            v["meshes"]["block"]["box"]["max"][1] = json!(0);
        },
        "meshes.block.box",
        "on the y axis",
    );
    expect_error(
        |v| {
            v["meshes"]["block"]["box"]["min"][2] = json!(300);
        },
        "meshes.block.box",
        "on the z axis",
    );
}

#[test]
fn icosphere_over_eight_levels() {
    expect_error(
        |v| {
            v["meshes"]["ball"]["icosphere"]["subdivisions"] = json!(9);
        },
        "meshes.ball.icosphere.subdivisions",
        "at most 8",
    );
    // A huge value must fail before anything is allocated.
    expect_error(
        |v| {
            v["meshes"]["ball"]["icosphere"]["subdivisions"] = json!(u64::MAX);
        },
        "meshes.ball.icosphere.subdivisions",
        "at most 8",
    );
}

/// A radius tiny against the centre's coordinates rounds the vertices
/// together in f32: the sphere rendered as nothing, without a word (and a
/// translucent one was called non-manifold).
#[test]
fn icosphere_radius_too_small_for_its_centre() {
    expect_error(
        |v| {
            v["meshes"]["ball"]["icosphere"]["center"] = json!([0.5, 0.3, 0.0]);
            v["meshes"]["ball"]["icosphere"]["radius"] = json!(1e-9);
        },
        "meshes.ball.icosphere.radius",
        "too small for a sphere centred at",
    );
}

#[test]
fn icosphere_subdivisions_must_be_non_negative_integer() {
    expect_error(
        |v| {
            v["meshes"]["ball"]["icosphere"]["subdivisions"] = json!(-1);
        },
        "meshes.ball.icosphere.subdivisions",
        "non-negative integer",
    );
    expect_error(
        |v| {
            v["meshes"]["ball"]["icosphere"]["subdivisions"] = json!(2.5);
        },
        "meshes.ball.icosphere.subdivisions",
        "integer",
    );
}

#[test]
fn icosphere_radius_not_positive() {
    expect_error(
        |v| {
            v["meshes"]["ball"]["icosphere"]["radius"] = json!(0);
        },
        "meshes.ball.icosphere.radius",
        "positive",
    );
    expect_error(
        |v| {
            v["meshes"]["ball"]["icosphere"]["radius"] = json!(-2);
        },
        "meshes.ball.icosphere.radius",
        "positive",
    );
}

#[test]
fn quad_needs_exactly_four_points() {
    expect_error(
        |v| {
            v["meshes"]["floor"]["quad"].as_array_mut().unwrap().pop();
        },
        "meshes.floor.quad",
        "exactly 4 points, found 3",
    );
    expect_error(
        |v| {
            v["meshes"]["floor"]["quad"]
                .as_array_mut()
                .unwrap()
                .push(json!([1, 1, 1]));
        },
        "meshes.floor.quad",
        "found 5",
    );
}

#[test]
fn degenerate_quads() {
    // All four points on a line.
    expect_error(
        |v| {
            v["meshes"]["floor"]["quad"] = json!([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]]);
        },
        "meshes.floor.quad",
        "degenerate quad",
    );
    // A repeated point collapses triangle (0,2,3).
    expect_error(
        |v| {
            v["meshes"]["floor"]["quad"] = json!([[0, 0, 0], [1, 0, 0], [1, 1, 0], [1, 1, 0]]);
        },
        "meshes.floor.quad",
        "(0,2,3) has no area",
    );
    // Points out of order: a bow tie whose halves face opposite ways.
    expect_error(
        |v| {
            v["meshes"]["floor"]["quad"] = json!([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]]);
        },
        "meshes.floor.quad",
        "folded",
    );
}

#[test]
fn mesh_needs_exactly_one_source() {
    expect_error(
        |v| {
            v["meshes"]["floor"] = json!({});
        },
        "meshes.floor",
        "one source key",
    );
    expect_error(
        |v| {
            v["meshes"]["floor"]["box"] = json!({"min": [0,0,0], "max": [1,1,1]});
        },
        "meshes.floor",
        "found quad and box",
    );
}

#[test]
fn smooth_only_for_obj() {
    expect_error(
        |v| {
            v["meshes"]["floor"]["smooth"] = json!(true);
        },
        "meshes.floor.smooth",
        "only to obj",
    );
}

#[test]
fn obj_path_must_be_a_string() {
    expect_error(
        |v| {
            v["meshes"]["floor"] = json!({"obj": ["a.obj"]});
        },
        "meshes.floor.obj",
        "expected a string",
    );
    expect_error(
        |v| {
            v["meshes"]["floor"] = json!({"obj": ""});
        },
        "meshes.floor.obj",
        "empty",
    );
}

#[test]
fn procedural_unknown_type_and_bad_parameters() {
    expect_error(
        |v| {
            v["meshes"]["p"] = json!({"procedural": {"type": "teapot"}});
        },
        "meshes.p.procedural.type",
        "unknown procedural type",
    );
    expect_error(
        |v| {
            v["meshes"]["p"] = json!({"procedural": {"level": 2}});
        },
        "meshes.p.procedural.type",
        "missing",
    );
    expect_error(
        |v| {
            v["meshes"]["p"] = json!({"procedural": {"type": "menger_sponge", "size": 2}});
        },
        "meshes.p.procedural.size",
        "unknown key",
    );
    expect_error(
        |v| {
            v["meshes"]["p"] = json!({"procedural": {"type": "menger_sponge", "level": -1}});
        },
        "meshes.p.procedural.level",
        "non-negative",
    );
    expect_error(
        |v| {
            v["meshes"]["p"] = json!({"procedural": {"type": "menger_sponge", "level": 40}});
        },
        "meshes.p.procedural.level",
        "level = 40",
    );
    expect_error(
        |v| {
            v["meshes"]["p"] = json!({"procedural": {"type": "torus_knot", "p": 0}});
        },
        "meshes.p.procedural.p",
        "p = 0",
    );
    expect_error(
        |v| {
            v["meshes"]["p"] = json!({"procedural": {"type": "displaced_sphere", "amplitude": 2}});
        },
        "meshes.p.procedural.amplitude",
        "amplitude",
    );
    // Absurd sizes are refused before allocating.
    expect_error(
        |v| {
            v["meshes"]["p"] =
                json!({"procedural": {"type": "displaced_sphere", "subdivisions": 30}});
        },
        "meshes.p.procedural",
        "triangles",
    );
}

// ---------------------------------------------------------------- OBJ files

#[track_caller]
fn obj_error(obj: &str, smooth: bool, needle: &str) -> SceneError {
    let value = if smooth {
        json!({"obj": "meshes/m.obj", "smooth": true})
    } else {
        json!({"obj": "meshes/m.obj"})
    };
    let (res, _) = load_with_obj("err", obj, value);
    let err = res.expect_err("OBJ should be rejected");
    let msg = err.to_string();
    assert!(matches!(err, SceneError::Obj { .. }), "{msg}");
    assert_eq!(err.key_path(), Some("meshes.m.obj"), "{msg}");
    assert!(msg.contains("meshes.m.obj"), "{msg}");
    assert!(msg.contains("m.obj"), "{msg}");
    assert!(msg.contains(needle), "message lacks {needle:?}: {msg}");
    err
}

#[test]
fn obj_unreadable() {
    let (res, dir) = load_with_obj("missing", "", json!({"obj": "meshes/nope.obj"}));
    let err = res.expect_err("missing OBJ");
    let msg = err.to_string();
    assert_eq!(err.key_path(), Some("meshes.m.obj"), "{msg}");
    assert!(
        msg.contains(&dir.join("meshes/nope.obj").display().to_string()),
        "{msg}"
    );
    assert!(msg.contains("cannot read"), "{msg}");
}

#[test]
fn obj_index_past_its_vertices() {
    let err = obj_error(
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n",
        false,
        "vertex index 4 points past the file's 3 vertices",
    );
    assert!(err.to_string().contains("m.obj:4:"), "{err}");
    obj_error(
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\nf 1//1 2//2 3//1\n",
        false,
        "normal index 2 points past",
    );
    obj_error(
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1 2/1 3/3\n",
        false,
        "texture coordinate index 3 points past",
    );
}

#[test]
fn obj_relative_index_before_first_vertex() {
    obj_error(
        "v 0 0 0\nv 1 0 0\nf -1 -2 -3\n",
        false,
        "only 2 defined so far",
    );
}

#[test]
fn obj_index_zero() {
    obj_error(
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n",
        false,
        "index 0 is invalid",
    );
}

#[test]
fn obj_face_with_fewer_than_three_vertices() {
    let err = obj_error(
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2\n",
        false,
        "at least 3 vertices",
    );
    assert!(err.to_string().contains("m.obj:5:"), "{err}");
}

#[test]
fn obj_smooth_face_without_normals() {
    let err = obj_error(
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\nf 1//1 2//1 3//1\nf 1 2 3\n",
        true,
        "no vertex normals",
    );
    assert!(err.to_string().contains("m.obj:6:"), "{err}");
    // One corner without a normal is enough.
    obj_error(
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\nf 1//1 2 3//1\n",
        true,
        "no vertex normals",
    );
}

#[test]
fn obj_smooth_zero_normal() {
    obj_error(
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 0\nf 1//1 2//1 3//1\n",
        true,
        "zero length",
    );
}

#[test]
fn obj_malformed_lines() {
    obj_error("v 0 0\nf 1 1 1\n", false, "needs 3 coordinates");
    obj_error("v 0 zero 0\n", false, "not a number");
    obj_error("v 0 1e39 0\n", false, "not finite");
    obj_error("v 0 nan 0\n", false, "not finite");
    obj_error(
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1/ 2 3\n",
        false,
        "is not one of",
    );
    obj_error(
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1/1/1/1 2 3\n",
        false,
        "is not one of",
    );
    obj_error(
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 x\n",
        false,
        "not an integer",
    );
}

#[test]
fn obj_without_faces() {
    obj_error("v 0 0 0\nv 1 0 0\nv 0 1 0\n", false, "no faces");
}

/// Faces that exist but cannot be hit: the object rendered invisible
/// without a word.
#[test]
fn obj_with_only_zero_area_faces() {
    obj_error(
        "v 0 0 0\nv 1 1 1\nv 2 2 2\nf 1 2 3\nf 1 1 2\n",
        false,
        "zero area",
    );
}

// ---------------------------------------------------------------- instances

#[test]
fn unknown_mesh_name() {
    expect_error(
        |v| {
            v["instances"][2]["mesh"] = json!("dragon");
        },
        "instances[2].mesh",
        "unknown mesh \"dragon\"",
    );
}

#[test]
fn unknown_material_name() {
    let err = expect_error(
        |v| {
            v["instances"][0]["material"] = json!("golld");
        },
        "instances[0].material",
        "unknown material \"golld\"",
    );
    assert!(
        err.to_string().contains("\"gold\""),
        "lists the known names: {err}"
    );
}

#[test]
fn scale_not_positive() {
    expect_error(
        |v| {
            v["instances"][1]["transform"]["scale"] = json!(0);
        },
        "instances[1].transform.scale",
        "positive",
    );
    expect_error(
        |v| {
            v["instances"][1]["transform"]["scale"] = json!(-2);
        },
        "instances[1].transform.scale",
        "positive",
    );
    // Positive in the file but zero as an f32.
    expect_error(
        |v| {
            v["instances"][1]["transform"]["scale"] = json!(1e-50);
        },
        "instances[1].transform.scale",
        "positive",
    );
}

#[test]
fn scale_not_finite() {
    expect_error(
        |v| {
            v["instances"][1]["transform"]["scale"] = json!(1e200);
        },
        "instances[1].transform.scale",
        "not finite",
    );
}

#[test]
fn zero_length_rotation_axis() {
    expect_error(
        |v| {
            v["instances"][1]["transform"]["rotate"]["axis"] = json!([0, 0, 0]);
        },
        "instances[1].transform.rotate.axis",
        "zero length",
    );
    expect_error(
        |v| {
            v["instances"][1]["transform"]["rotate"]["axis"] = json!([0, -0.0, 0]);
        },
        "instances[1].transform.rotate.axis",
        "zero length",
    );
}

/// Only the axis' direction matters: one whose squared length leaves
/// f64's normal range (1e-200 long) is the same rotation as [1, 1, 0]
/// (it was "zero length", printed with 200 digits).
#[test]
fn rotation_axes_of_any_length_give_their_direction() {
    let rotation = |axis: Value| {
        let mut v = base();
        v["instances"][1]["transform"]["rotate"] = json!({"axis": axis, "deg": 30});
        parse(&v).expect("loads").instances[1].transform.rotation
    };
    let unit = rotation(json!([1, 1, 0]));
    for axis in [
        json!([1e-200, 1e-200, 0]),
        json!([3e38, 3e38, 0]),
        json!([5e-324, 5e-324, 0]),
    ] {
        let r = rotation(axis.clone());
        assert!(r.abs_diff_eq(unit, 1e-7), "{axis}: {r:?} against {unit:?}");
    }
}

#[test]
fn estimator_path_must_not_be_empty() {
    expect_error(
        |v| {
            v["instances"][1]["estimator"] = json!("");
        },
        "instances[1].estimator",
        "empty",
    );
}

// ---------------------------------------------------------------- camera

#[test]
fn camera_position_equals_look_at() {
    expect_error(
        |v| {
            v["camera"]["look_at"] = json!([278, 273, -800]);
        },
        "camera.look_at",
        "equals camera.position",
    );
}

#[test]
fn camera_up_parallel_to_forward() {
    expect_error(
        |v| {
            v["camera"]["up"] = json!([0, 0, 1]);
        },
        "camera.up",
        "parallel",
    );
    expect_error(
        |v| {
            v["camera"]["up"] = json!([0, 0, -3]);
        },
        "camera.up",
        "parallel",
    );
    // The default up is parallel to a camera looking straight down.
    expect_error(
        |v| {
            obj_of(v, &["camera"]).remove("up");
            v["camera"]["look_at"] = json!([278, -100, -800]);
        },
        "camera.up",
        "parallel",
    );
    expect_error(
        |v| {
            v["camera"]["up"] = json!([0, 0, 0]);
        },
        "camera.up",
        "no direction",
    );
    // Parallel whatever its length.
    expect_error(
        |v| {
            v["camera"]["up"] = json!([0, 0, 3e30]);
        },
        "camera.up",
        "parallel",
    );
}

/// `up` is a direction: one of any length f32 holds is that direction
/// (a squared length past f32's range was refused as "no direction").
#[test]
fn camera_up_of_any_length_is_its_direction() {
    // Looking along z, and nearly straight up (1e-3 and 1e-4 off the y
    // axis: a short `up` made a subnormal cross product there, refused as
    // parallel or normalized 5.6% short).
    let straight_on = (json!([278, 273, -800]), json!([278, 273, 0]));
    let nearly_up = |tilt: f64| (json!([0, 0, 0]), json!([tilt, 1.0, 0]));
    for (camera, up) in [
        (straight_on.clone(), json!([0, 2e19, 0])),
        (straight_on.clone(), json!([1e30, 1e30, 0])),
        (straight_on.clone(), json!([0, 1e-30, 0])),
        (nearly_up(1e-4), json!([0, 2e-19, 0])),
        (nearly_up(1e-3), json!([0, 1e-18, 0])),
        (nearly_up(1e-4), json!([0, 5e-18, 0])),
    ] {
        let mut v = base();
        v["camera"]["position"] = camera.0;
        v["camera"]["look_at"] = camera.1;
        v["camera"]["up"] = up.clone();
        let scene = parse(&v).unwrap_or_else(|e| panic!("up {up}: {e}"));
        let c = &scene.camera;
        let forward = (c.look_at - c.position).normalize();
        let right = forward.cross(c.up).normalize();
        assert!(
            right.is_finite() && (right.length() - 1.0).abs() < 1e-6,
            "up {up}: right {right}"
        );
    }
    // Exact: an `up` of another length is the same up, bit for bit.
    let mut v = base();
    v["camera"]["up"] = json!([0.1, 1.0, 0]);
    let one = parse(&v).unwrap().camera.up;
    v["camera"]["up"] = json!([0.4, 4.0, 0]);
    assert_eq!(parse(&v).unwrap().camera.up, one);
}

#[test]
fn camera_fov_outside_open_interval() {
    for fov in [json!(0), json!(180), json!(-10), json!(200.5)] {
        expect_error(
            |v| {
                v["camera"]["fov_y_deg"] = fov;
            },
            "camera.fov_y_deg",
            "strictly between 0 and 180",
        );
    }
}

#[test]
fn camera_image_size() {
    expect_error(
        |v| {
            v["camera"]["width"] = json!(0);
        },
        "camera.width",
        "at least 1",
    );
    expect_error(
        |v| {
            v["camera"]["height"] = json!(0);
        },
        "camera.height",
        "at least 1",
    );
    expect_error(
        |v| {
            v["camera"]["width"] = json!(16385);
        },
        "camera.width",
        "at most 16384",
    );
    expect_error(
        |v| {
            v["camera"]["height"] = json!(1u64 << 40);
        },
        "camera.height",
        "at most 16384",
    );
    expect_error(
        |v| {
            v["camera"]["width"] = json!(-64);
        },
        "camera.width",
        "non-negative integer",
    );
    expect_error(
        |v| {
            v["camera"]["width"] = json!(64.5);
        },
        "camera.width",
        "integer",
    );
    // The maximum itself renders.
    let mut v = base();
    v["camera"]["width"] = json!(16384);
    v["camera"]["height"] = json!(16384);
    parse(&v).expect("16384 x 16384 is allowed");
}

// ---------------------------------------------------------------- render

#[test]
fn spp_zero() {
    expect_error(
        |v| {
            v["render"]["spp"] = json!(0);
        },
        "render.spp",
        "at least 1",
    );
}

#[test]
fn negative_or_fractional_counts() {
    expect_error(
        |v| {
            v["render"]["max_bounces"] = json!(-1);
        },
        "render.max_bounces",
        "non-negative integer",
    );
    expect_error(
        |v| {
            v["render"]["estimator_min_bounces"] = json!(1.5);
        },
        "render.estimator_min_bounces",
        "integer",
    );
    expect_error(
        |v| {
            v["render"]["spp"] = json!(4294967296u64);
        },
        "render.spp",
        "at most",
    );
}

#[test]
fn seed_negative_or_fractional() {
    expect_error(
        |v| {
            v["render"]["seed"] = json!(-7);
        },
        "render.seed",
        "non-negative integer",
    );
    expect_error(
        |v| {
            v["render"]["seed"] = json!(7.25);
        },
        "render.seed",
        "integer",
    );
    expect_error(
        |v| {
            v["render"]["seed"] = json!(1e17);
        },
        "render.seed",
        "not exactly representable",
    );
}

#[test]
fn every_error_message_names_the_file() {
    // Spot-check the Display format: "<file>: <key path>: <message>".
    let err = expect_error(
        |v| {
            v["camera"]["fov_y_deg"] = json!(0);
        },
        "camera.fov_y_deg",
        "",
    );
    assert!(
        err.to_string()
            .starts_with(&format!("{FILE}: camera.fov_y_deg: ")),
        "{err}"
    );
    check(&err, "camera.fov_y_deg", "180");
}

/// Sizes 32-bit float geometry cannot hold: beyond 1e12 the intersection
/// test's products overflow (8e12 rendered 16% dark), under 1e-9 they
/// underflow, an object spanning a few float steps at its place has its
/// vertices rounded together (its tree took minutes to build), and a medium
/// whose mean free path is under one step cannot move its walks.
#[test]
fn sizes_beyond_32_bit_float_geometry() {
    expect_error(
        |v| v["instances"][1]["transform"]["translate"] = json!([3e12, 0, 0]),
        "instances[1].transform",
        "beyond 1e12",
    );
    expect_error(
        |v| v["instances"][2]["transform"] = json!({"scale": 1e-10}),
        "instances[2].transform",
        "below 1e-9",
    );
    expect_error(
        |v| v["instances"][2]["transform"] = json!({"scale": 1e-4, "translate": [300, 0, 0]}),
        "instances[2].transform",
        "steps of a 32-bit float there",
    );
    // A mesh is intersected in its own units: those count too.
    expect_error(
        |v| {
            v["meshes"]["block"]["box"] = json!({"min": [0, 0, 0], "max": [3e12, 3e12, 3e12]});
            v["instances"][1]["transform"] = json!({"scale": 1e-10});
        },
        "meshes.block",
        "in its own units",
    );
    // The same ball 1,000 times larger is fine there.
    let mut ok = base();
    ok["instances"][2]["transform"] = json!({"scale": 0.1, "translate": [300, 0, 0]});
    parse(&ok).expect("a ball 0.2 across at x = 300 loads");
    expect_error(
        |v| {
            v["materials"]["glass"] = json!({"type": "translucent", "ior": 1.5,
                "sigma_s": [1e9, 1e9, 1e9], "sigma_a": [0, 0, 0]});
            v["instances"][2]["transform"] = json!({"scale": 10, "translate": [300, 0, 0]});
        },
        "instances[2].transform",
        "mean free path",
    );
}

// ---------------------------------------------------------------- memory

/// A scene whose meshes, each within the per-mesh limit, would not fit in
/// memory together is refused before any mesh is built (here 1,000 knots
/// of 10-15 M triangles: 600 GB to load), naming the largest.
#[test]
fn geometry_beyond_the_memory_available_is_refused_before_building() {
    if nppp_files::available_memory().is_none() {
        return;
    }
    let start = std::time::Instant::now();
    let err = expect_error(
        |v| {
            let meshes = obj_of(v, &["meshes"]);
            for k in 0..1000 {
                meshes.insert(
                    format!("knot{k:04}"),
                    json!({"procedural": {"type": "torus_knot", "segments": 2000 + k, "sides": 2500}}),
                );
            }
        },
        "meshes",
        "of memory available",
    );
    let msg = err.to_string();
    assert!(
        msg.contains("the largest meshes.knot0999 with 14995000"),
        "{msg}"
    );
    assert!(msg.contains("loading them takes about"), "{msg}");
    // Nothing was built: a 20 M-triangle knot alone takes seconds.
    assert!(start.elapsed().as_secs_f64() < 5.0, "{:?}", start.elapsed());
}
