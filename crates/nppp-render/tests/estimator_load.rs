//! An estimator file that passes its own checks (magic, version, checksum,
//! mesh and material hashes) but whose bounding sphere does not fit the mesh
//! is refused when the scene loads: it could only have been damaged or
//! forged, and it would put the object in the wrong place.

mod common;
use common::*;
use nppp_estimator::BakedEstimator;
use nppp_render::estimator::{EstimatorMode, Estimators};

#[test]
fn a_sphere_that_does_not_fit_the_mesh_is_refused() {
    let root = repo_root();
    let good = BakedEstimator::load(&root.join("models/cornell-knot.nppp")).unwrap();
    let dir = std::env::temp_dir().join(format!("nppp-sphere-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let scene_text = std::fs::read_to_string(root.join("data/scenes/cornell-box.json")).unwrap();
    let forged_spheres = [
        (
            good.meta.sphere.center + glam::Vec3::splat(3e3),
            good.meta.sphere.radius,
        ),
        (good.meta.sphere.center, good.meta.sphere.radius * 0.5),
        (good.meta.sphere.center, good.meta.sphere.radius * 100.0),
    ];
    for (k, (center, radius)) in forged_spheres.into_iter().enumerate() {
        let mut forged = good.clone();
        forged.meta.sphere.center = center;
        forged.meta.sphere.radius = radius;
        let file = dir.join(format!("forged-{k}.nppp"));
        forged.save(&file).unwrap();
        let json = scene_text.replace("../../models/cornell-knot.nppp", file.to_str().unwrap());
        let scene =
            nppp_scene::parse_scene(&json, &root.join("data/scenes/cornell-box.json")).unwrap();
        let err = match Estimators::load(&scene, EstimatorMode::Neural, 0) {
            Ok(_) => panic!("forged sphere {k} was accepted"),
            Err(e) => e.to_string(),
        };
        assert!(err.contains("instances[6].estimator"), "{err}");
        assert!(err.contains("bounding sphere"), "{err}");
        assert!(err.contains("forged-"), "{err}");
    }
    // The real file loads.
    let scene = nppp_scene::load_scene(&root.join("data/scenes/cornell-box.json")).unwrap();
    assert!(
        Estimators::load(&scene, EstimatorMode::Neural, 0)
            .unwrap()
            .is_some()
    );
    let _ = std::fs::remove_dir_all(&dir);
}
