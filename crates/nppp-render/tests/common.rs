//! Helpers shared by the renderer's integration tests.
#![allow(dead_code)]

use nppp_render::{Image, RenderOptions, RenderScene};
use std::path::{Path, PathBuf};

pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

pub fn scene_from_str(json: &str) -> nppp_scene::Scene {
    nppp_scene::parse_scene(json, &repo_root().join("tests/inline.json"))
        .expect("test scene must parse")
}

pub fn render_str(json: &str, spp: u32, max_bounces: u32, seed: u64) -> Image {
    let scene = scene_from_str(json);
    let rs = RenderScene::new(&scene);
    nppp_render::render(
        &rs,
        &RenderOptions {
            spp,
            max_bounces,
            seed,
            progress: false,
        },
    )
    .0
}

/// A closed cube of inward-facing emitter quads (radiance `le`) around the
/// origin with half-size `h`, and a camera inside looking at `object`.
pub fn furnace_scene(object_material: &str, le: f32, h: f32, object_mesh: &str) -> String {
    let q = |a: [f32; 3], b: [f32; 3], c: [f32; 3], d: [f32; 3]| {
        // Listed in reverse so that (p1-p0)x(p2-p0) points into the cube.
        format!(
            "{{\"quad\": [[{},{},{}],[{},{},{}],[{},{},{}],[{},{},{}]]}}",
            a[0], a[1], a[2], d[0], d[1], d[2], c[0], c[1], c[2], b[0], b[1], b[2]
        )
    };
    // Each quad as written faces out of the cube; `q` reverses it.
    let walls = [
        q([-h, -h, -h], [h, -h, -h], [h, -h, h], [-h, -h, h]), // floor, +y
        q([-h, h, -h], [-h, h, h], [h, h, h], [h, h, -h]),     // ceiling, -y
        q([-h, -h, -h], [-h, -h, h], [-h, h, h], [-h, h, -h]), // x = -h, +x
        q([h, -h, -h], [h, h, -h], [h, h, h], [h, -h, h]),     // x = +h, -x
        q([-h, -h, -h], [-h, h, -h], [h, h, -h], [h, -h, -h]), // z = -h, +z
        q([-h, -h, h], [h, -h, h], [h, h, h], [-h, h, h]),     // z = +h, -z
    ];
    let meshes: Vec<String> = walls
        .iter()
        .enumerate()
        .map(|(i, w)| format!("\"w{i}\": {w}"))
        .collect();
    let insts: Vec<String> = (0..6)
        .map(|i| format!("{{\"mesh\": \"w{i}\", \"material\": \"lamp\"}}"))
        .collect();
    format!(
        r#"{{
  "camera": {{"position": [0, 0, {cz}], "look_at": [0, 0, 0], "fov_y_deg": 60, "width": 24, "height": 24}},
  "materials": {{"lamp": {{"type": "emitter", "radiance": [{le}, {le}, {le}]}}, "obj": {object_material}}},
  "meshes": {{ {meshes}, "object": {object_mesh} }},
  "instances": [ {insts}, {{"mesh": "object", "material": "obj"}} ]
}}"#,
        cz = -0.9 * h,
        meshes = meshes.join(", "),
        insts = insts.join(", ")
    )
}

pub fn mean(img: &Image) -> [f64; 3] {
    img.mean()
}
