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

/// The EXR file itself is deterministic, not only its pixels: exr's parallel
/// compressor used to write tiles in the order they finished (same pixels,
/// different bytes about every other run).
#[test]
fn exr_files_are_byte_identical() {
    let (w, h) = (300u32, 200u32);
    let mut img = nppp_render::Image::new(w, h);
    for (i, p) in img.pixels.iter_mut().enumerate() {
        let v = (i as f32 * 0.618).fract();
        *p = [v, v * 0.5 + (i % 7) as f32, (i % 13) as f32 * 0.1];
    }
    let dir = std::env::temp_dir().join(format!("nppp-exr-bytes-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let files: Vec<Vec<u8>> = (0..8)
        .map(|k| {
            let path = dir.join(format!("{k}.exr"));
            nppp_render::image_io::write_exr(&img, &path).unwrap();
            // And it still holds the pixels, exactly.
            assert_eq!(nppp_render::image_io::read_exr(&path).unwrap(), img);
            std::fs::read(&path).unwrap()
        })
        .collect();
    std::fs::remove_dir_all(&dir).ok();
    for (k, f) in files.iter().enumerate() {
        assert!(f == &files[0], "write {k} differs from write 0");
    }
}
