//! The exact camera fixture of ../shared/conformance (copied to tests/conformance).

mod common;
use common::*;

#[test]
fn camera_pixel_grid_fixture() {
    let dir = repo_root().join("tests/conformance");
    let scene = nppp_scene::load_scene(&dir.join("camera_pixel_grid.json")).unwrap();
    let expected: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(dir.join("camera_pixel_grid.expected.json")).unwrap(),
    )
    .unwrap();
    let rs = nppp_render::RenderScene::new(&scene);
    for spp in [1, 7] {
        let img = nppp_render::render(
            &rs,
            &nppp_render::RenderOptions {
                spp,
                max_bounces: 0,
                seed: 3,
                progress: false,
            },
        )
        .0;
        let rects = expected["rects_c0_r0_c1_r1_radiance"].as_array().unwrap();
        for y in 0..img.height {
            for x in 0..img.width {
                let mut want = [0.0f32; 3];
                for r in rects {
                    let v: Vec<f64> = r.as_array().unwrap()[..4]
                        .iter()
                        .map(|v| v.as_f64().unwrap())
                        .collect();
                    if (x as f64) >= v[0]
                        && (x as f64) < v[2]
                        && (y as f64) >= v[1]
                        && (y as f64) < v[3]
                    {
                        let rad = r[4].as_array().unwrap();
                        want = [0, 1, 2].map(|c| rad[c].as_f64().unwrap() as f32);
                    }
                }
                assert_eq!(img.get(x, y), want, "pixel ({x}, {y}) at spp {spp}");
            }
        }
    }
}
