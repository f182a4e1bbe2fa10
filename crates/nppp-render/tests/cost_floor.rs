//! The cost floor (`EstimatorMode::CostFloor`) is a timing instrument: the
//! baked masks decide entries exactly as in a neural render, and every entry
//! ends its path. These tests pin down both halves, since a floor that
//! quietly continued its paths would make every bound drawn from it wrong.

mod common;
use common::*;
use nppp_render::estimator::{EstimatorMode, Estimators};
use nppp_render::{RenderOptions, RenderScene, RenderStats};

fn render(mode: EstimatorMode, p: u32) -> (nppp_render::Image, RenderStats) {
    let mut scene =
        nppp_scene::load_scene(&repo_root().join("data/scenes/cornell-box.json")).unwrap();
    scene.camera.width = 48;
    scene.camera.height = 48;
    let mut rs = RenderScene::for_estimators(&scene);
    rs.estimators = Estimators::load(&scene, mode, p).unwrap();
    nppp_render::render(
        &rs,
        &RenderOptions {
            spp: 8,
            max_bounces: 5,
            seed: 3,
            progress: false,
        },
    )
}

fn mean(img: &nppp_render::Image) -> f64 {
    img.mean().iter().map(|&c| c as f64).sum()
}

#[test]
fn every_entry_ends_its_path() {
    let (neural, ns) = render(EstimatorMode::Neural, 0);
    let (floor, fs) = render(EstimatorMode::CostFloor, 0);
    assert!(fs.estimators.entries > 0);
    // Same camera rays and the same mask: the first bounce's entries are
    // shared, and the floor's paths never get to make more.
    assert!(fs.estimators.entries < ns.estimators.entries);
    assert_eq!(fs.estimators.over_max_bounces, 0);
    assert_eq!(fs.estimators.repairs.clamped, 0);
    // Every camera ray that enters the knot's sphere and hits its mask ends
    // there, black: the knot's pixels. The neural render lights most of them
    // (a few stay black at 8 spp: no NEE happens at the skipped vertices).
    let black = |img: &nppp_render::Image| {
        img.pixels
            .iter()
            .filter(|p| p.iter().all(|&c| c == 0.0))
            .count()
    };
    let n = floor.pixels.len();
    assert!(
        black(&floor) > n / 20,
        "{} of {n} floor pixels black",
        black(&floor)
    );
    assert!(
        black(&floor) > 2 * black(&neural),
        "{} floor vs {} neural pixels black",
        black(&floor),
        black(&neural)
    );
    assert!(mean(&floor) < mean(&neural));
    assert!(
        floor
            .pixels
            .iter()
            .flatten()
            .all(|v| v.is_finite() && *v >= 0.0)
    );
}

#[test]
fn floor_uses_the_same_mask_as_the_network() {
    // At P = 4 (M = 5) only the last bounce can enter, so no path continues
    // far past an entry in either render and the mask alone sets the count:
    // the floor must see as many sphere crossings skipped by the mask.
    let (_, ns) = render(EstimatorMode::Neural, 4);
    let (_, fs) = render(EstimatorMode::CostFloor, 4);
    assert!(fs.estimators.entries > 0);
    assert_eq!(fs.estimators.entries, ns.estimators.entries);
    assert_eq!(fs.estimators.mask_skips, ns.estimators.mask_skips);
}
