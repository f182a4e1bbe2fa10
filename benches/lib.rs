//! Criterion micro-benchmarks of the renderer's hot paths (see `render.rs`);
//! run with `make bench` or `cargo bench -p nppp-benches`.

use glam::{Vec2, Vec3};
use nppp_geom::{SampleRng, sampling::uniform_sphere};
use nppp_render::RenderScene;
use std::path::Path;

/// Rays as (origin, direction).
pub type Rays = Vec<(Vec3, Vec3)>;
/// Shadow rays: (origin, direction, length).
pub type ShadowRays = Vec<(Vec3, Vec3, f32)>;

/// The ray kinds the BVH benchmarks time, on the default scene: `n` primary
/// (coherent camera) rays; from each one's first hit an incoherent ray in a
/// random direction and a shadow ray to the lamp's centre.
pub fn bench_rays(rs: &RenderScene, n: usize) -> (Rays, Rays, ShadowRays) {
    let mut rng = SampleRng::from_seed(1);
    let (w, h) = (rs.camera.width as f32, rs.camera.height as f32);
    let primary: Rays = (0..n)
        .map(|_| {
            (
                rs.camera.origin,
                rs.camera.ray_dir(rng.uniform2() * Vec2::new(w, h)),
            )
        })
        .collect();
    let mut incoherent = Vec::with_capacity(n);
    let mut shadow = Vec::with_capacity(n);
    let light = Vec3::new(278.0, 548.0, 279.5);
    for (o, d) in &primary {
        if let Some(hit) = rs.accel.intersect(*o, *d, f32::INFINITY) {
            let p = *o + *d * (hit.t * 0.999);
            incoherent.push((p, uniform_sphere(rng.uniform2())));
            let to = light - p;
            shadow.push((p, to.normalize(), to.length() * 0.999));
        }
    }
    (primary, incoherent, shadow)
}

/// The default scene, as the benchmarks load it.
pub fn default_scene() -> nppp_scene::Scene {
    nppp_scene::load_scene(
        &Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/scenes/cornell-box.json"),
    )
    .expect("default scene")
}
