//! Helpers shared by the integration tests: a small valid scene to mutate,
//! and scratch folders for scenes that reference OBJ files.
#![allow(dead_code)] // each test binary uses a different subset

use nppp_scene::{Scene, SceneError, parse_scene};
use serde_json::{Value, json};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

/// A valid scene touching every section, so each error test changes one
/// thing and everything else stays valid.
pub fn base() -> Value {
    json!({
        "camera": {"position": [278, 273, -800], "look_at": [278, 273, 0],
                   "up": [0, 1, 0], "fov_y_deg": 39.3, "width": 64, "height": 48},
        "materials": {
            "white": {"type": "diffuse", "albedo": [0.73, 0.73, 0.73]},
            "gold":  {"type": "conductor", "reflectance": [1.0, 0.78, 0.34], "roughness": 0.2},
            "glass": {"type": "dielectric", "ior": 1.5},
            "lamp":  {"type": "emitter", "radiance": [17, 12, 4]}
        },
        "meshes": {
            "floor": {"quad": [[0,0,0], [0,0,559], [556,0,559], [556,0,0]]},
            "block": {"box": {"min": [100,0,100], "max": [200,150,200]}},
            "ball":  {"icosphere": {"center": [0,0,0], "radius": 1, "subdivisions": 1}}
        },
        "instances": [
            {"mesh": "floor", "material": "white"},
            {"mesh": "block", "material": "gold",
             "transform": {"scale": 2, "rotate": {"axis": [0,1,0], "deg": 30}, "translate": [1, 2, 3]},
             "estimator": "models/block-gold.nppp"},
            {"mesh": "ball", "material": "glass"}
        ],
        "render": {"spp": 16, "max_bounces": 5, "estimator_min_bounces": 1, "seed": 7}
    })
}

pub const FILE: &str = "scenes/test-scene.json";

pub fn parse(v: &Value) -> Result<Scene, SceneError> {
    parse_scene(&v.to_string(), Path::new(FILE))
}

/// Applies `edit` to the base scene and expects an error at exactly `key`,
/// whose message names the file and the key and contains `needle`.
#[track_caller]
pub fn expect_error(edit: impl FnOnce(&mut Value), key: &str, needle: &str) -> SceneError {
    let mut v = base();
    edit(&mut v);
    let err = match parse(&v) {
        Ok(_) => panic!("expected an error at {key}, but the scene loaded"),
        Err(e) => e,
    };
    check(&err, key, needle);
    err
}

#[track_caller]
pub fn check(err: &SceneError, key: &str, needle: &str) {
    let msg = err.to_string();
    assert_eq!(err.key_path(), Some(key), "wrong key path in: {msg}");
    assert!(msg.contains(key), "message lacks key path {key}: {msg}");
    assert!(
        msg.contains(FILE) || msg.contains("scene.json"),
        "message lacks the file: {msg}"
    );
    assert!(msg.contains(needle), "message lacks {needle:?}: {msg}");
}

/// A fresh, empty folder under cargo's per-target scratch space.
pub fn scratch_dir(tag: &str) -> PathBuf {
    static N: AtomicUsize = AtomicUsize::new(0);
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!(
        "nppp-scene-{tag}-{}-{}",
        std::process::id(),
        N.fetch_add(1, Ordering::Relaxed)
    ));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(dir.join("meshes")).expect("create scratch dir");
    dir
}

/// Writes `obj` to `<dir>/meshes/m.obj` and a scene whose mesh `m` is
/// `mesh_value` (e.g. `{"obj": "meshes/m.obj"}`), and loads it.
pub fn load_with_obj(
    tag: &str,
    obj: &str,
    mesh_value: Value,
) -> (Result<Scene, SceneError>, PathBuf) {
    let dir = scratch_dir(tag);
    std::fs::write(dir.join("meshes/m.obj"), obj).expect("write obj");
    let mut v = base();
    v["meshes"]["m"] = mesh_value;
    v["instances"] = json!([{"mesh": "m", "material": "white"}]);
    let scene_path = dir.join("scene.json");
    std::fs::write(&scene_path, v.to_string()).expect("write scene");
    let result = nppp_scene::load_scene(&scene_path);
    // The scene is fully loaded; only the path is still needed, for messages.
    let _ = std::fs::remove_dir_all(&dir);
    (result, dir)
}

pub fn obj_mesh(obj: &str, smooth: bool) -> Result<nppp_scene::Mesh, SceneError> {
    let value = if smooth {
        json!({"obj": "meshes/m.obj", "smooth": true})
    } else {
        json!({"obj": "meshes/m.obj"})
    };
    let (scene, _) = load_with_obj("obj", obj, value);
    scene.map(|s| {
        let i = s.mesh_names.iter().position(|n| n == "m").expect("mesh m");
        s.meshes[i].clone()
    })
}
