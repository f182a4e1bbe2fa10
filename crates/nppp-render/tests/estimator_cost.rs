//! What a render with estimators pays for, checked where a mistake would
//! only show as a wrong timing: the cost floor (`EstimatorMode::CostFloor`,
//! a timing instrument: the baked masks decide entries exactly as in a
//! neural render and every entry ends its path; a floor that quietly
//! continued its paths would make every bound drawn from it wrong), free
//! exits (`EstimatorMode::FreeExits`: the same entries, every path going on
//! from a free exit, so that its time is a neural render's with decoding
//! free), and the plain layout that rays no estimator can serve must trace.

mod common;
use common::*;
use nppp_render::estimator::{EstimatorMode, Estimators};
use nppp_render::{RenderOptions, RenderScene, RenderStats};

fn cornell_box() -> nppp_scene::Scene {
    nppp_scene::load_scene(&repo_root().join("data/scenes/cornell-box.json")).unwrap()
}

fn render(mode: EstimatorMode, p: u32) -> (nppp_render::Image, RenderStats) {
    let mut scene = cornell_box();
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
    img.mean().iter().sum()
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
    // The network answers its entries in batches (what a decoder backend
    // sees per call, reported by `nppp render`); the floor never decodes.
    assert_eq!(fs.estimators.decoder_batches, 0);
    assert!(ns.estimators.decoder_batches > 0);
    assert!(
        ns.estimators.decoder_batches * 4 <= ns.estimators.entries,
        "{} batches for {} entries: not batched",
        ns.estimators.decoder_batches,
        ns.estimators.entries
    );
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

/// Free exits decide entries with the same mask and continue every path as
/// a neural render does, without decoding: their paths go on (more entries
/// and rays than the floor's, about as many as the network's) from exits
/// straight through the sphere with the file's typical exit throughput.
#[test]
fn free_exits_continue_every_path_without_decoding() {
    let (neural, ns) = render(EstimatorMode::Neural, 0);
    let (floor, fs) = render(EstimatorMode::CostFloor, 0);
    let (free, xs) = render(EstimatorMode::FreeExits, 0);
    assert_eq!(xs.estimators.decoder_batches, 0);
    assert_eq!(xs.estimators.decoder_rows, 0);
    assert!(xs.estimators.entries > fs.estimators.entries);
    assert!(xs.work.rays > fs.work.rays && xs.work.shadow_rays > fs.work.shadow_rays);
    // The same camera rays and the same mask: the first entries are shared,
    // and the continued paths make about as many more as the network's.
    let ratio = xs.estimators.entries as f64 / ns.estimators.entries as f64;
    assert!(
        (0.8..1.25).contains(&ratio),
        "free exits made {ratio} of the network's entries"
    );
    // The free-exits model keeps the file's sampler, the network's own.
    let ests = Estimators::load(&cornell_box(), EstimatorMode::FreeExits, 0)
        .unwrap()
        .unwrap();
    let nppp_render::estimator::EstimatorModel::CostFloor {
        sampler,
        continue_with,
    } = &ests.list[0].model
    else {
        panic!("free exits load as the cost floor's model");
    };
    let typical = continue_with.expect("free exits carry their exit");
    // The knot is diffuse: some light goes on, none is created.
    assert!(typical.throughput.min_element() > 0.0 && typical.throughput.max_element() <= 1.0);
    // And it is the network's typical exit: the geometric mean of 1 + the
    // throughput of the exits it samples for chords that hit, less 1
    // (decoding the data's mean as if it were a standardized feature gave
    // too much throughput and too many bounces).
    let network_typical = {
        let mut rng = nppp_geom::SampleRng::from_seed(17);
        let pairs: Vec<nppp_geom::SpherePair> = (0..20_000)
            .map(|_| {
                nppp_geom::SpherePair([rng.uniform(), rng.uniform(), rng.uniform(), rng.uniform()])
            })
            .filter(|p| sampler.hits(p))
            .take(4096)
            .collect();
        assert!(pairs.len() > 1000, "{} chords hit", pairs.len());
        let mut batch = nppp_estimator::ExitBatch::default();
        let mut repairs = nppp_estimator::DecodeRepairs::default();
        let decoded = sampler.sample_batch(
            &mut batch,
            pairs.len(),
            |k, z, r| {
                sampler.latent(&pairs[k], z);
                r.iter_mut().for_each(|v| *v = rng.normal());
            },
            &mut repairs,
        );
        let n = decoded.exits.len() as f32;
        let log_mean = decoded.exits.iter().fold(glam::Vec3::ZERO, |a, e| {
            a + (glam::Vec3::ONE + e.throughput).map(f32::ln)
        }) / n;
        let log_bounces = decoded
            .exits
            .iter()
            .map(|e| (1.0 + e.bounces as f32).ln())
            .sum::<f32>()
            / n;
        (
            log_mean.map(f32::exp) - glam::Vec3::ONE,
            (log_bounces.exp() - 1.0).round() as u32,
        )
    };
    // Measured: within 1.4%-3.1% per channel (the network's exits are not
    // exactly the data's), one bounce; the wrong decoding was 6%-8% off
    // and made two.
    let rel = (typical.throughput - network_typical.0).abs() / network_typical.0;
    assert!(
        rel.max_element() < 0.05,
        "typical exit throughput {:?}, the network's {:?}",
        typical.throughput,
        network_typical.0
    );
    assert_eq!(typical.bounces, network_typical.1);
    assert_eq!(typical.radiance, glam::Vec3::ZERO);
    // Lit like the network's image, unlike the floor's black knot.
    assert!(mean(&free) > mean(&floor));
    assert!(mean(&free) > 0.5 * mean(&neural));
    assert!(
        free.pixels
            .iter()
            .flatten()
            .all(|v| v.is_finite() && *v >= 0.0)
    );
}

/// Rays that cannot use an estimator trace the plain layout (the knot
/// merged into the world BLAS): with P >= M no ray can, and the render with
/// estimators attached is bit for bit plain path tracing's.
#[test]
fn with_p_at_least_m_every_ray_traces_the_plain_layout() {
    let mut scene = cornell_box();
    scene.camera.width = 32;
    scene.camera.height = 32;
    let opts = RenderOptions {
        spp: 4,
        max_bounces: 5,
        seed: 9,
        progress: false,
    };
    let pt = nppp_render::render(&RenderScene::new(&scene), &opts).0;
    let mut rs = RenderScene::for_estimators(&scene);
    assert!(rs.plain_accel.is_some());
    rs.estimators = Estimators::load(&scene, EstimatorMode::Neural, 5).unwrap();
    let (with, st) = nppp_render::render(&rs, &opts);
    assert_eq!(st.estimators.entries, 0);
    assert!(
        pt.pixels
            .iter()
            .zip(&with.pixels)
            .all(|(a, b)| a.map(f32::to_bits) == b.map(f32::to_bits))
    );
}

/// A ray that starts inside the sphere of the scene's only estimator
/// instance, or does not enter that sphere ahead, meets no estimator: it
/// skips the estimator query and traces the merged layout
/// (`Estimators::cannot_enter`). It must meet what the query would have
/// traced, the same instance and triangle at the same distance (to
/// rounding: the merged BLAS holds world-space triangles, the instance's
/// BLAS object-space ones). With a second estimator instance no ray is let
/// through.
#[test]
fn a_ray_that_cannot_enter_the_sole_estimator_sphere_meets_what_the_estimator_layout_traces() {
    use glam::Vec3;
    use nppp_render::accel::NO_SKIP;
    use nppp_render::estimator::{EstimatorStats, Meet};
    let scene =
        nppp_scene::load_scene(&repo_root().join("data/scenes/cornell-glass.json")).unwrap();
    let mut rs = RenderScene::for_estimators(&scene);
    rs.estimators = Estimators::load(&scene, EstimatorMode::Oracle, 1).unwrap();
    let est = rs.estimators.as_ref().unwrap();
    let inst = est.per_instance().iter().position(Option::is_some).unwrap();
    let sphere = est.list[est.per_instance()[inst].unwrap() as usize].sphere;
    let x = rs.accel.instances[inst];
    let mut rng = nppp_geom::rng::SampleRng::new(7, 0, 0);
    let mut stats = EstimatorStats::default();
    let (mut inside, mut missing, mut entering, mut hits) = (0, 0, 0, 0);
    for _ in 0..8000 {
        let mut u = || 2.0 * rng.uniform() - 1.0;
        // A point of the cube of side 4 around the unit sphere, a direction.
        let p = 2.0 * Vec3::new(u(), u(), u());
        let d = Vec3::new(u(), u(), u());
        if d.length_squared() < 1e-4 || d.length_squared() > 1.0 {
            continue;
        }
        let d = d.normalize();
        // Whether the ray can enter the unit sphere ahead, in f64 (the
        // rotation keeps directions, so object space is world space here
        // up to the transform): starts outside, and its closest approach
        // ahead lies inside.
        let (pd, dd) = (p.as_dvec3(), d.as_dvec3());
        let b = pd.dot(dd);
        let closest = (pd - dd * b).length_squared();
        let starts_inside = pd.length_squared() <= 1.0;
        if (pd.length_squared() - 1.0).abs() < 1e-4 || (closest - 1.0).abs() < 1e-4 {
            continue; // too close to call
        }
        let may_enter = !starts_inside && b < 0.0 && closest < 1.0;
        let o = x.point_to_world(sphere.from_unit_point(p));
        let dw = x.dir_to_world(d);
        let can_skip = est.cannot_enter(&rs.accel, o, dw);
        assert_eq!(can_skip, !may_enter, "from {p} along {d}");
        if !can_skip {
            entering += 1;
            continue;
        }
        if starts_inside {
            inside += 1;
        } else {
            missing += 1;
        }
        let query = est.intersect(&rs.accel, o, dw, NO_SKIP, 1, &mut stats);
        let merged = rs.plain().intersect(o, dw, f32::INFINITY);
        match (query, merged) {
            (Meet::Nothing, None) => {}
            (Meet::Surface(a), Some(b)) => {
                hits += 1;
                assert_eq!((a.instance, a.prim), (b.instance, b.prim), "{o} {dw}");
                assert!((a.t - b.t).abs() <= 1e-4 * a.t.max(1.0), "{} {}", a.t, b.t);
            }
            (q, m) => panic!("from {o} along {dw}: the query met {q:?}, the merged layout {m:?}"),
        }
    }
    assert!(
        inside > 200 && missing > 1000 && entering > 200 && hits > 1000,
        "{inside} rays from inside, {missing} missing the sphere, {entering} entering it, {hits} hits"
    );
    assert_eq!(stats.entries, 0);

    // A second instance of the glass knot with the same estimator.
    let mut two = scene.clone();
    let mut copy = two.instances[inst].clone();
    copy.transform.translation.x += 150.0;
    two.instances.push(copy);
    let mut rs2 = RenderScene::for_estimators(&two);
    rs2.estimators = Estimators::load(&two, EstimatorMode::Oracle, 1).unwrap();
    let est2 = rs2.estimators.as_ref().unwrap();
    let centre = rs2.accel.instances[inst].point_to_world(sphere.center);
    assert!(!est2.cannot_enter(&rs2.accel, centre, Vec3::X));
}
