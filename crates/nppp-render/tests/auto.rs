//! `--estimators auto` (nppp_render::auto): the pilot's decision is a
//! function of the scene and the seed only (the same at any thread count),
//! it turns off an estimator that loses to path tracing (the default scene's
//! diffuse knot, 0.3x-0.7x at equal error, BENCHMARKS.md), and it rejects
//! a configuration whose image mean is wrong however little noise it has
//! (the tube's first, under-trained estimator at P = 0 renders the tube's
//! inside black).

mod common;
use common::*;
use nppp_render::RenderScene;
use nppp_render::auto::{Decision, EstimatorDecision, PilotOptions, Trial, decide, plan};
use nppp_render::estimator::{EstimatorMode, Estimators};
use nppp_render::film::{PixelSum, film_image};
use nppp_render::{Image, RenderOptions};

/// The scene `name` of data/scenes, `width` pixels wide (0: as it is).
fn load(name: &str, width: u32) -> nppp_scene::Scene {
    let mut scene = nppp_scene::load_scene(&repo_root().join("data/scenes").join(name)).unwrap();
    if width == 0 {
        return scene;
    }
    let h = (scene.camera.height as u64 * width as u64 / scene.camera.width as u64).max(1);
    scene.camera.width = width;
    scene.camera.height = h as u32;
    scene
}

/// data/scenes/tube.json with the tube's first estimator: 5 minutes of
/// training on 200,000 rays, whose exits almost never leave the far mouth
/// (the tube's inside renders black at P = 0) and which loses to PT at
/// every P >= 1 (0.97x PT's efficiency in its pilots at 8 seeds of 8).
/// `models/tube.nppp` replaced it (2026-11-28); it stays here as an
/// estimator `auto` must turn off.
fn undertrained_tube() -> nppp_scene::Scene {
    let mut scene = load("tube.json", 0);
    let tube = scene
        .instances
        .iter_mut()
        .find(|i| i.estimator.is_some())
        .unwrap();
    tube.estimator = Some(
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/tube-undertrained.nppp"),
    );
    scene
}

/// The pilot's decision for `scene`'s estimators with `opts`.
fn decision(scene: &nppp_scene::Scene, opts: &PilotOptions) -> Decision {
    let mut rs = RenderScene::for_estimators(scene);
    let ests = Estimators::load(scene, EstimatorMode::Neural, 0)
        .unwrap()
        .unwrap();
    decide(&mut rs, ests, opts).1
}

/// The default pilot (seed 3) on `threads` threads.
fn pilot(scene: &nppp_scene::Scene, threads: usize) -> Decision {
    let opts = PilotOptions {
        max_bounces: scene.render.max_bounces,
        seed: 3,
        ..Default::default()
    };
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    pool.install(|| decision(scene, &opts))
}

/// The trial of configuration P = `p`.
fn trial_at(d: &EstimatorDecision, p: u32) -> &Trial {
    d.trials
        .iter()
        .find(|t| t.choice.is_some_and(|c| c.min_bounces == p))
        .unwrap_or_else(|| panic!("P = {p} not tried: {d:?}"))
}

#[test]
fn the_decision_is_the_same_at_any_thread_count_and_turns_off_a_losing_estimator() {
    // The under-trained tube, whose estimator loses at every P >= 1. The
    // default scene's knot served here until rays that cannot enter its
    // sphere took the merged layout: with picked NEE it is now within 2-4%
    // of PT at equal error, a tie its pilot puts on either side of the
    // margin.
    let scene = undertrained_tube();
    let one = pilot(&scene, 1);
    let two = pilot(&scene, 2);
    let three = pilot(&scene, 3);
    // More threads than the pilot's image has tiles (64 x 48: twelve): its
    // sample ranges are cut and rendered at once, and merge exactly.
    let sixteen = pilot(&scene, 16);
    let forty = pilot(&scene, 40);
    for d in [&two, &three, &sixteen, &forty] {
        assert_eq!(d.samples, one.samples);
        assert_eq!(d.pt.rel_var, one.pt.rel_var);
        assert_eq!(d.pt.cost, one.pt.cost);
        for (a, b) in d.estimators.iter().zip(&one.estimators) {
            assert_eq!(a.choice, b.choice);
            for (x, y) in a.trials.iter().zip(&b.trials) {
                assert_eq!((x.rel_var, x.cost), (y.rel_var, y.cost));
            }
        }
    }
    let knot = &one.estimators[0];
    assert_eq!(knot.choice, None, "{:?}", knot.trials);
    // Every configuration measured below the margin a choice needs.
    let margin = PilotOptions::default().margin;
    assert!(
        knot.trials.iter().all(|t| t.efficiency < margin),
        "{:?}",
        knot.trials
    );
    // A render after an all-off decision is plain path tracing.
    let mut rs = RenderScene::for_estimators(&scene);
    let ests = Estimators::load(&scene, EstimatorMode::Neural, 0)
        .unwrap()
        .unwrap();
    let (chosen, _) = decide(
        &mut rs,
        ests,
        &PilotOptions {
            max_bounces: 5,
            seed: 3,
            ..Default::default()
        },
    );
    assert!(chosen.is_none());
    assert_eq!(rs.camera.width, 256, "the pilot puts the camera back");
    assert_eq!(rs.camera.height, 192);
}

#[test]
fn a_biased_configuration_is_rejected() {
    // At the scene's own resolution: the pilot (a quarter of it) must see
    // PT's light in the tube above its own noise.
    // P = 0 is not tried by default (PilotOptions::min_p and, the tube
    // being diffuse, min_p_light_sampled): ask for it.
    let scene = undertrained_tube();
    let opts = PilotOptions {
        max_bounces: scene.render.max_bounces,
        seed: 3,
        min_p: 0,
        min_p_light_sampled: 0,
        ..Default::default()
    };
    let d = decision(&scene, &opts);
    let p0 = trial_at(&d.estimators[0], 0);
    assert!(p0.biased, "P = 0 on the tube: {p0:?} against PT {:?}", d.pt);
    assert_eq!(p0.efficiency, 0.0);
    assert_ne!(
        d.estimators[0].choice.map(|c| c.min_bounces),
        Some(0),
        "{:?}",
        d.estimators[0]
    );
}

#[test]
fn a_configuration_that_cannot_win_is_not_measured_twice() {
    // cornell-jade: P = 0 skips the medium walks (a quarter of PT's work
    // per sample) and wins by multiples; P = 2 does nearly PT's work, and
    // no variance the prior allows could make it tie P = 0.
    let scene = load("cornell-jade.json", 128);
    let opts = PilotOptions {
        max_bounces: scene.render.max_bounces,
        seed: 1,
        ..Default::default()
    };
    let d = decision(&scene, &opts);
    let jade = &d.estimators[0];
    assert_eq!(jade.choice.map(|c| c.min_bounces), Some(0), "{jade:?}");
    let p2 = trial_at(jade, 2);
    assert!(p2.skipped && p2.efficiency == 0.0, "{p2:?}");
    // Two PT halves, three probes of one sample per pixel (each the start
    // of its candidate's first half), P = 0's two halves and at most
    // P = 1's: never the eight halves of measuring every candidate.
    let pixels = (d.width * d.height) as u64;
    let per_half = pixels * opts.spp as u64;
    assert!(d.samples <= 6 * per_half + pixels, "{} samples", d.samples);
}

/// The confirmation pass ([`plan`]), forced on (every candidate counts as
/// unsure): its samples are the image's own, so the plan's image is the
/// same bits at any thread count and when rendered in parts over any split
/// of the sample range; and the decision is the one its own measurement
/// makes (the default scene's knot with picked NEE, within a few percent
/// of PT: on at this seed since rays that cannot enter its sphere took the
/// merged layout, off before).
#[test]
fn the_confirmation_pass_renders_the_image_s_own_samples_and_decides_by_them() {
    let scene = load("cornell-box.json", 64);
    let render = RenderOptions {
        spp: 16,
        max_bounces: 5,
        seed: 3,
        progress: false,
    };
    let opts = PilotOptions {
        max_bounces: 5,
        seed: 3,
        spp: 1,
        confirm_spp: 1,
        // No pilot measurement is sure at these bounds: confirm all.
        confirm_sigmas: 1e3,
        ..Default::default()
    };
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let mut rs = RenderScene::for_estimators(&scene);
            let ests = Estimators::load(&scene, EstimatorMode::Neural, 0)
                .unwrap()
                .unwrap();
            let mut p = plan(&mut rs, ests, &opts, &render);
            let (img, stats) = p.render(&mut rs, &render);
            assert_eq!(stats.samples, 64 * 64 * 16, "every sample once");
            // Parts that cut the confirmation's segments and the rest.
            let mut film = vec![PixelSum::default(); 64 * 64];
            for range in [0..3, 3..9, 9..16] {
                let (part, _) = p.render_part(&mut rs, &render, range);
                for (f, x) in film.iter_mut().zip(&part) {
                    f.merge(x);
                }
            }
            (
                p.decision.clone(),
                p.rest_start(),
                img,
                film_image(64, 64, &film),
            )
        })
    };
    let (d, rest, one, parts) = run(1);
    let (d2, _, two, _) = run(2);
    let knot = &d.estimators[0];
    let confirmed = knot.confirmed.as_ref().expect("confirmed");
    assert!(d.confirmation_pt.is_some());
    assert!(
        rest > 0 && rest <= render.spp / 2,
        "confirmation samples 0..{rest}"
    );
    assert_eq!(
        knot.choice.is_some(),
        confirmed.efficiency >= opts.confirm_margin,
        "{confirmed:?}"
    );
    assert!(confirmed.efficiency.is_finite() && confirmed.efficiency > 0.0);
    assert_eq!(
        d2.estimators[0].confirmed.as_ref().unwrap().rel_var,
        confirmed.rel_var
    );
    let bits =
        |img: &Image| -> Vec<u32> { img.pixels.iter().flatten().map(|v| v.to_bits()).collect() };
    assert!(
        bits(&one) == bits(&two),
        "the image depends on the thread count"
    );
    assert!(
        bits(&one) == bits(&parts),
        "render parts differ from the image"
    );
}

#[test]
fn estimators_that_take_light_samples_are_tried_from_p_2() {
    // Their networks' picked vertices and exits are accurate under light
    // like the training scenes', less under other light, most at P = 1,
    // and no pilot can see it (PilotOptions::min_p_light_sampled). Glass
    // takes no light sample and keeps P = 1.
    let tried = |name: &str| -> Vec<u32> {
        let scene = load(name, 64);
        let opts = PilotOptions {
            max_bounces: scene.render.max_bounces,
            seed: 1,
            ..Default::default()
        };
        let d = decision(&scene, &opts);
        d.estimators[0]
            .trials
            .iter()
            .filter_map(|t| t.choice.map(|c| c.min_bounces))
            .collect()
    };
    assert_eq!(tried("cornell-gold.json").first(), Some(&2));
    assert_eq!(tried("cornell-box.json").first(), Some(&2));
    assert_eq!(tried("cornell-glass.json").first(), Some(&1));
}
