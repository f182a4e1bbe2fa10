//! The shared conformance fixture (copied from /work/shared/conformance so
//! a fresh clone can run it) must load, and the loaded camera and quads must
//! be the ones the fixture's expected pixel rectangles were computed from.

use glam::Vec3;
use nppp_scene::{Material, RenderSettings, load_scene};
use std::path::Path;

fn data(name: &str) -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data")
        .join(name)
}

#[test]
fn camera_pixel_grid_loads() {
    let scene = load_scene(&data("camera_pixel_grid.json")).expect("fixture loads");
    let c = &scene.camera;
    assert_eq!(c.position, Vec3::new(1.0, 2.0, 10.0));
    assert_eq!(c.look_at, Vec3::ZERO);
    assert_eq!(c.up, Vec3::Y);
    assert_eq!(c.fov_y_deg, 40.0);
    assert_eq!((c.width, c.height), (160, 96));
    assert_eq!(scene.material_names, ["m0", "m1", "m2"]);
    assert_eq!(scene.mesh_names, ["q0", "q1", "q2"]);
    assert_eq!(
        scene.materials,
        [
            Material::Emitter { radiance: Vec3::X },
            Material::Emitter { radiance: Vec3::Y },
            Material::Emitter { radiance: Vec3::Z },
        ]
    );
    for (i, inst) in scene.instances.iter().enumerate() {
        assert_eq!((inst.mesh, inst.material), (i, i));
        assert_eq!(inst.transform, nppp_scene::Transform::default());
        assert_eq!(inst.estimator, None);
    }
    // `estimator_min_bounces` is absent and takes its default.
    assert_eq!(
        scene.render,
        RenderSettings {
            spp: 64,
            max_bounces: 0,
            seed: 3,
            estimator_min_bounces: RenderSettings::default().estimator_min_bounces,
        }
    );
}

/// Projects each quad's corners with the contract's pinhole camera and
/// checks they land on the expected pixel rectangles, and that each quad's
/// front side (the side an emitter shines from) faces the camera. This ties
/// the loader's quad winding and camera fields to the fixture's numbers.
#[test]
fn camera_pixel_grid_quads_project_onto_expected_rectangles() {
    let scene = load_scene(&data("camera_pixel_grid.json")).expect("fixture loads");
    let expected: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(data("camera_pixel_grid.expected.json")).expect("read expected"),
    )
    .expect("expected is JSON");
    let rects = expected["rects_c0_r0_c1_r1_radiance"]
        .as_array()
        .expect("rects");

    let c = &scene.camera;
    let forward = (c.look_at - c.position).normalize();
    let right = forward.cross(c.up).normalize();
    let up = right.cross(forward);
    let tan_half = (c.fov_y_deg.to_radians() * 0.5).tan();
    let (w, h) = (c.width as f32, c.height as f32);
    let aspect = w / h;

    for (mesh, rect) in scene.meshes.iter().zip(rects) {
        let r: Vec<f32> = (0..4)
            .map(|k| rect[k].as_f64().expect("number") as f32)
            .collect();
        let (mut c0, mut r0, mut c1, mut r1) = (f32::MAX, f32::MAX, f32::MIN, f32::MIN);
        for &p in &mesh.positions {
            let d = p - c.position;
            let z = d.dot(forward);
            let x = d.dot(right) / (z * tan_half * aspect);
            let y = d.dot(up) / (z * tan_half);
            let col = (x + 1.0) * 0.5 * w;
            let row = (1.0 - y) * 0.5 * h;
            c0 = c0.min(col);
            c1 = c1.max(col);
            r0 = r0.min(row);
            r1 = r1.max(row);
        }
        // Pixel rectangles cover every pixel whose centre is inside.
        for (got, want) in [(c0, r[0]), (r0, r[1]), (c1, r[2]), (r1, r[3])] {
            assert!(
                (got - want).abs() < 0.5,
                "projected {got}, expected edge {want}"
            );
        }
        let [a, b, cc] = mesh.triangles[0].map(|i| mesh.positions[i as usize]);
        let normal = (b - a).cross(cc - a);
        assert!(
            normal.dot(c.position - a) > 0.0,
            "emitter quad faces away from the camera"
        );
    }
}
