//! Bad input through the real `nppp` binary: the corpus in `tests/bad_input/`
//! (every error class of docs/scene-format.md, broken OBJ, estimator and
//! training-data files, absurd flags). For each case the tool must exit with
//! status 1 (101 would be a panic), name the file and the key path or reason
//! on stderr, and leave the output folder exactly as it was: no new file, and
//! an existing output file byte for byte intact.
//!
//! The binary fixtures (`*.nppp`, `*.nppd`) are made by the ignored test
//! `regenerate_binary_fixtures` (run it with `--ignored` after a format
//! change); the JSON and OBJ files are hand-made. docs/robustness.md lists
//! every case and what the pipeline does.

use nppp_estimator::{
    BakedEstimator, DatasetHeader, DatasetReader, DatasetWriter, Dense, EstimatorMeta, Exit,
    ExitTransform, Mlp, RayRecord, WriterOptions,
};
use nppp_geom::{BoundingSphere, SpherePair, Vec3};
use std::ffi::OsStr;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

mod common;
use common::nppp;
use std::time::Duration;

fn corpus() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../tests/bad_input")
        .canonicalize()
        .expect("tests/bad_input exists")
}

fn file(name: &str) -> PathBuf {
    corpus().join(name)
}

/// A fresh, empty folder for one case.
fn scratch(name: &str) -> common::Scratch {
    common::scratch("bad-input", name)
}

fn text(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// The names in `dir`, sorted: what a failed run must have left there.
fn names_in(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    names
}

/// Exit status 1 (not a panic's 101, not success) and every needle on stderr.
fn assert_clean_error(what: &str, o: &Output, needles: &[&str]) {
    let err = text(o);
    assert!(!err.contains("panicked"), "{what}: panicked:\n{err}");
    assert_eq!(
        o.status.code(),
        Some(1),
        "{what}: exit status {:?}, stderr:\n{err}",
        o.status
    );
    for n in needles {
        assert!(err.contains(n), "{what}: stderr lacks {n:?}:\n{err}");
    }
}

const PREVIOUS: &[u8] = b"a previous render the user wants to keep";

/// Runs `nppp render` on `scene` with `--out` naming an existing file in a
/// fresh folder; afterwards that file is untouched and nothing else exists.
fn render_fails(case: &str, scene: &Path, extra: &[&str], needles: &[&str]) {
    let dir = scratch(case);
    let out = dir.join("out.exr");
    std::fs::write(&out, PREVIOUS).unwrap();
    let mut args: Vec<&OsStr> = vec![
        "render".as_ref(),
        scene.as_os_str(),
        "--quiet".as_ref(),
        "--out".as_ref(),
        out.as_os_str(),
    ];
    args.extend(extra.iter().map(|s| OsStr::new(*s)));
    let o = nppp(&args);
    assert_clean_error(case, &o, needles);
    assert_eq!(
        std::fs::read(&out).unwrap(),
        PREVIOUS,
        "{case}: the existing output was modified"
    );
    let names = names_in(&dir);
    assert_eq!(names, ["out.exr"], "{case}: files left behind");
    let _ = std::fs::remove_dir_all(&dir);
}

// ---------------------------------------------------------------------------
// Scenes: docs/scene-format.md's error list, case by case
// ---------------------------------------------------------------------------

/// (scene file in tests/bad_input, what stderr must say besides the file's
/// path). Key paths are checked as the contract writes them.
const SCENES: &[(&str, &[&str])] = &[
    // Not JSON at all, or not the JSON we take.
    ("empty.json", &["invalid JSON", "EOF while parsing"]),
    (
        "truncated.json",
        &["truncated.json:9:7: invalid JSON", "EOF while parsing"],
    ),
    (
        "garbage_binary.json",
        &["cannot read the scene file", "UTF-8"],
    ),
    ("garbage_text.json", &["invalid JSON", "expected value"]),
    ("nul_bytes.json", &["invalid JSON", "expected value"]),
    (
        "not_an_object.json",
        &["(top level)", "expected an object, found an array"],
    ),
    (
        "trailing_characters.json",
        &["invalid JSON", "trailing characters"],
    ),
    (
        "duplicate_key.json",
        &["invalid JSON at render", "duplicate key \"render\""],
    ),
    (
        "deep_nesting.json",
        &["invalid JSON at camera", "recursion limit exceeded"],
    ),
    (
        "nan_literal.json",
        &["invalid JSON at camera.fov_y_deg", "expected value"],
    ),
    (
        "infinity_literal.json",
        &[
            "invalid JSON at instances[0].transform.rotate.deg",
            "expected value",
        ],
    ),
    // Non-finite numbers: beyond f64 (a JSON error), beyond f32 (a range error).
    (
        "number_1e999.json",
        &[
            "invalid JSON at materials.white.albedo[1]",
            "number out of range",
        ],
    ),
    (
        "negative_1e999.json",
        &[
            "invalid JSON at instances[0].transform.translate[1]",
            "number out of range",
        ],
    ),
    (
        "not_f32_finite_translate.json",
        &[
            "instances[0].transform.translate[1]",
            "not finite as a 32-bit float",
        ],
    ),
    (
        "not_f32_finite_position.json",
        &["camera.position[2]", "not finite as a 32-bit float"],
    ),
    ("spp_huge_integer.json", &["render.spp", "above 2^64 - 1"]),
    ("spp_not_u32.json", &["render.spp", "at most 4294967295"]),
    (
        "spp_float.json",
        &["render.spp", "must be an integer, found 1.5"],
    ),
    (
        "spp_negative.json",
        &["render.spp", "non-negative integer, found -4"],
    ),
    ("spp_zero.json", &["render.spp", "at least 1"]),
    (
        "seed_string.json",
        &[
            "render.seed",
            "expected a non-negative integer, found a string",
        ],
    ),
    ("seed_1e30.json", &["render.seed", "above 2^64 - 1"]),
    ("width_string.json", &["camera.width", "found a string"]),
    (
        "position_two_numbers.json",
        &["camera.position", "3 numbers, found 2 elements"],
    ),
    ("position_null.json", &["camera.position", "found null"]),
    // Unknown keys.
    (
        "unknown_key_top.json",
        &["lights", "unknown key \"lights\""],
    ),
    (
        "unknown_key_camera.json",
        &["camera.fov", "unknown key \"fov\""],
    ),
    (
        "unknown_key_material.json",
        &["materials.white.roughness", "unknown key"],
    ),
    (
        "unknown_key_instance.json",
        &["instances[1].materal", "unknown key"],
    ),
    (
        "unknown_key_transform.json",
        &["instances[0].transform.rotation", "unknown key"],
    ),
    (
        "unknown_key_rotate.json",
        &["instances[0].transform.rotate.angle", "unknown key"],
    ),
    (
        "unknown_key_render.json",
        &["render.samples", "unknown key"],
    ),
    (
        "unknown_key_mesh.json",
        &["meshes.floor.flip", "unknown key"],
    ),
    (
        "unknown_key_box.json",
        &["meshes.block.box.center", "unknown key"],
    ),
    (
        "unknown_material_type.json",
        &["materials.white.type", "unknown material type \"plastic\""],
    ),
    (
        "unknown_procedural_type.json",
        &[
            "meshes.block.procedural.type",
            "unknown procedural type \"teapot\"",
        ],
    ),
    // Missing required keys.
    ("missing_camera.json", &["camera: required key is missing"]),
    (
        "missing_materials.json",
        &["materials: required key is missing"],
    ),
    ("missing_meshes.json", &["meshes: required key is missing"]),
    (
        "missing_instances.json",
        &["instances: required key is missing"],
    ),
    (
        "missing_camera_position.json",
        &["camera.position: required key is missing"],
    ),
    (
        "missing_camera_look_at.json",
        &["camera.look_at: required key is missing"],
    ),
    (
        "missing_camera_fov_y_deg.json",
        &["camera.fov_y_deg: required key is missing"],
    ),
    (
        "missing_camera_width.json",
        &["camera.width: required key is missing"],
    ),
    (
        "missing_camera_height.json",
        &["camera.height: required key is missing"],
    ),
    (
        "missing_albedo.json",
        &["materials.white.albedo: required key is missing"],
    ),
    (
        "missing_material_type.json",
        &["materials.white.type: required key is missing"],
    ),
    (
        "missing_reflectance.json",
        &["materials.gold.reflectance: required key is missing"],
    ),
    (
        "missing_roughness.json",
        &["materials.gold.roughness: required key is missing"],
    ),
    (
        "missing_ior.json",
        &["materials.glass.ior: required key is missing"],
    ),
    (
        "missing_radiance.json",
        &["materials.lamp.radiance: required key is missing"],
    ),
    (
        "missing_instance_mesh.json",
        &["instances[2].mesh: required key is missing"],
    ),
    (
        "missing_instance_material.json",
        &["instances[1].material: required key is missing"],
    ),
    (
        "missing_mesh_source.json",
        &["meshes.floor", "needs one source key"],
    ),
    (
        "missing_box_max.json",
        &["meshes.block.box.max: required key is missing"],
    ),
    (
        "missing_icosphere_radius.json",
        &["meshes.ball.icosphere.radius: required key is missing"],
    ),
    (
        "missing_rotate_deg.json",
        &["instances[0].transform.rotate.deg: required key is missing"],
    ),
    // Values outside their range.
    (
        "albedo_above_one.json",
        &["materials.white.albedo[1]", "outside [0, 1]"],
    ),
    (
        "albedo_negative.json",
        &["materials.white.albedo[0]", "outside [0, 1]"],
    ),
    (
        "reflectance_above_one.json",
        &["materials.gold.reflectance[2]", "outside [0, 1]"],
    ),
    (
        "roughness_negative.json",
        &["materials.gold.roughness", "outside [0, 1]"],
    ),
    (
        "roughness_above_one.json",
        &["materials.gold.roughness", "outside [0, 1]"],
    ),
    (
        "radiance_negative.json",
        &["materials.lamp.radiance[1]", "must not be negative"],
    ),
    (
        "ior_zero.json",
        &["materials.glass.ior", "must be positive"],
    ),
    (
        "ior_negative.json",
        &["materials.glass.ior", "must be positive"],
    ),
    (
        "box_min_equals_max.json",
        &["meshes.block.box", "not below max", "y axis"],
    ),
    (
        "box_min_above_max.json",
        &["meshes.block.box", "not below max"],
    ),
    (
        "scale_zero.json",
        &["instances[0].transform.scale", "must be positive"],
    ),
    (
        "scale_negative.json",
        &["instances[0].transform.scale", "must be positive"],
    ),
    (
        "scale_underflows_f32.json",
        &[
            "instances[0].transform.scale",
            "must be positive (as a 32-bit float)",
        ],
    ),
    // Geometry that overflows 32-bit floats once placed in the world.
    (
        "world_extent_overflow.json",
        &["instances[2].transform", "mesh \"block\"", "beyond 1e12"],
    ),
    (
        "camera_too_far.json",
        &["camera.position", "farther than 1e12"],
    ),
    (
        "axis_zero.json",
        &["instances[0].transform.rotate.axis", "zero length"],
    ),
    (
        "icosphere_radius_zero.json",
        &["meshes.ball.icosphere.radius", "must be positive"],
    ),
    (
        "icosphere_radius_negative.json",
        &["meshes.ball.icosphere.radius", "must be positive"],
    ),
    // Degenerate cameras.
    (
        "camera_look_at_is_position.json",
        &["camera.look_at", "no viewing direction"],
    ),
    (
        "camera_up_parallel.json",
        &["camera.up", "parallel to the viewing direction"],
    ),
    (
        "camera_up_antiparallel.json",
        &["camera.up", "parallel to the viewing direction"],
    ),
    ("camera_up_zero.json", &["camera.up", "has no direction"]),
    (
        "camera_look_straight_up_default_up.json",
        &["camera.up", "parallel to the viewing direction"],
    ),
    (
        "camera_fov_zero.json",
        &["camera.fov_y_deg", "strictly between 0 and 180"],
    ),
    (
        "camera_fov_180.json",
        &["camera.fov_y_deg", "strictly between 0 and 180"],
    ),
    (
        "camera_fov_negative.json",
        &["camera.fov_y_deg", "strictly between 0 and 180"],
    ),
    ("camera_width_zero.json", &["camera.width", "at least 1"]),
    ("camera_height_zero.json", &["camera.height", "at least 1"]),
    // Unknown names.
    (
        "unknown_mesh_name.json",
        &["instances[0].mesh", "unknown mesh \"flor\"", "\"floor\""],
    ),
    (
        "unknown_material_name.json",
        &[
            "instances[2].material",
            "unknown material \"golden\"",
            "\"gold\"",
        ],
    ),
    (
        "mesh_name_not_string.json",
        &["instances[0].mesh", "expected a string"],
    ),
    // Sizes that cannot be rendered.
    ("image_too_wide.json", &["camera.width", "at most 16384"]),
    ("image_too_tall.json", &["camera.height", "at most 16384"]),
    ("image_width_1e10.json", &["camera.width", "at most 16384"]),
    (
        "icosphere_9_levels.json",
        &["meshes.ball.icosphere.subdivisions", "at most 8"],
    ),
    (
        "icosphere_u32_max_levels.json",
        &["meshes.ball.icosphere.subdivisions", "at most 8"],
    ),
    (
        "menger_level_99.json",
        &["meshes.block.procedural.level", "at most 4"],
    ),
    (
        "knot_segments_u32_max.json",
        &["meshes.block.procedural", "more than the limit"],
    ),
    // Mesh sources.
    (
        "two_mesh_sources.json",
        &["meshes.floor", "exactly one source, found quad and box"],
    ),
    (
        "smooth_on_quad.json",
        &["meshes.floor.smooth", "only to obj meshes"],
    ),
    (
        "quad_collinear.json",
        &["meshes.floor.quad", "degenerate quad"],
    ),
    ("quad_folded.json", &["meshes.floor.quad", "folded"]),
    (
        "quad_three_points.json",
        &["meshes.floor.quad", "exactly 4 points, found 3"],
    ),
    // OBJ files: the scene key, the OBJ file, its line and the reason.
    (
        "obj_index_past_vertices.json",
        &[
            "meshes.block.obj",
            "obj_index_past_vertices.obj:6",
            "vertex index 4 points past the file's 3 vertices",
        ],
    ),
    (
        "obj_index_zero.json",
        &[
            "meshes.block.obj",
            "obj_index_zero.obj:4",
            "index 0 is invalid",
        ],
    ),
    (
        "obj_negative_index_before_first.json",
        &[
            "meshes.block.obj",
            "obj_negative_index_before_first.obj:4",
            "before the first vertex",
        ],
    ),
    (
        "obj_index_huge.json",
        &["meshes.block.obj", "obj_index_huge.obj:4", "too large"],
    ),
    (
        "obj_normal_index_past.json",
        &[
            "meshes.block.obj",
            "obj_normal_index_past.obj:5",
            "normal index 2 points past",
        ],
    ),
    (
        "obj_bad_corner.json",
        &[
            "meshes.block.obj",
            "obj_bad_corner.obj:4",
            "`1/1/1/1` is not one of",
        ],
    ),
    (
        "obj_two_vertex_face.json",
        &[
            "meshes.block.obj",
            "obj_two_vertex_face.obj:4",
            "at least 3 vertices",
        ],
    ),
    (
        "obj_no_faces.json",
        &["meshes.block.obj", "obj_no_faces.obj", "no faces"],
    ),
    (
        "obj_empty.json",
        &["meshes.block.obj", "obj_empty.obj", "no faces"],
    ),
    (
        "obj_zero_area.json",
        &["meshes.block.obj", "obj_zero_area.obj", "zero area"],
    ),
    (
        "obj_vertex_1e39.json",
        &[
            "meshes.block.obj",
            "obj_vertex_1e39.obj:2",
            "not finite as a 32-bit float",
        ],
    ),
    (
        "obj_vertex_nan.json",
        &["meshes.block.obj", "obj_vertex_nan.obj:2", "not finite"],
    ),
    (
        "obj_vertex_two_coordinates.json",
        &[
            "meshes.block.obj",
            "obj_vertex_two_coordinates.obj:2",
            "needs 3 coordinates",
        ],
    ),
    (
        "obj_smooth_without_normals.json",
        &[
            "meshes.block.obj",
            "obj_smooth_without_normals.obj:4",
            "no vertex normals",
        ],
    ),
    (
        "obj_smooth_zero_normal.json",
        &[
            "meshes.block.obj",
            "obj_smooth_zero_normal.obj:5",
            "zero length",
        ],
    ),
    (
        "obj_garbage_binary.json",
        &["meshes.block.obj", "obj_garbage_binary.obj"],
    ),
    (
        "obj_missing_file.json",
        &["meshes.block.obj", "does_not_exist.obj", "cannot read"],
    ),
    (
        "obj_path_is_a_folder.json",
        &["meshes.block.obj", "cannot read"],
    ),
    (
        "obj_path_empty.json",
        &["meshes.block.obj", "the OBJ path is empty"],
    ),
    (
        "est_path_empty.json",
        &["instances[3].estimator", "the estimator path is empty"],
    ),
];

/// Scenes whose estimator file cannot be used: (scene, estimator file that
/// stderr must name with its full path, what else it must say). These
/// errors name the scene file, the instance and the estimator file.
const ESTIMATOR_SCENES: &[(&str, &str, &[&str])] = &[
    (
        "est_missing_file.json",
        "est_does_not_exist.nppp",
        &["No such file"],
    ),
    ("est_truncated.json", "est_truncated.nppp", &["truncated"]),
    (
        "est_wrong_magic.json",
        "est_wrong_magic.nppp",
        &["not an nppp estimator file"],
    ),
    (
        "est_wrong_version.json",
        "est_version_3.nppp",
        &["version 3 not supported"],
    ),
    (
        "est_corrupted.json",
        "est_corrupted.nppp",
        &["checksum mismatch"],
    ),
    ("est_absurd_grid.json", "est_absurd_grid.nppp", &["absurd"]),
    (
        "est_is_a_scene_file.json",
        "ok_tiny.json",
        &["not an nppp estimator file"],
    ),
    (
        "est_wrong_mesh.json",
        "est_valid.nppp",
        &[
            "instances[2]",
            "trained for mesh \"ball\"",
            "uses mesh \"block\"",
        ],
    ),
    (
        "est_wrong_material.json",
        "est_valid.nppp",
        &["instances[3]", "material \"white\"", "material \"gold\""],
    ),
];

/// Valid scenes of the corpus (positive controls), with what a render must print.
const GOOD_SCENES: &[&str] = &["ok_tiny.json", "ok_estimator.json", "ok_radiance_3e38.json"];

#[test]
fn every_scene_error_is_clean_and_names_file_and_key() {
    for (name, needles) in SCENES {
        let path = file(name);
        let shown = path.display().to_string();
        let mut all = vec![shown.as_str()];
        all.extend_from_slice(needles);
        render_fails(name, &path, &[], &all);
    }
    for (name, est, needles) in ESTIMATOR_SCENES {
        let shown = file(est).display().to_string();
        // The scene file and the instance that names the estimator, too.
        let scene = file(name).display().to_string();
        let mut all = vec![shown.as_str(), scene.as_str(), "instances["];
        all.extend_from_slice(needles);
        render_fails(name, &file(name), &[], &all);
    }
}

/// The corpus and the table above stay in step: every file in the folder is
/// used by a case, so a new crasher dropped in cannot be forgotten.
#[test]
fn every_corpus_file_has_a_case() {
    let mut referenced: Vec<String> = SCENES.iter().map(|(n, _)| n.to_string()).collect();
    referenced.extend(ESTIMATOR_SCENES.iter().map(|(n, _, _)| n.to_string()));
    referenced.extend(GOOD_SCENES.iter().map(|s| s.to_string()));
    referenced.extend(ESTIMATORS.iter().map(|(n, _)| n.to_string()));
    referenced.extend(
        DATASETS
            .iter()
            .chain(KNOWN_CRASHERS)
            .map(|(n, _)| n.to_string()),
    );
    referenced.push("README.md".into());
    for entry in std::fs::read_dir(corpus()).unwrap() {
        let name = entry.unwrap().file_name().to_string_lossy().into_owned();
        // OBJ files belong to the scene of the same name.
        let owner = name
            .strip_suffix(".obj")
            .map(|s| format!("{s}.json"))
            .unwrap_or_else(|| name.clone());
        assert!(
            referenced.contains(&owner),
            "tests/bad_input/{name} is used by no case in bad_input.rs"
        );
    }
}

#[test]
fn unreadable_scene_files_are_named() {
    let missing = file("no_such_scene.json");
    render_fails(
        "missing-scene",
        &missing,
        &[],
        &[
            &missing.display().to_string(),
            "cannot read the scene file",
            "No such file",
        ],
    );
    // The reason is said once (it used to be repeated by the error chain).
    let o = nppp([
        "render".as_ref(),
        file("garbage_binary.json").as_os_str(),
        "--out".as_ref(),
        "/nonexistent/out.exr".as_ref(),
    ]);
    assert_clean_error("garbage_binary.json", &o, &["cannot read the scene file"]);
    assert_eq!(text(&o).matches("valid UTF-8").count(), 1, "{}", text(&o));
    let folder = corpus();
    render_fails(
        "scene-is-folder",
        &folder,
        &[],
        &[&folder.display().to_string(), "cannot read the scene file"],
    );
}

// ---------------------------------------------------------------------------
// Flags and output paths
// ---------------------------------------------------------------------------

#[test]
fn absurd_flags_are_rejected_before_rendering() {
    let scene = file("ok_tiny.json");
    // Next-event estimation through the estimator at a picked vertex needs
    // an estimator that returns vertices: refused for the cost floor and
    // free exits (as is any entry NEE: they answer entries with nothing), and
    // for an estimator file without a vertex head (named, with how to
    // rebuild it and the alternatives); an unknown mode is a usage error.
    render_fails(
        "entry-nee-picked-cost-floor",
        &scene,
        &["--estimators", "cost-floor", "--entry-nee", "picked"],
        &[
            "--entry-nee picked needs",
            "the cost floor and free exits",
            "--entry-nee off",
        ],
    );
    render_fails(
        "entry-nee-first-free-exits",
        &scene,
        &["--estimators", "free-exits", "--entry-nee", "first"],
        &[
            "--entry-nee first needs",
            "the cost floor and free exits",
            "--entry-nee off",
        ],
    );
    render_fails(
        "entry-nee-picked-no-vertex-head",
        &file("ok_estimator.json"),
        &["--estimators", "neural", "--entry-nee", "picked"],
        &[
            "the estimator of mesh 'ball' (white) has no vertex head",
            "nppp bake",
            "--entry-nee first",
        ],
    );
    render_fails(
        "auto-with-p",
        &scene,
        &["--estimators", "auto", "--min-bounces", "1"],
        &["--estimators auto chooses P"],
    );
    for margin in ["0.9", "NaN", "inf", "11"] {
        render_fails(
            &format!("auto-margin-{margin}"),
            &scene,
            &["--auto-margin", margin],
            &[&format!("--auto-margin {margin}"), "a factor from 1 to 10"],
        );
    }
    render_fails(
        "auto-margin-not-auto",
        &scene,
        &["--estimators", "neural", "--auto-margin", "1.2"],
        &["--auto-margin is the margin of --estimators auto"],
    );
    let o = nppp([
        "render".as_ref(),
        scene.as_os_str(),
        "--entry-nee".as_ref(),
        "everywhere".as_ref(),
        "--out".as_ref(),
        "/nonexistent/out.exr".as_ref(),
    ]);
    assert_eq!(o.status.code(), Some(2), "{}", text(&o));
    let dir = scratch("threads-0");
    let out = dir.join("out.exr");
    let o = nppp([
        "render".as_ref(),
        scene.as_os_str(),
        "--threads".as_ref(),
        "0".as_ref(),
        "--out".as_ref(),
        out.as_os_str(),
    ]);
    assert_eq!(o.status.code(), Some(2), "--threads 0: {}", text(&o));
    assert!(
        text(&o).contains("--threads") && text(&o).contains("must be at least 1"),
        "{}",
        text(&o)
    );
    assert!(!out.exists());
    // Every count flag's 0 is a usage error naming the flag, as the README
    // says (`render --spp 0` and `gen --rays 0` exited 1).
    let data = file("data_valid.nppd");
    let tail = dir.join("never-written");
    let gen_zero = |flag: &'static str| -> Vec<&OsStr> {
        vec![
            "gen".as_ref(),
            "--scene".as_ref(),
            scene.as_os_str(),
            "--instance".as_ref(),
            "0".as_ref(),
            flag.as_ref(),
            "0".as_ref(),
            "--out".as_ref(),
            tail.as_os_str(),
        ]
    };
    let gens = ["--rays", "--k", "--max-internal-bounces"].map(gen_zero);
    for args in gens.into_iter().chain([
        vec![
            "render".as_ref(),
            scene.as_os_str(),
            "--spp".as_ref(),
            "0".as_ref(),
            "--out".as_ref(),
            out.as_os_str(),
        ],
        vec![
            "bench".as_ref(),
            "--scenes".as_ref(),
            scene.as_os_str(),
            "--seeds".as_ref(),
            "0".as_ref(),
            "--out".as_ref(),
            tail.as_os_str(),
        ],
        vec![
            "bench".as_ref(),
            "--scenes".as_ref(),
            scene.as_os_str(),
            "--spp".as_ref(),
            "4,0".as_ref(),
            "--out".as_ref(),
            tail.as_os_str(),
        ],
        vec![
            "train".as_ref(),
            "--data".as_ref(),
            data.as_os_str(),
            "--out".as_ref(),
            tail.as_os_str(),
            "--threads".as_ref(),
            "0".as_ref(),
        ],
    ]) {
        let what: Vec<String> = args
            .iter()
            .map(|a: &&OsStr| a.to_string_lossy().into_owned())
            .collect();
        let o = nppp(args);
        let err = text(&o);
        assert_eq!(o.status.code(), Some(2), "{what:?}: {err}");
        assert!(
            err.contains("must be at least 1") && !err.contains("panicked"),
            "{what:?}: {err}"
        );
        assert!(!tail.exists() && !out.exists(), "{what:?} wrote something");
    }
    // --threads only where it means something: `info` and `mesh` have no
    // thread pool to size, so the flag is a usage error there (status 2).
    let est = file("est_valid.nppp");
    for args in [
        vec![
            "info".as_ref(),
            "--threads".as_ref(),
            "2".as_ref(),
            est.as_os_str(),
        ],
        vec![
            "mesh".as_ref(),
            "--scene".as_ref(),
            scene.as_os_str(),
            "--mesh".as_ref(),
            "m".as_ref(),
            "--out".as_ref(),
            "m.obj".as_ref(),
            "--threads".as_ref(),
            "2".as_ref(),
        ],
    ] {
        let o = nppp(&args);
        assert_eq!(o.status.code(), Some(2), "{:?}: {}", args, text(&o));
        assert!(
            text(&o).contains("unexpected argument '--threads'"),
            "{}",
            text(&o)
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn unwritable_outputs_fail_cleanly() {
    let scene = file("ok_tiny.json");
    // A file that cannot be created.
    let o = nppp([
        "render".as_ref(),
        scene.as_os_str(),
        "--quiet".as_ref(),
        "--out".as_ref(),
        "/proc/x.exr".as_ref(),
    ]);
    assert_clean_error("--out /proc/x.exr", &o, &["/proc/x.exr"]);
    // A folder in the way of the file, and a file in the way of a folder.
    let dir = scratch("unwritable");
    std::fs::create_dir(dir.join("taken.exr")).unwrap();
    std::fs::write(dir.join("plain"), PREVIOUS).unwrap();
    for out in [dir.join("taken.exr"), dir.join("plain/out.exr")] {
        let o = nppp([
            "render".as_ref(),
            scene.as_os_str(),
            "--quiet".as_ref(),
            "--out".as_ref(),
            out.as_os_str(),
        ]);
        assert_clean_error(
            &out.display().to_string(),
            &o,
            &[&out.display().to_string()],
        );
    }
    assert!(dir.join("taken.exr").is_dir());
    assert_eq!(std::fs::read(dir.join("plain")).unwrap(), PREVIOUS);
    let names = names_in(&dir);
    assert_eq!(names, ["plain", "taken.exr"], "temporary files left behind");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Output paths, their kinds and the reference's size are checked before
/// rendering: each case asks for 10^9 samples per pixel, so a check made
/// after rendering would not return, and stderr carries no render summary.
#[test]
fn outputs_and_reference_are_checked_before_rendering() {
    let scene = file("ok_tiny.json");
    let dir = scratch("before-render");
    let out = dir.join("out.exr");
    std::fs::write(&out, PREVIOUS).unwrap();
    let wrong_size = dir.join("wrong-size.exr");
    let mut img = nppp_render::Image::new(3, 2);
    img.pixels[0] = [1.0, 2.0, 3.0];
    nppp_render::image_io::write_exr(&img, &wrong_size).unwrap();
    let s = |p: &Path| p.display().to_string();
    let cases: Vec<(Vec<String>, Vec<String>)> = vec![
        (
            vec!["--out".into(), s(&dir.join("x.png"))],
            vec!["x.png".into(), "name it *.exr".into()],
        ),
        (
            vec!["--out".into(), s(&dir.join("noext"))],
            vec!["noext".into(), "name it *.exr".into()],
        ),
        (
            vec![
                "--out".into(),
                s(&out),
                "--png".into(),
                s(&dir.join("p.exr")),
            ],
            vec!["p.exr".into(), "name it *.png".into()],
        ),
        (
            vec![
                "--out".into(),
                s(&out),
                "--png".into(),
                "/proc/x.png".into(),
            ],
            vec!["--png".into(), "/proc/x.png".into()],
        ),
        (
            vec!["--out".into(), "/proc/deep/x.exr".into()],
            vec!["--out".into(), "/proc/deep/x.exr".into()],
        ),
        (
            vec![
                "--out".into(),
                s(&out),
                "--reference".into(),
                s(&wrong_size),
            ],
            vec!["wrong-size.exr".into(), "3x2".into()],
        ),
    ];
    for (args, needles) in cases {
        let mut all: Vec<String> = vec![
            "render".into(),
            s(&scene),
            "--quiet".into(),
            "--spp".into(),
            "1000000000".into(),
        ];
        all.extend(args.iter().cloned());
        let o = nppp(&all);
        let needles: Vec<&str> = needles.iter().map(String::as_str).collect();
        let what = args.join(" ");
        assert_clean_error(&what, &o, &needles);
        assert!(!text(&o).contains("samples/s"), "{what}: rendered first");
    }
    assert_eq!(std::fs::read(&out).unwrap(), PREVIOUS);
    let names = names_in(&dir);
    assert_eq!(names, ["out.exr", "wrong-size.exr"], "files left behind");
    let _ = std::fs::remove_dir_all(&dir);
}

/// A render killed half way leaves the previous output in place, whole.
#[test]
fn interrupted_render_keeps_the_previous_output() {
    let dir = scratch("interrupted");
    let out = dir.join("out.exr");
    std::fs::write(&out, PREVIOUS).unwrap();
    let scene = file("ok_tiny.json");
    let mut child = Command::new(env!("CARGO_BIN_EXE_nppp"))
        .args([
            "render".as_ref(),
            scene.as_os_str(),
            "--quiet".as_ref(),
            "--spp".as_ref(),
            "100000000".as_ref(),
            "--out".as_ref(),
            out.as_os_str(),
        ])
        .spawn()
        .unwrap();
    std::thread::sleep(Duration::from_millis(700));
    assert!(
        child.try_wait().unwrap().is_none(),
        "the long render finished already"
    );
    child.kill().unwrap();
    child.wait().unwrap();
    assert_eq!(std::fs::read(&out).unwrap(), PREVIOUS);
    let names = names_in(&dir);
    assert_eq!(names, ["out.exr"]);
    let _ = std::fs::remove_dir_all(&dir);
}

/// A render stopped by SIGTERM while it puts its outputs in place says
/// which ones are new: an output it does not name keeps its old contents
/// (one in four such runs exited 130, "interrupted", with both files
/// already replaced).
#[test]
fn a_render_stopped_while_writing_names_what_it_had_written() {
    let dir = scratch("interrupted-writing");
    let (out, png) = (dir.join("big.exr"), dir.join("big.png"));
    let scene = file("ok_tiny.json");
    let args: Vec<&OsStr> = vec![
        "render".as_ref(),
        scene.as_os_str(),
        "--quiet".as_ref(),
        "--width".as_ref(),
        "1536".as_ref(),
        "--spp".as_ref(),
        "1".as_ref(),
        "--out".as_ref(),
        out.as_os_str(),
        "--png".as_ref(),
        png.as_os_str(),
    ];
    let t0 = std::time::Instant::now();
    let o = nppp(&args);
    assert_eq!(o.status.code(), Some(0), "{}", text(&o));
    let whole = t0.elapsed();
    for k in 0..16u32 {
        std::fs::write(&out, PREVIOUS).unwrap();
        std::fs::write(&png, PREVIOUS).unwrap();
        let child = Command::new(env!("CARGO_BIN_EXE_nppp"))
            .args(&args)
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        // From half the render's time to a little past its end: the
        // signal lands before, during and after the writes.
        std::thread::sleep(whole.mul_f64(0.5 + 0.04 * f64::from(k)));
        let _ = Command::new("kill")
            .args(["-TERM", &child.id().to_string()])
            .status();
        let o = child.wait_with_output().unwrap();
        let err = text(&o);
        assert!(!err.contains("panicked"), "{err}");
        let new = |p: &Path| std::fs::read(p).unwrap() != PREVIOUS;
        match o.status.code() {
            Some(0) => assert!(new(&out) && new(&png), "{err}"),
            Some(130) => {
                assert_eq!(new(&out), err.contains("big.exr"), "EXR: {err}");
                assert_eq!(new(&png), err.contains("big.png"), "PNG: {err}");
            }
            c => panic!("exit {c:?}: {err}"),
        }
        let names = names_in(&dir);
        assert_eq!(names, ["big.exr", "big.png"], "files left behind: {err}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// Positive controls: the valid scenes render, replace the previous output
/// with a finite EXR, and leave no temporary file. The tiny estimator has
/// random decoder weights (its exits are nonsense) and the 3e38 lamp
/// overflows some samples: the image is still finite and the dropped
/// samples are reported.
#[test]
fn valid_scenes_render_finite_images() {
    for (name, flags, must_say) in [
        ("ok_tiny.json", &[][..], ""),
        (
            "ok_estimator.json",
            &["--estimators", "neural"][..],
            "estimators (neural, P = ",
        ),
        // The default, auto, runs its pilot with the same nonsense estimator.
        ("ok_estimator.json", &[][..], "auto: ball/white"),
        (
            "ok_radiance_3e38.json",
            &[][..],
            "non-finite samples dropped",
        ),
    ] {
        let dir = scratch(name);
        let out = dir.join("out.exr");
        std::fs::write(&out, PREVIOUS).unwrap();
        let scene = file(name);
        let mut args: Vec<&OsStr> = vec![
            "render".as_ref(),
            scene.as_os_str(),
            "--quiet".as_ref(),
            "--out".as_ref(),
            out.as_os_str(),
        ];
        args.extend(flags.iter().map(OsStr::new));
        let o = nppp(&args);
        assert_eq!(o.status.code(), Some(0), "{name}: {}", text(&o));
        assert!(
            text(&o).contains(must_say),
            "{name}: stderr lacks {must_say:?}:\n{}",
            text(&o)
        );
        let img = nppp_render::image_io::read_exr(&out).unwrap();
        assert_eq!((img.width, img.height), (8, 8));
        assert!(
            img.pixels
                .iter()
                .flatten()
                .all(|c| c.is_finite() && *c >= 0.0),
            "{name}: non-finite pixel"
        );
        assert!(img.mean().iter().sum::<f64>() > 0.0, "{name}: black image");
        let names = names_in(&dir);
        assert_eq!(names, ["out.exr"], "{name}: files left behind");
        let _ = std::fs::remove_dir_all(&dir);
    }
}

// ---------------------------------------------------------------------------
// Estimator (.nppp) and training-data (.nppd) files
// ---------------------------------------------------------------------------

/// Estimator files for `nppp info`.
const ESTIMATORS: &[(&str, &[&str])] = &[
    ("est_valid.nppp", &[]),
    ("est_empty.nppp", &["truncated", "file is 0 bytes"]),
    (
        "est_truncated.nppp",
        &["truncated: header says", "decoder layer 0"],
    ),
    ("est_truncated_in_header.nppp", &["truncated: header says"]),
    (
        "est_wrong_magic.nppp",
        &["not an nppp estimator file (wrong magic"],
    ),
    (
        "est_garbage.nppp",
        &["not an nppp estimator file (wrong magic"],
    ),
    (
        "est_version_3.nppp",
        &[
            "version 3 not supported (this build reads 1 to 2; `make bake` or `nppp bake` rebuilds it)",
        ],
    ),
    (
        "est_corrupted.nppp",
        &["checksum mismatch (file corrupted)"],
    ),
    (
        "est_absurd_grid.nppp",
        &["latent grid: resolution 65535", "absurd"],
    ),
    (
        "est_huge_claim.nppp",
        &["truncated: header says 2000000000000 latent bytes"],
    ),
    (
        "est_header_length_huge.nppp",
        &["header length 4294967295 is absurd"],
    ),
    (
        "est_trailing_bytes.nppp",
        &["1 bytes after the last section"],
    ),
    ("est_nan_sphere.nppp", &["bounding sphere"]),
    (
        "est_unknown_header_field.nppp",
        &["invalid header", "unknown field"],
    ),
];

#[test]
fn estimator_files_give_clear_errors() {
    for (name, needles) in ESTIMATORS {
        let path = file(name);
        let o = nppp(["info".as_ref(), path.as_os_str()]);
        if needles.is_empty() {
            assert_eq!(o.status.code(), Some(0), "{name}: {}", text(&o));
            assert!(String::from_utf8_lossy(&o.stdout).contains("mesh:      ball"));
            continue;
        }
        let shown = path.display().to_string();
        let mut all = vec![shown.as_str()];
        all.extend_from_slice(needles);
        assert_clean_error(name, &o, &all);
    }
}

/// Training-data files for `nppp train`.
const DATASETS: &[(&str, &[&str])] = &[
    ("data_valid.nppd", &[]),
    ("data_empty.nppd", &["truncated: file is 0 bytes"]),
    ("data_truncated.nppd", &["no chunk index at the end"]),
    ("data_truncated_in_header.nppd", &["truncated: header says"]),
    (
        "data_wrong_magic.nppd",
        &["not an nppp training-data file (wrong magic"],
    ),
    ("data_version_3.nppd", &["version 3 not supported"]),
    (
        "data_corrupted_header.nppd",
        &["invalid header: checksum mismatch"],
    ),
    (
        "data_corrupted_chunk.nppd",
        &["chunk 1 (at byte", "checksum mismatch (file corrupted)"],
    ),
    (
        "data_chunk_claims_4gib.nppd",
        &[
            "chunk 0 (at byte",
            "chunk claims 4294967295 uncompressed bytes",
        ],
    ),
    ("data_k_zero.nppd", &["invalid header: k = 0"]),
];

#[test]
fn dataset_files_give_clear_errors() {
    for (name, needles) in DATASETS.iter().filter(|(_, n)| !n.is_empty()) {
        let path = file(name);
        let dir = scratch(name);
        let model = dir.join("model");
        let o = nppp([
            "train".as_ref(),
            "--data".as_ref(),
            path.as_os_str(),
            "--out".as_ref(),
            model.as_os_str(),
            "--quiet".as_ref(),
        ]);
        let shown = path.display().to_string();
        let mut all = vec![shown.as_str()];
        all.extend_from_slice(needles);
        assert_clean_error(name, &o, &all);
        assert!(!model.exists(), "{name}: a model folder was created");
        let _ = std::fs::remove_dir_all(&dir);
    }
}

/// Files that once crashed the debug build, kept as regression tests, each
/// with the error it must now give (see docs/robustness.md).
const KNOWN_CRASHERS: &[(&str, &[&str])] = &[
    // dataset/mod.rs, DatasetReader::from_source: `e.offset + CHUNK_HEADER_LEN`
    // overflowed for a (checksummed) index entry near u64::MAX (fixed with a
    // checked add).
    (
        "data_index_offset_overflow.nppd",
        &["chunk index entry 1 points at byte 18446744073709551610"],
    ),
];

#[test]
fn known_crashers_give_clear_errors() {
    for (name, needles) in KNOWN_CRASHERS {
        let path = file(name);
        let dir = scratch(name);
        let model = dir.join("model");
        let o = nppp([
            "train".as_ref(),
            "--data".as_ref(),
            path.as_os_str(),
            "--out".as_ref(),
            model.as_os_str(),
            "--quiet".as_ref(),
        ]);
        let shown = path.display().to_string();
        let mut all = vec![shown.as_str()];
        all.extend_from_slice(needles);
        assert_clean_error(name, &o, &all);
        let _ = std::fs::remove_dir_all(&dir);
    }
}

/// The binary fixtures are what their names say: the valid ones load, so
/// the damaged ones fail for their damage and not for a stale format.
#[test]
fn valid_binary_fixtures_load() {
    let est = BakedEstimator::load(&file("est_valid.nppp")).unwrap();
    assert_eq!(est.meta.mesh_name, "ball");
    let mut r = DatasetReader::open(&file("data_valid.nppd")).unwrap();
    assert_eq!(r.read_all().unwrap().len(), 10);
    for (name, _) in ESTIMATORS.iter().chain(DATASETS) {
        let len = std::fs::metadata(file(name)).unwrap().len();
        assert!(len < 100_000, "{name} is {len} bytes: keep fixtures small");
    }
}

// ---------------------------------------------------------------------------
// Fixture generation
// ---------------------------------------------------------------------------

use common::crc32;

fn le32(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(b[at..at + 4].try_into().unwrap())
}

/// The tiny estimator: trained (nominally) for `ball` with material `white`
/// of ok_estimator.json; 2^4-node grids, one decoder layer of random weights.
fn tiny_estimator() -> BakedEstimator {
    let scene = nppp_scene::load_scene(&file("ok_estimator.json")).unwrap();
    let mesh = &scene.meshes[scene.mesh_names.iter().position(|n| n == "ball").unwrap()];
    let material = &scene.materials[scene
        .material_names
        .iter()
        .position(|n| n == "white")
        .unwrap()];
    let mut seed = 12345u32;
    let mut rnd = move || {
        seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
        (seed >> 8) as f32 / (1 << 24) as f32 - 0.5
    };
    let (latent_dim, noise_dim, res) = (2u32, 2u32, 2u32);
    let nodes = (res as usize).pow(4);
    let latent: Vec<f32> = (0..nodes * latent_dim as usize).map(|_| rnd()).collect();
    // Logits > 0: every ray that meets the sphere "hits", so renders use the decoder.
    let mask: Vec<f32> = (0..nodes).map(|_| 4.0 + rnd()).collect();
    let inputs = (latent_dim + noise_dim) as usize;
    let outputs = nppp_estimator::EXIT_FEATURES;
    let decoder = Mlp {
        layers: vec![Dense {
            inputs,
            outputs,
            weight: (0..inputs * outputs).map(|_| rnd()).collect(),
            bias: (0..outputs).map(|_| rnd()).collect(),
        }],
    };
    let meta = EstimatorMeta {
        mesh_name: "ball".into(),
        mesh_hash: nppp_scene::mesh_content_hash(mesh),
        material_name: "white".into(),
        material_hash: nppp_scene::material_content_hash(material),
        sphere: BoundingSphere::around(&mesh.positions, 0.01),
        latent_dim,
        noise_dim,
        max_internal_bounces: 8,
        notes: "tests/bad_input fixture: random weights".into(),
    };
    BakedEstimator::from_f32_grids(
        meta,
        res,
        &latent,
        res,
        &mask,
        8,
        decoder,
        ExitTransform::default(),
    )
    .unwrap()
}

/// Replaces an estimator file's JSON header and fixes its checksum.
fn est_with_header(good: &[u8], edit: impl Fn(&mut serde_json::Value)) -> Vec<u8> {
    let hlen = le32(good, 16) as usize;
    let mut v: serde_json::Value = serde_json::from_slice(&good[20..20 + hlen]).unwrap();
    edit(&mut v);
    let json = serde_json::to_vec(&v).unwrap();
    let mut out = good[..16].to_vec();
    out.extend_from_slice(&(json.len() as u32).to_le_bytes());
    out.extend_from_slice(&json);
    out.extend_from_slice(&good[20 + hlen..]);
    est_fix_crc(&mut out);
    out
}

fn est_fix_crc(b: &mut [u8]) {
    let crc = crc32(&b[16..]);
    b[12..16].copy_from_slice(&crc.to_le_bytes());
}

fn write_estimators() {
    let good = tiny_estimator().to_bytes();
    let hlen = le32(&good, 16) as usize;
    let w = |name: &str, bytes: &[u8]| std::fs::write(file(name), bytes).unwrap();
    w("est_valid.nppp", &good);
    w("est_empty.nppp", &[]);
    w("est_truncated.nppp", &good[..good.len() - 20]);
    w("est_truncated_in_header.nppp", &good[..40]);
    let mut b = good.clone();
    b[..8].copy_from_slice(b"NPPPDAT\0");
    w("est_wrong_magic.nppp", &b);
    let mut seed = 99u32;
    let garbage: Vec<u8> = (0..1024)
        .map(|_| {
            seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (seed >> 24) as u8
        })
        .collect();
    w("est_garbage.nppp", &garbage);
    let mut b = good.clone();
    b[8..12].copy_from_slice(&3u32.to_le_bytes());
    w("est_version_3.nppp", &b);
    let mut b = good.clone();
    let last = b.len() - 3;
    b[last] ^= 0x40;
    w("est_corrupted.nppp", &b);
    w(
        "est_absurd_grid.nppp",
        &est_with_header(&good, |v| v["latent"]["res"] = 65535.into()),
    );
    w(
        "est_huge_claim.nppp",
        &est_with_header(&good, |v| v["latent"]["res"] = 1000.into()),
    );
    let mut b = good.clone();
    b[16..20].copy_from_slice(&u32::MAX.to_le_bytes());
    est_fix_crc(&mut b);
    w("est_header_length_huge.nppp", &b);
    let mut b = good.clone();
    b.push(0);
    est_fix_crc(&mut b);
    w("est_trailing_bytes.nppp", &b);
    let mut b = good.clone();
    let radius = 20 + hlen + 12;
    b[radius..radius + 4].copy_from_slice(&f32::NAN.to_le_bytes());
    est_fix_crc(&mut b);
    w("est_nan_sphere.nppp", &b);
    w(
        "est_unknown_header_field.nppp",
        &est_with_header(&good, |v| v["extra"] = 1.into()),
    );
}

fn tiny_dataset(path: &Path) {
    let header = DatasetHeader {
        mesh_name: "ball".into(),
        mesh_hash: 1,
        material_name: "white".into(),
        material_hash: 2,
        material_json: r#"{"type": "diffuse", "albedo": [0.7, 0.7, 0.7]}"#.into(),
        sphere: BoundingSphere {
            center: Vec3::ZERO,
            radius: 1.0,
        },
        k: 2,
        seed: 0,
        max_internal_bounces: 8,
        shard: None,
        vertices: false,
    };
    let mut wr = DatasetWriter::create_with(
        path,
        header,
        WriterOptions {
            chunk_rays: 4,
            compress: false,
            replace: true,
        },
    )
    .unwrap();
    for i in 0..10u32 {
        let f = i as f32 / 10.0;
        let hit = i % 2 == 0;
        let exit = Exit {
            position: Vec3::new(0.0, 0.0, 1.0),
            direction: Vec3::new(f, 0.0, 1.0).normalize(),
            throughput: Vec3::splat(0.5),
            radiance: Vec3::ZERO,
            bounces: i % 3,
        };
        let exits = if hit { vec![exit; 2] } else { vec![] };
        wr.write(&RayRecord {
            pair: SpherePair([f, 0.5, 1.0 - f, 0.25]),
            hit,
            exits,
            vertices: vec![],
        })
        .unwrap();
    }
    wr.finish().unwrap();
}

fn write_datasets() {
    let valid = file("data_valid.nppd");
    tiny_dataset(&valid);
    let good = std::fs::read(&valid).unwrap();
    let w = |name: &str, bytes: &[u8]| std::fs::write(file(name), bytes).unwrap();
    let hlen = le32(&good, 12) as usize;
    let data_start = 16 + hlen + 4;
    w("data_empty.nppd", &[]);
    w("data_truncated.nppd", &good[..good.len() / 2]);
    w("data_truncated_in_header.nppd", &good[..30]);
    let mut b = good.clone();
    b[..8].copy_from_slice(b"NPPPEST\0");
    w("data_wrong_magic.nppd", &b);
    let mut b = good.clone();
    b[8..12].copy_from_slice(&3u32.to_le_bytes());
    w("data_version_3.nppd", &b);
    let mut b = good.clone();
    b[20] ^= 0x01;
    w("data_corrupted_header.nppd", &b);
    // Chunks are 28-byte headers followed by their payload; chunk 1 starts after chunk 0.
    let chunk0 = data_start;
    let chunk1 = chunk0 + 28 + le32(&good, chunk0 + 16) as usize;
    let mut b = good.clone();
    b[chunk1 + 28 + 5] ^= 0x01;
    w("data_corrupted_chunk.nppd", &b);
    // A chunk claiming 4 GiB uncompressed, its own checksum fixed.
    let mut b = good.clone();
    b[chunk0 + 20..chunk0 + 24].copy_from_slice(&u32::MAX.to_le_bytes());
    let stored = le32(&b, chunk0 + 16) as usize;
    let mut covered = b[chunk0 + 4..chunk0 + 24].to_vec();
    covered.extend_from_slice(&b[chunk0 + 28..chunk0 + 28 + stored]);
    let crc = crc32(&covered);
    b[chunk0 + 24..chunk0 + 28].copy_from_slice(&crc.to_le_bytes());
    w("data_chunk_claims_4gib.nppd", &b);
    // Index entry 1 at an offset near u64::MAX (offset + header overflows), checksum fixed.
    let mut b = good.clone();
    let n = b.len();
    let index_offset = u64::from_le_bytes(b[n - 40..n - 32].try_into().unwrap()) as usize;
    b[index_offset + 16..index_offset + 24].copy_from_slice(&(u64::MAX - 5).to_le_bytes());
    let crc = crc32(&b[index_offset..n - 8]);
    b[n - 8..n - 4].copy_from_slice(&crc.to_le_bytes());
    w("data_index_offset_overflow.nppd", &b);
    // k = 0 in the header, header checksum fixed.
    let mut v: serde_json::Value = serde_json::from_slice(&good[16..16 + hlen]).unwrap();
    v["k"] = 0.into();
    let json = serde_json::to_vec(&v).unwrap();
    let mut b = good[..12].to_vec();
    b.extend_from_slice(&(json.len() as u32).to_le_bytes());
    b.extend_from_slice(&json);
    let crc = crc32(&b[8..]);
    b.extend_from_slice(&crc.to_le_bytes());
    // The rest keeps its offsets only if the header length is unchanged; it is (same digits).
    assert_eq!(json.len(), hlen, "k edit changed the header length");
    b.extend_from_slice(&good[data_start..]);
    w("data_k_zero.nppd", &b);
}

/// Rewrites the binary fixtures. Run after a file-format change:
/// `cargo test -p nppp-cli --test bad_input -- --ignored regenerate`.
#[test]
#[ignore]
fn regenerate_binary_fixtures() {
    write_estimators();
    write_datasets();
}

/// `nppp bench --plot-csv` on files that are not a bench's results.csv.
#[test]
fn plot_csv_errors_name_the_file() {
    let dir = scratch("plot-csv");
    let cases: [(&str, &str, &str); 4] = [
        ("empty.csv", "", "empty file"),
        ("no-columns.csv", "a,b,c\n1,2,3\n", "no column \"scene\""),
        (
            "short-row.csv",
            "scene,config,kind,max_bounces,min_bounces,spp,seed,width,height,seconds,rel_mse\ncb,PT M=5,pt,5,,4\n",
            "malformed row",
        ),
        (
            "nan-row.csv",
            "scene,config,kind,max_bounces,min_bounces,spp,seed,width,height,seconds,rel_mse\ncb,PT M=5,pt,5,,4,1,8,8,fast,0.1\n",
            "malformed row",
        ),
    ];
    for (name, body, needle) in cases {
        let p = dir.join(name);
        std::fs::write(&p, body).unwrap();
        let o = nppp([
            "bench".as_ref(),
            "--plot-csv".as_ref(),
            p.as_os_str(),
            "--out".as_ref(),
            dir.join("plots").as_os_str(),
        ]);
        assert_clean_error(name, &o, &[&p.display().to_string(), needle]);
    }
    assert!(
        !dir.join("plots").exists(),
        "plots folder created for bad input"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

// ---------------------------------------------------------------------------
// Found by the adversarial pass of 2026-11-26
// ---------------------------------------------------------------------------

/// `nppp mesh` exported over the scene's own OBJ (the one exported or
/// another mesh's), replacing the user's file with triangles.
#[test]
fn mesh_export_never_replaces_a_file_the_scene_reads() {
    let dir = scratch("mesh-over-input");
    let user_obj =
        "# the user's model\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nf 1/1 2/1 3/1 4/1\n";
    std::fs::write(dir.join("model.obj"), user_obj).unwrap();
    let scene = std::fs::read_to_string(file("ok_tiny.json"))
        .unwrap()
        .replace(
            r#""block": {"box": {"min": [-0.5, 0, -0.5], "max": [0, 0.5, 0]}}"#,
            r#""block": {"obj": "model.obj"}"#,
        );
    assert!(scene.contains("model.obj"));
    let scene_path = dir.join("scene.json");
    std::fs::write(&scene_path, &scene).unwrap();
    for mesh in ["block", "ball"] {
        let o = nppp([
            "mesh".as_ref(),
            "--scene".as_ref(),
            scene_path.as_os_str(),
            "--mesh".as_ref(),
            mesh.as_ref(),
            "--out".as_ref(),
            dir.join("model.obj").as_os_str(),
        ]);
        assert_clean_error(
            &format!("mesh {mesh} over model.obj"),
            &o,
            &["--out", "model.obj", "a mesh of the scene"],
        );
        assert_eq!(
            std::fs::read_to_string(dir.join("model.obj")).unwrap(),
            user_obj
        );
    }
    assert_eq!(names_in(&dir), ["model.obj", "scene.json"]);
    // An OBJ the scene does not read is kept too, unless --overwrite (it
    // was replaced without a word).
    let other = dir.join("other.obj");
    std::fs::write(&other, user_obj).unwrap();
    let export = |overwrite: bool| {
        let mut a: Vec<&OsStr> = vec![
            "mesh".as_ref(),
            "--scene".as_ref(),
            scene_path.as_os_str(),
            "--mesh".as_ref(),
            "ball".as_ref(),
            "--out".as_ref(),
            other.as_os_str(),
        ];
        if overwrite {
            a.push("--overwrite".as_ref());
        }
        nppp(&a)
    };
    assert_clean_error(
        "mesh over other.obj",
        &export(false),
        &["--out", "other.obj", "exists", "--overwrite"],
    );
    assert_eq!(std::fs::read_to_string(&other).unwrap(), user_obj);
    let o = export(true);
    assert_eq!(o.status.code(), Some(0), "{}", text(&o));
    assert!(
        std::fs::read_to_string(&other)
            .unwrap()
            .contains("triangles")
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// A device (here `/dev/zero`) named as a scene, a mesh, an estimator or a
/// render part was read until memory ran out; a folder as a part was "no
/// such file".
#[cfg(target_os = "linux")]
#[test]
fn special_files_are_refused_as_inputs() {
    let zero = Path::new("/dev/zero");
    if !zero.exists() {
        return;
    }
    render_fails(
        "scene-dev-zero",
        zero,
        &[],
        &["/dev/zero", "not a regular file"],
    );
    let dir = scratch("special-files");
    let tiny = std::fs::read_to_string(file("ok_tiny.json")).unwrap();
    let obj_scene = dir.join("obj.json");
    std::fs::write(
        &obj_scene,
        tiny.replace(
            r#""block": {"box": {"min": [-0.5, 0, -0.5], "max": [0, 0.5, 0]}}"#,
            r#""block": {"obj": "/dev/zero"}"#,
        ),
    )
    .unwrap();
    render_fails(
        "obj-dev-zero",
        &obj_scene,
        &[],
        &["meshes.block", "not a regular file"],
    );
    let est_scene = dir.join("est.json");
    std::fs::write(
        &est_scene,
        tiny.replace(
            r#"{"mesh": "block", "material": "gold"}"#,
            r#"{"mesh": "block", "material": "gold", "estimator": "/dev/zero"}"#,
        ),
    )
    .unwrap();
    render_fails(
        "est-dev-zero",
        &est_scene,
        &[],
        &["instances[2].estimator", "not a regular file"],
    );
    let o = nppp(["info".as_ref(), zero.as_os_str()]);
    assert_clean_error("info /dev/zero", &o, &["/dev/zero", "not a regular file"]);
    for (part, needle) in [(zero, "a device"), (&*dir, "a folder")] {
        let o = nppp([
            "merge".as_ref(),
            part.as_os_str(),
            "--out".as_ref(),
            dir.join("m.exr").as_os_str(),
        ]);
        assert_clean_error(
            "merge of a special file",
            &o,
            &["not a regular file", needle],
        );
    }
    // The output's kind is said before the parts are looked at.
    let o = nppp([
        "merge".as_ref(),
        file("data_valid.nppd").as_os_str(),
        "--out".as_ref(),
        dir.join("m.json").as_os_str(),
    ]);
    assert_clean_error(
        "merge --out m.json",
        &o,
        &["--out", "*.exr (render parts) or *.nppd"],
    );
    // Data parts merged into an EXR: the fix is --out's name, which the
    // error names (it blamed the part, "not an nppp render part").
    let o = nppp([
        "merge".as_ref(),
        file("data_valid.nppd").as_os_str(),
        "--out".as_ref(),
        dir.join("m.exr").as_os_str(),
    ]);
    assert_clean_error(
        "merge of data parts --out m.exr",
        &o,
        &["--out", "training-data parts", "*.nppd"],
    );
    assert_eq!(names_in(&dir), ["est.json", "obj.json"]);
    let _ = std::fs::remove_dir_all(&dir);
}

/// A sample range at the top of u32 wrapped the batch arithmetic and
/// rendered from sample 0 again (billions of samples); a thread count far
/// beyond the cores took minutes to start.
#[test]
fn extreme_sample_ranges_and_thread_counts() {
    let dir = scratch("extreme-ranges");
    let part = dir.join("p.nppr");
    let o = nppp([
        "render".as_ref(),
        file("ok_tiny.json").as_os_str(),
        "--spp".as_ref(),
        "4294967295".as_ref(),
        "--samples".as_ref(),
        "4294967290..4294967295".as_ref(),
        "--out".as_ref(),
        part.as_os_str(),
        "--quiet".as_ref(),
    ]);
    assert_eq!(o.status.code(), Some(0), "{}", text(&o));
    assert!(
        text(&o).contains("samples 4294967290..4294967295 of 4294967295"),
        "{}",
        text(&o)
    );
    let out = dir.join("out.exr");
    let o = nppp([
        "render".as_ref(),
        file("ok_tiny.json").as_os_str(),
        "--threads".as_ref(),
        "100000".as_ref(),
        "--out".as_ref(),
        out.as_os_str(),
    ]);
    assert_clean_error(
        "--threads 100000",
        &o,
        &["--threads 100000: at most", "per core"],
    );
    assert!(!out.exists());
    let _ = std::fs::remove_dir_all(&dir);
}

/// Runs `nppp` with `args`, killing it after `limit`: for inputs that once
/// made it wait forever. `None` when it had to be killed.
fn nppp_within(args: &[&OsStr], limit: Duration) -> Option<Output> {
    use std::process::Stdio;
    let mut child = Command::new(env!("CARGO_BIN_EXE_nppp"))
        .args(args)
        .env("RUST_BACKTRACE", "0")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("cannot run nppp");
    let start = std::time::Instant::now();
    while start.elapsed() < limit {
        if child.try_wait().expect("waiting for nppp").is_some() {
            return Some(child.wait_with_output().expect("reading nppp's output"));
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let _ = child.kill();
    let _ = child.wait();
    None
}

/// A named pipe as an input blocked `nppp` forever in `open` (the
/// regular-file check came after it), and a training log that is a device
/// was read until memory ran out (adversarial pass of 2026-11-27).
#[cfg(target_os = "linux")]
#[test]
fn named_pipes_and_devices_are_refused_without_waiting() {
    let dir = scratch("named-pipes");
    let pipe = dir.join("pipe.json");
    let made = Command::new("mkfifo").arg(&pipe).status();
    if !made.is_ok_and(|s| s.success()) {
        return;
    }
    let out = dir.join("out.exr");
    let data = dir.join("data.nppd");
    let (tiny, model) = (file("ok_tiny.json"), dir.join("model"));
    let cases: Vec<(&str, Vec<&OsStr>)> = vec![
        (
            "render",
            vec![
                "render".as_ref(),
                pipe.as_os_str(),
                "--out".as_ref(),
                out.as_os_str(),
            ],
        ),
        ("info", vec!["info".as_ref(), pipe.as_os_str()]),
        (
            "render --reference",
            vec![
                "render".as_ref(),
                tiny.as_os_str(),
                "--reference".as_ref(),
                pipe.as_os_str(),
                "--out".as_ref(),
                out.as_os_str(),
            ],
        ),
        (
            "train --data",
            vec![
                "train".as_ref(),
                "--data".as_ref(),
                pipe.as_os_str(),
                "--out".as_ref(),
                model.as_os_str(),
            ],
        ),
        (
            "gen --mesh",
            vec![
                "gen".as_ref(),
                "--mesh".as_ref(),
                pipe.as_os_str(),
                "--material".as_ref(),
                "white".as_ref(),
                "--out".as_ref(),
                data.as_os_str(),
            ],
        ),
    ];
    for (what, args) in &cases {
        let o = nppp_within(args, Duration::from_secs(60))
            .unwrap_or_else(|| panic!("{what} on a named pipe did not return"));
        assert_clean_error(what, &o, &["pipe.json", "not a regular file"]);
    }
    let zero = Path::new("/dev/zero");
    if zero.exists() {
        let model = dir.join("zero-model");
        std::fs::create_dir_all(&model).unwrap();
        std::os::unix::fs::symlink(zero, model.join("log.csv")).unwrap();
        let svg = dir.join("log.svg");
        let o = nppp_within(
            &[
                "plot-log".as_ref(),
                model.as_os_str(),
                "--out".as_ref(),
                svg.as_os_str(),
            ],
            Duration::from_secs(60),
        )
        .expect("plot-log of /dev/zero did not return");
        assert_clean_error("plot-log /dev/zero", &o, &["log.csv", "not a regular file"]);
        assert!(!svg.exists());
    }
    assert!(!out.exists());
    let _ = std::fs::remove_dir_all(&dir);
}

/// Counts of 0 that trained nothing (`--steps 0` said "next: nppp bake" and
/// saved no checkpoint), silently meant the default (`--epochs 0`) or scored
/// nothing as a perfect score (`bake --eval-rays 0`) are usage errors naming
/// the flag; so is `--smooth` where there are no vertex normals.
#[test]
fn zero_counts_and_ignored_flags_are_usage_errors_naming_the_flag() {
    let dir = scratch("zero-counts");
    let data = file("data_valid.nppd");
    let model = dir.join("model");
    for (flag, value, needle) in [
        ("--steps", "0", "must be at least 1"),
        ("--stop-after", "0", "must be at least 1"),
        ("--epochs", "0", "must be at least 1"),
        ("--steps-per-epoch", "0", "must be at least 1"),
        ("--batch", "0", "must be at least 1"),
        ("--k", "0", "must be at least 1"),
        ("--mask-batch", "0", "must be at least 1"),
        ("--holdout-every", "1", "must be at least 2"),
        ("--lr", "0", "positive finite"),
        ("--lr", "inf", "positive finite"),
    ] {
        let o = nppp([
            "train".as_ref(),
            "--data".as_ref(),
            data.as_os_str(),
            "--out".as_ref(),
            model.as_os_str(),
            flag.as_ref(),
            value.as_ref(),
        ]);
        common::assert_refused(&format!("train {flag} {value}"), &o, 2, &[flag, needle]);
    }
    for (flag, value, needle) in [
        ("--eval-rays", "0", "must be at least 1"),
        ("--latent-grid", "0", "2 to 256"),
        ("--mask-grid", "1", "2 to 256"),
        ("--latent-grid", "257", "2 to 256"),
    ] {
        let o = nppp([
            "bake".as_ref(),
            "--model".as_ref(),
            model.as_os_str(),
            "--out".as_ref(),
            dir.join("m.nppp").as_os_str(),
            flag.as_ref(),
            value.as_ref(),
        ]);
        common::assert_refused(&format!("bake {flag} {value}"), &o, 2, &[flag, needle]);
    }
    let o = nppp([
        "gen".as_ref(),
        "--mesh".as_ref(),
        "builtin".as_ref(),
        "--material".as_ref(),
        "white".as_ref(),
        "--smooth".as_ref(),
        "--out".as_ref(),
        dir.join("d.nppd").as_os_str(),
    ]);
    assert_clean_error(
        "gen --smooth builtin",
        &o,
        &["--smooth", "no vertex normals"],
    );
    assert!(names_in(&dir).is_empty(), "{:?}", names_in(&dir));
    let _ = std::fs::remove_dir_all(&dir);
}

/// With stderr a closed pipe (`nppp render ... 2>&1 | head -0`), the first
/// note panicked (exit status 101): an error still exits with 1, and a
/// render goes on and writes its image.
#[test]
fn a_closed_stderr_is_not_a_panic() {
    use std::process::Stdio;
    let dir = scratch("closed-stderr");
    let out = dir.join("out.exr");
    let run = |args: &[&OsStr]| {
        let mut child = Command::new(env!("CARGO_BIN_EXE_nppp"))
            .args(args)
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .expect("cannot run nppp");
        // The read end closes before the child has parsed its flags.
        drop(child.stderr.take());
        child.wait().expect("waiting for nppp").code()
    };
    let missing = dir.join("missing.json");
    assert_eq!(run(&["render".as_ref(), missing.as_os_str()]), Some(1));
    let scene = file("ok_tiny.json");
    assert_eq!(
        run(&[
            "render".as_ref(),
            scene.as_os_str(),
            "--out".as_ref(),
            out.as_os_str()
        ]),
        Some(0)
    );
    assert!(out.exists());
    let _ = std::fs::remove_dir_all(&dir);
}

/// A triangle with edges past about 4e9 (the loader accepts coordinates up
/// to 1e15) overflowed its normal's squared length in f32: an emitter quad
/// filling the view rendered black, and an OBJ of one such triangle was
/// refused as "zero area".
#[test]
fn huge_triangles_render() {
    let dir = scratch("huge-triangles");
    let obj = dir.join("huge.obj");
    std::fs::write(
        &obj,
        "v -2.2e9 -2.2e9 1e9\nv 0 2.2e9 1e9\nv 2.2e9 -2.2e9 1e9\nf 1 2 3\n",
    )
    .unwrap();
    for (name, mesh) in [
        (
            "quad",
            r#"{"quad": [[-2.2e9, -2.2e9, 1e9], [-2.2e9, 2.2e9, 1e9], [2.2e9, 2.2e9, 1e9], [2.2e9, -2.2e9, 1e9]]}"#.to_string(),
        ),
        ("obj", format!(r#"{{"obj": {:?}}}"#, obj.to_string_lossy())),
    ] {
        let scene = dir.join(format!("{name}.json"));
        std::fs::write(
            &scene,
            format!(
                r#"{{"camera": {{"position": [0, 0, 0], "look_at": [0, 0, 1], "fov_y_deg": 20, "width": 4, "height": 4}},
 "materials": {{"lamp": {{"type": "emitter", "radiance": [1, 1, 1]}}}},
 "meshes": {{"q": {mesh}}},
 "instances": [{{"mesh": "q", "material": "lamp"}}], "render": {{"spp": 1, "max_bounces": 1}}}}"#
            ),
        )
        .unwrap();
        let out = dir.join(format!("{name}.exr"));
        let o = nppp(["render".as_ref(), scene.as_os_str(), "--out".as_ref(), out.as_os_str()]);
        common::assert_ok(name, &o);
        let img = nppp_render::image_io::read_exr(&out).unwrap();
        assert!(
            img.pixels.iter().all(|p| p.iter().all(|&c| (c - 1.0).abs() < 1e-4)),
            "{name}: {:?}",
            &img.pixels[..4]
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// Found by an adversarial pass (2026-11-27): a render part with the oracle
/// or `off` read every estimator file first (the full render does not);
/// two bench scenes of one file name overwrote each other's outputs; OBJ
/// lines with text after their numbers loaded silently.
#[test]
fn parts_without_estimators_bench_names_and_obj_tails() {
    let dir = scratch("parts-bench-obj");
    let scene = dir.join("s.json");
    std::fs::write(
        &scene,
        r#"{"camera": {"position": [0, 0, -5], "look_at": [0, 0, 0], "fov_y_deg": 40, "width": 8, "height": 8},
 "materials": {"white": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}, "lamp": {"type": "emitter", "radiance": [1, 1, 1]}},
 "meshes": {"ball": {"icosphere": {"center": [0, 0, 0], "radius": 1, "subdivisions": 1}},
            "light": {"quad": [[-3, 3, -3], [3, 3, -3], [3, 3, 3], [-3, 3, 3]]}},
 "instances": [{"mesh": "ball", "material": "white", "estimator": "missing.nppp"},
               {"mesh": "light", "material": "lamp"}],
 "render": {"spp": 2, "max_bounces": 2}}"#,
    )
    .unwrap();
    for mode in ["off", "oracle"] {
        let part = dir.join(format!("{mode}.nppr"));
        let o = nppp([
            "render".as_ref(),
            scene.as_os_str(),
            "--quiet".as_ref(),
            "--estimators".as_ref(),
            mode.as_ref(),
            "--shard".as_ref(),
            "0/2".as_ref(),
            "--out".as_ref(),
            part.as_os_str(),
        ]);
        assert!(o.status.success(), "{mode}: {}", text(&o));
        assert!(part.exists());
    }
    // Neural reads the file, and says which scene and key.
    let o = nppp([
        "render".as_ref(),
        scene.as_os_str(),
        "--quiet".as_ref(),
        "--estimators".as_ref(),
        "neural".as_ref(),
        "--out".as_ref(),
        dir.join("n.exr").as_os_str(),
    ]);
    assert_clean_error("neural, missing estimator", &o, &["instances[0].estimator"]);

    let (a, b) = (dir.join("a"), dir.join("b"));
    for d in [&a, &b] {
        std::fs::create_dir_all(d).unwrap();
        std::fs::copy(&scene, d.join("x.json")).unwrap();
    }
    let scenes = format!(
        "{},{}",
        a.join("x.json").display(),
        b.join("x.json").display()
    );
    let out = dir.join("bench-out");
    let bench = |scenes: &str| {
        nppp([
            "bench".as_ref(),
            "--scenes".as_ref(),
            scenes.as_ref(),
            "--out".as_ref(),
            out.as_os_str(),
        ])
    };
    let o = bench(&scenes);
    assert_clean_error("bench, one name twice", &o, &["have the same file name"]);
    assert!(!out.exists(), "bench created --out before refusing");
    // A scene whose folder is where a report or a plot goes: refused
    // before its renders (they ran, and the report was lost at the end).
    std::fs::copy(&scene, dir.join("results.md.json")).unwrap();
    std::fs::copy(&scene, a.join("x.svg.json")).unwrap();
    let o = bench(&dir.join("results.md.json").display().to_string());
    assert_clean_error(
        "bench, results.md.json",
        &o,
        &["results.md.json", "its report"],
    );
    assert!(!out.exists(), "bench began before refusing");
    let o = bench(&format!(
        "{},{}",
        a.join("x.svg.json").display(),
        a.join("x.json").display()
    ));
    assert_clean_error("bench, x.svg.json", &o, &["x.svg.json", "a scene's plot"]);
    assert!(!out.exists(), "bench began before refusing");
    // A bad scene after a good one is refused before the good one's
    // renders, not after them.
    let bad = dir.join("bad.json");
    std::fs::write(
        &bad,
        std::fs::read_to_string(&scene)
            .unwrap()
            .replacen("{", "{\"bogus\": 1, ", 1),
    )
    .unwrap();
    let o = bench(&format!("{},{}", a.join("x.json").display(), bad.display()));
    assert_clean_error("bench, a bad second scene", &o, &["bad.json", "bogus"]);
    assert!(!out.exists(), "bench began before checking every scene");

    for (name, line) in [
        ("text", "v 0 0 0 abc"),
        ("nan", "v 0 0 0 nan"),
        ("many", "v 0 0 0 1 1 1 1 1"),
        ("vt", "vt abc def"),
    ] {
        let obj = dir.join(format!("{name}.obj"));
        std::fs::write(
            &obj,
            format!("v 0 0 0\nv 1 0 0\nv 0 1 0\n{line}\nf 1 2 3\n"),
        )
        .unwrap();
        let s = dir.join(format!("{name}.json"));
        std::fs::write(
            &s,
            std::fs::read_to_string(&scene)
                .unwrap()
                .replace(
                    r#"{"icosphere": {"center": [0, 0, 0], "radius": 1, "subdivisions": 1}}"#,
                    &format!(r#"{{"obj": "{name}.obj"}}"#),
                )
                .replace(r#", "estimator": "missing.nppp""#, ""),
        )
        .unwrap();
        let o = nppp([
            "render".as_ref(),
            s.as_os_str(),
            "--quiet".as_ref(),
            "--out".as_ref(),
            dir.join("o.exr").as_os_str(),
        ]);
        assert_clean_error(name, &o, &[&format!("{name}.obj:4:")]);
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// bench's cached reference is its own to remake: a damaged image, NaN
/// pixels or an impossible noise floor in it are rendered again with a
/// note, not the end of the run (a truncated one failed the whole bench; a
/// negative noise floor was reported as the reference's noise).
#[test]
fn a_damaged_cached_bench_reference_is_rendered_again() {
    let dir = scratch("bench-cache");
    let out = dir.join("bench");
    let bench = || {
        nppp([
            "bench".as_ref(),
            "--scenes".as_ref(),
            file("ok_tiny.json").as_os_str(),
            "--out".as_ref(),
            out.as_os_str(),
            "--spp".as_ref(),
            "1".as_ref(),
            "--reference-spp".as_ref(),
            "2".as_ref(),
            "--seeds".as_ref(),
            "1".as_ref(),
            "--max-bounces".as_ref(),
            "1".as_ref(),
        ])
    };
    let o = bench();
    assert_eq!(o.status.code(), Some(0), "{}", text(&o));
    let (exr, json) = (
        out.join("ok_tiny/reference.exr"),
        out.join("ok_tiny/reference.json"),
    );
    let o = bench();
    assert!(text(&o).contains("cached"), "{}", text(&o));
    let good = std::fs::read(&exr).unwrap();
    std::fs::write(&exr, &good[..100]).unwrap();
    let o = bench();
    assert_eq!(o.status.code(), Some(0), "{}", text(&o));
    assert!(
        text(&o).contains("is unreadable") && text(&o).contains("re-rendering"),
        "{}",
        text(&o)
    );
    let meta = std::fs::read_to_string(&json).unwrap();
    let floor = meta
        .lines()
        .find(|l| l.contains("noise_floor_rel_mse"))
        .unwrap()
        .to_string();
    std::fs::write(
        &json,
        meta.replace(&floor, "  \"noise_floor_rel_mse\": -1.0"),
    )
    .unwrap();
    let o = bench();
    assert_eq!(o.status.code(), Some(0), "{}", text(&o));
    assert!(text(&o).contains("impossible noise floor"), "{}", text(&o));
    assert!(!std::fs::read_to_string(&json).unwrap().contains("-1.0"));

    // A plot's path holding a link: replaced, the file it named untouched
    // (the plot was drawn through the link).
    let victim = dir.join("victim.txt");
    std::fs::write(&victim, "keep").unwrap();
    let svg = out.join("ok_tiny.svg");
    std::fs::remove_file(&svg).unwrap();
    std::os::unix::fs::symlink(&victim, &svg).unwrap();
    let o = bench();
    assert_eq!(o.status.code(), Some(0), "{}", text(&o));
    assert_eq!(std::fs::read_to_string(&victim).unwrap(), "keep");
    assert!(!std::fs::symlink_metadata(&svg).unwrap().is_symlink());

    // A folder where the reference's preview goes: refused before any
    // render (a run failed there after writing a new reference.exr beside
    // the old settings, and the next measured against the other M's image
    // as "cached, settings match"; the settings are now also written right
    // after the image).
    let png = out.join("ok_tiny/reference.png");
    let exr_before = std::fs::read(&exr).unwrap();
    std::fs::remove_file(&png).unwrap();
    std::fs::create_dir(&png).unwrap();
    let mut m2: Vec<std::ffi::OsString> = [
        "bench",
        "--spp",
        "1",
        "--reference-spp",
        "2",
        "--seeds",
        "1",
        "--max-bounces",
        "2",
    ]
    .map(Into::into)
    .to_vec();
    m2.extend(["--scenes".into(), file("ok_tiny.json").into_os_string()]);
    m2.extend(["--out".into(), out.clone().into_os_string()]);
    assert_clean_error(
        "bench with a folder at reference.png",
        &nppp(&m2),
        &["reference.png", "is a folder"],
    );
    assert_eq!(std::fs::read(&exr).unwrap(), exr_before);
    std::fs::remove_dir(&png).unwrap();
}

/// The thread-count variables rayon reads (its deprecated
/// `RAYON_RS_NUM_CPUS` where `RAYON_NUM_THREADS` is unset) are capped at 64
/// threads a core, with a warning naming the variable: 3000 made a tiny
/// render take 15 s (the renderer's pool and exr's each started them).
#[test]
fn thread_count_variables_are_capped() {
    let dir = scratch("thread-vars");
    let out = dir.join("a.exr");
    for var in ["RAYON_NUM_THREADS", "RAYON_RS_NUM_CPUS"] {
        // Only this one set, whatever the test's own environment holds.
        let o = Command::new(env!("CARGO_BIN_EXE_nppp"))
            .args(["render".as_ref(), file("ok_tiny.json").as_os_str()])
            .args(["--quiet".as_ref(), "--out".as_ref(), out.as_os_str()])
            .env_remove("RAYON_NUM_THREADS")
            .env_remove("RAYON_RS_NUM_CPUS")
            .env(var, "1000000")
            .output()
            .unwrap();
        let err = text(&o);
        assert_eq!(o.status.code(), Some(0), "{var}: {err}");
        assert!(
            err.contains(&format!("warning: {var}=1000000: using")),
            "{var}: {err}"
        );
    }
}
