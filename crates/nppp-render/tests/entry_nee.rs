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
    render_scene(&scene, mode, p, nee, spp, seed)
}

fn render_scene(
    scene: &nppp_scene::Scene,
    mode: EstimatorMode,
    p: u32,
    nee: EntryNee,
    spp: u32,
    seed: u64,
) -> Image {
    let scene = scene.clone();
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

/// The committed knot lit from its side (a lamp beside it on a wall), light
/// the network was never judged under: the picked vertex takes its light
/// sample on the real surface, so the image mean stays PT's. With the
/// vertex pushed along its predicted normal instead (before 2026-11-27)
/// this scene was 22% dark at P = 0 and 4.2% at P = 1 (64x64, 256 spp;
/// here 40x40: -21.5% at P = 0); on the surface, 2%-3% and 1.2%.
#[test]
fn a_knot_lit_from_the_side_keeps_its_mean() {
    let scene = nppp_scene::parse_scene(
        r#"{"camera": {"position": [150, 0, -350], "look_at": [150, 0, 0], "fov_y_deg": 40, "width": 40, "height": 40},
            "materials": {"white": {"type": "diffuse", "albedo": [0.73, 0.73, 0.73]},
                          "knot": {"type": "diffuse", "albedo": [0.8, 0.6, 0.35]},
                          "lamp": {"type": "emitter", "radiance": [200, 160, 90]}},
            "meshes": {"knot": {"procedural": {"type": "torus_knot"}},
                       "wall": {"quad": [[0, -200, -200], [0, 200, -200], [0, 200, 400], [0, -200, 400]]},
                       "lamp": {"quad": [[1, -30, -30], [1, 30, -30], [1, 30, 30], [1, -30, 30]]}},
            "instances": [{"mesh": "wall", "material": "white"},
                          {"mesh": "lamp", "material": "lamp"},
                          {"mesh": "knot", "material": "knot",
                           "transform": {"scale": 90, "rotate": {"axis": [0, 1, 1], "deg": 40}, "translate": [150, 0, 0]},
                           "estimator": "../../models/cornell-knot.nppp"}],
            "render": {"spp": 64, "max_bounces": 5}}"#,
        &repo_root().join("data/scenes/side-lit.json"),
    )
    .unwrap();
    let pt = render_scene(&scene, EstimatorMode::Off, 0, EntryNee::Off, 512, 5);
    for (p, tolerance) in [(0, 0.06), (1, 0.025)] {
        let nn = render_scene(
            &scene,
            EstimatorMode::Neural,
            p,
            EntryNee::PickedVertex,
            256,
            6,
        );
        let d = (sum(&nn) - sum(&pt)) / sum(&pt);
        assert!(
            d.abs() < tolerance,
            "P = {p}: mean {:.4} against PT's {:.4} ({:+.1}%)",
            sum(&nn),
            sum(&pt),
            100.0 * d
        );
    }
}
