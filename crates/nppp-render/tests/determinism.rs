//! Same scene, seed and spp give a bit-identical image at any thread count.

mod common;
use common::*;

#[test]
fn identical_at_one_and_two_threads() {
    let scene = nppp_scene::load_scene(&repo_root().join("data/scenes/cornell-box.json")).unwrap();
    let mut small = scene.clone();
    small.camera.width = 40;
    small.camera.height = 36;
    let rs = nppp_render::RenderScene::new(&small);
    let opts = nppp_render::RenderOptions {
        spp: 4,
        max_bounces: 5,
        seed: 11,
        progress: false,
    };
    let run = |threads| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| nppp_render::render(&rs, &opts).0)
    };
    let a = run(1);
    let b = run(2);
    let c = run(3);
    assert!(
        a.pixels
            .iter()
            .zip(&b.pixels)
            .all(|(x, y)| x.map(f32::to_bits) == y.map(f32::to_bits))
    );
    assert!(
        a.pixels
            .iter()
            .zip(&c.pixels)
            .all(|(x, y)| x.map(f32::to_bits) == y.map(f32::to_bits))
    );
    // A different seed changes it.
    let d = nppp_render::render(&rs, &nppp_render::RenderOptions { seed: 12, ..opts }).0;
    assert_ne!(a, d);
}
