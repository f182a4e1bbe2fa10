//! Criterion micro-benchmarks of the renderer's hot paths (see `render.rs`);
//! run with `make bench` or `cargo bench -p nppp-benches`.

use std::path::Path;

/// The default scene, as the benchmarks load it.
pub fn default_scene() -> nppp_scene::Scene {
    nppp_scene::load_scene(
        &Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/scenes/cornell-box.json"),
    )
    .expect("default scene")
}
