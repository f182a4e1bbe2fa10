//! Next-event estimation through the committed neural estimator: with
//! `--entry-nee first` the entry's first vertex is found on the real mesh
//! and gets a light sample, and a one-bounce exit's emitter hit is weighted
//! by MIS against it; with `--entry-nee picked` the estimator's vertex head
//! returns the vertex. On the default scene the image mean must stay
//! the network's (the method adds no bias) and the noise must fall well
//! below the thesis' rendering, which finds the lamp only when an exit ray
//! happens to hit it.

mod common;
use common::*;
use nppp_render::estimator::{EntryNee, EstimatorMode, Estimators};
use nppp_render::{Image, RenderOptions, RenderScene};

fn render(mode: EstimatorMode, p: u32, nee: EntryNee, spp: u32, seed: u64) -> Image {
    let mut scene =
        nppp_scene::load_scene(&repo_root().join("data/scenes/cornell-box.json")).unwrap();
    scene.camera.width = 48;
    scene.camera.height = 48;
    let mut rs = if mode == EstimatorMode::Off {
        RenderScene::new(&scene)
    } else {
        RenderScene::for_estimators(&scene)
    };
    rs.estimators = Estimators::load(&scene, mode, p).unwrap();
    if let Some(e) = &mut rs.estimators {
        e.configure(p, nee);
    }
    nppp_render::render(
        &rs,
        &RenderOptions {
            spp,
            max_bounces: 5,
            seed,
            progress: false,
        },
    )
    .0
}

fn sum(img: &Image) -> f64 {
    img.mean().iter().sum()
}

/// PT at 1024 spp: both tests' reference, rendered once.
fn reference() -> &'static Image {
    static REFERENCE: std::sync::OnceLock<Image> = std::sync::OnceLock::new();
    REFERENCE.get_or_init(|| render(EstimatorMode::Off, 0, EntryNee::Off, 1024, 100))
}

/// The network with `nee` at P = `p`, 256 spp: its image mean within 2% of
/// PT's (the network's own bias, about 1% on the default knot, is all that
/// may separate them).
fn assert_mean_near_pt(p: u32, nee: EntryNee) {
    let big = render(EstimatorMode::Neural, p, nee, 256, 2);
    let d = (sum(&big) - sum(reference())).abs() / sum(reference());
    assert!(
        d < 0.02,
        "P={p}, {nee:?}: mean {:.4} vs PT {:.4}",
        sum(&big),
        sum(reference())
    );
}

#[test]
fn first_vertex_nee_keeps_the_mean_and_cuts_the_noise() {
    let err = |img: &Image| nppp_render::metrics::rel_mse(img, reference()).unwrap();
    for p in [0, 2] {
        let off = render(EstimatorMode::Neural, p, EntryNee::Off, 32, 1);
        let first = render(EstimatorMode::Neural, p, EntryNee::FirstVertex, 32, 1);
        let (e_off, e_first) = (err(&off), err(&first));
        assert!(
            e_first < 0.6 * e_off,
            "P={p}: relMSE without {e_off:.4}, with first-vertex NEE {e_first:.4}"
        );
        assert_mean_near_pt(p, EntryNee::FirstVertex);
    }
}

/// Picked-vertex NEE with the committed network (`--entry-nee picked`): its
/// vertex head returns one skipped vertex per entry, the light sample there
/// counts alone and the exit's emitter hit counts 0. It must keep the image
/// mean near PT's and cut the noise below first-vertex NEE's, which lights
/// the first vertex only (the default scene at 64 spp, 256x256, with the
/// committed 32-wide network: relMSE 0.00181 against 0.00328 at P = 1,
/// PT's 0.00188).
#[test]
fn picked_vertex_nee_through_the_network_keeps_the_mean_and_beats_first_vertex() {
    let err = |img: &Image| nppp_render::metrics::rel_mse(img, reference()).unwrap();
    for p in [1, 2] {
        let first = render(EstimatorMode::Neural, p, EntryNee::FirstVertex, 32, 1);
        let picked = render(EstimatorMode::Neural, p, EntryNee::PickedVertex, 32, 1);
        let (e_first, e_picked) = (err(&first), err(&picked));
        // P = 1 skips the second vertex, which first-vertex NEE leaves dark;
        // at P = 2 the skipped vertices carry less light. 48x48, 32 spp:
        // 0.76x and 0.91x with 64-wide decoders, 0.88x at P = 1 with the
        // committed 32-wide ones (at 256x256, 64 spp: 0.55x). At P = 2 the
        // 32-wide ones measure 0.96x-0.98x here, by the noise draws (0.977x
        // since the 32-bit ziggurat): not worse is what this image can tell.
        let bound = if p == 1 { 0.94 } else { 1.0 };
        assert!(
            e_picked < bound * e_first,
            "P={p}: relMSE with first-vertex NEE {e_first:.5}, with picked-vertex NEE {e_picked:.5}"
        );
        assert_mean_near_pt(p, EntryNee::PickedVertex);
    }
}
