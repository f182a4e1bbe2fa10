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

/// Every scene the repository ships (benchmark scenes, unseen variants,
/// translucent checks) parses, and its estimators load and bind to their
/// instances (mesh and material hashes, bounding sphere): a scene file
/// edited by hand or by a script must not reach a user broken.
#[test]
fn every_committed_scene_loads_with_its_estimators() {
    fn scenes(dir: &std::path::Path, out: &mut Vec<std::path::PathBuf>) {
        for e in std::fs::read_dir(dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                scenes(&p, out);
            } else if p.extension().is_some_and(|x| x == "json") {
                out.push(p);
            }
        }
    }
    let mut files = Vec::new();
    scenes(&repo_root().join("data/scenes"), &mut files);
    files.sort();
    assert!(files.len() >= 15, "{files:?}");
    let mut with_estimators = 0;
    for f in &files {
        let scene = nppp_scene::load_scene(f).unwrap_or_else(|e| panic!("{}: {e}", f.display()));
        if scene.instances.iter().any(|i| i.estimator.is_some()) {
            Estimators::load(&scene, EstimatorMode::Neural, 0)
                .unwrap_or_else(|e| panic!("{}: {e}", f.display()));
            with_estimators += 1;
        }
    }
    assert!(with_estimators >= 12, "{with_estimators}");
}

/// One file named through several spellings is one estimator: loaded once
/// and shared (four spellings of the knot's file were loaded four times,
/// 65 MiB for 16, and `auto` decided on each apart).
#[test]
fn one_file_under_several_spellings_is_loaded_once() {
    let root = repo_root();
    let path = root.join("data/scenes/cornell-box.json");
    let mut v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    let insts = v["instances"].as_array_mut().unwrap();
    let knot = insts
        .iter()
        .find(|i| i.get("estimator").is_some())
        .unwrap()
        .clone();
    let spelled = knot["estimator"].as_str().unwrap().to_string();
    for other in [
        spelled.replace("models/", "models/./"),
        format!("../scenes/{spelled}"),
    ] {
        let mut copy = knot.clone();
        copy["estimator"] = other.into();
        insts.push(copy);
    }
    let scene = nppp_scene::parse_scene(&v.to_string(), &path).unwrap();
    let ests = Estimators::load(&scene, EstimatorMode::Neural, 0)
        .unwrap()
        .unwrap();
    assert_eq!(ests.list.len(), 1);
    assert_eq!(ests.per_instance().iter().flatten().count(), 3);
}
