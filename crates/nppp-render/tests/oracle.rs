//! The estimator integration, checked independently of any network: the
//! oracle estimator answers each entry by tracing the object alone, so where
//! no other geometry enters the object's sphere, PT + oracle must match plain
//! PT within noise, at every P.

mod common;
use common::*;
use nppp_render::estimator::{EntryNee, EstimatorMode, Estimators};
use nppp_render::{RenderOptions, RenderScene};

/// A closed diffuse room lit from above, with `object` floating in the middle (clear of every wall).
fn room(object_mesh: &str, object_material: &str, extra: &str) -> String {
    format!(
        r#"{{
  "camera": {{"position": [0, 0, -4.5], "look_at": [0, 0, 0], "fov_y_deg": 50, "width": 32, "height": 32}},
  "materials": {{"white": {{"type": "diffuse", "albedo": [0.7, 0.7, 0.7]}}, "red": {{"type": "diffuse", "albedo": [0.7, 0.1, 0.1]}},
                 "lamp": {{"type": "emitter", "radiance": [8, 8, 8]}}, "obj": {object_material}}},
  "meshes": {{
    "room": {{"box": {{"min": [-3, -3, -6], "max": [3, 3, 3]}}}},
    "light": {{"quad": [[-0.8, 2.95, -0.8], [0.8, 2.95, -0.8], [0.8, 2.95, 0.8], [-0.8, 2.95, 0.8]]}},
    "object": {object_mesh} {extra}
  }},
  "instances": [
    {{"mesh": "room", "material": "white"}},
    {{"mesh": "light", "material": "lamp"}},
    {{"mesh": "object", "material": "obj", "transform": {{"scale": 1.2, "rotate": {{"axis": [1, 1, 0], "deg": 35}}}}, "estimator": "no-file-needed-for-the-oracle.nppp"}}
  ]
}}"#
    )
}

fn render_mode(
    json: &str,
    mode: EstimatorMode,
    p: u32,
    spp: u32,
    m: u32,
    seed: u64,
) -> (nppp_render::Image, nppp_render::RenderStats) {
    render_mode_nee(json, mode, p, spp, m, seed, EntryNee::Off)
}

fn render_mode_nee(
    json: &str,
    mode: EstimatorMode,
    p: u32,
    spp: u32,
    m: u32,
    seed: u64,
    entry_nee: EntryNee,
) -> (nppp_render::Image, nppp_render::RenderStats) {
    let scene = scene_from_str(json);
    let mut rs = RenderScene::for_estimators(&scene);
    rs.estimators = Estimators::load(&scene, mode, p).unwrap();
    if let Some(e) = &mut rs.estimators {
        e.configure(p, entry_nee);
    }
    nppp_render::render(
        &rs,
        &RenderOptions {
            spp,
            max_bounces: m,
            seed,
            progress: false,
        },
    )
}

fn rel_diff(a: [f64; 3], b: [f64; 3]) -> f64 {
    let s: f64 = a.iter().sum::<f64>();
    let t: f64 = b.iter().sum::<f64>();
    (s - t).abs() / t.max(1e-9)
}

const KNOT: &str = r#"{"procedural": {"type": "torus_knot", "p": 2, "q": 3, "tube_radius": 0.45, "segments": 128, "sides": 12}}"#;

#[test]
fn oracle_matches_path_tracing_at_every_p() {
    let json = room(
        KNOT,
        r#"{"type": "diffuse", "albedo": [0.9, 0.8, 0.6]}"#,
        "",
    );
    let (pt, _) = render_mode(&json, EstimatorMode::Off, 0, 512, 5, 1);
    for p in [0, 1, 2] {
        let (or, st) = render_mode(&json, EstimatorMode::Oracle, p, 512, 5, 2);
        assert!(
            st.estimators.entries > 1000,
            "P={p}: the estimator was barely used ({} entries)",
            st.estimators.entries
        );
        assert_eq!(
            st.estimators.ambiguous, 0,
            "no geometry enters the sphere here"
        );
        let d = rel_diff(or.mean(), pt.mean());
        assert!(
            d < 0.015,
            "P={p}: image mean differs by {:.2}% (oracle {:?} vs PT {:?})",
            d * 100.0,
            or.mean(),
            pt.mean()
        );
        // The object's own pixels (centre of the image), where the estimator matters most.
        let centre = |img: &nppp_render::Image| {
            let mut s = 0.0f64;
            for y in 10..22 {
                for x in 10..22 {
                    s += img.get(x, y).iter().map(|v| *v as f64).sum::<f64>();
                }
            }
            s
        };
        let dc = (centre(&or) - centre(&pt)).abs() / centre(&pt);
        assert!(
            dc < 0.03,
            "P={p}: object region differs by {:.2}%",
            dc * 100.0
        );
    }
}

/// Next-event estimation through the estimator (issue 18): the oracle that
/// samples the lights at one skipped vertex per entry (picked by throughput,
/// or the first), with the exit's emitter hit weighted by MIS against it
/// (or, a network's scheme, the light sample alone and the exit's emitter
/// hit counted 0), still matches plain PT at every P, and its noise falls
/// well below the oracle's without it (which only finds the lamp when an
/// exit ray happens to hit it).
#[test]
fn oracle_with_entry_nee_matches_path_tracing_and_cuts_its_noise() {
    let json = room(
        KNOT,
        r#"{"type": "conductor", "reflectance": [0.95, 0.8, 0.4], "roughness": 0.3}"#,
        "",
    );
    let (reference, _) = render_mode(&json, EstimatorMode::Off, 0, 2048, 5, 7);
    let (pt, _) = render_mode(&json, EstimatorMode::Off, 0, 64, 5, 1);
    let err = |img: &nppp_render::Image| nppp_render::metrics::rel_mse(img, &reference).unwrap();
    for p in [0, 1, 2] {
        let (plain, _) = render_mode_nee(&json, EstimatorMode::Oracle, p, 64, 5, 2, EntryNee::Off);
        let e_plain = err(&plain);
        for nee_mode in [
            EntryNee::PickedVertex,
            EntryNee::FirstVertex,
            EntryNee::PickedVertexLightOnly,
        ] {
            let (nee, st) = render_mode_nee(&json, EstimatorMode::Oracle, p, 64, 5, 2, nee_mode);
            assert!(st.estimators.entries > 1000, "P={p}: barely used");
            let (big, _) = render_mode_nee(&json, EstimatorMode::Oracle, p, 1024, 5, 3, nee_mode);
            let d = rel_diff(big.mean(), reference.mean());
            assert!(
                d < 0.01,
                "P={p}, {nee_mode:?}: image mean differs by {:.2}% (oracle + entry NEE {:?} vs PT {:?})",
                d * 100.0,
                big.mean(),
                reference.mean()
            );
            let (e_pt, e_nee) = (err(&pt), err(&nee));
            // First-vertex NEE leaves the later skipped vertices without a
            // light sample: less of the penalty goes than with a picked vertex.
            let vs_pt = match nee_mode {
                EntryNee::FirstVertex => 2.0,
                _ => 1.5,
            };
            assert!(
                e_nee < 0.6 * e_plain && e_nee < vs_pt * e_pt,
                "P={p}, {nee_mode:?}: relMSE PT {e_pt:.4}, oracle {e_plain:.4}, oracle + entry NEE {e_nee:.4}"
            );
        }
    }
}

#[test]
fn light_seen_only_through_a_glass_object_counts_fully() {
    // The camera sees the lamp only through the glass ball: with P = 0, every
    // camera ray that enters the sphere leaves through the estimator, and the
    // lamp it then hits must count with MIS weight 1.
    let json = room(
        r#"{"icosphere": {"center": [0, 0, 0], "radius": 1, "subdivisions": 4}}"#,
        r#"{"type": "dielectric", "ior": 1.5}"#,
        r#", "backlight": {"quad": [[-0.5, -0.5, 2.9], [-0.5, 0.5, 2.9], [0.5, 0.5, 2.9], [0.5, -0.5, 2.9]]}"#,
    );
    let json = json.replace(
        r#"{"mesh": "light", "material": "lamp"},"#,
        r#"{"mesh": "light", "material": "lamp"}, {"mesh": "backlight", "material": "lamp"},"#,
    );
    let (pt, _) = render_mode(&json, EstimatorMode::Off, 0, 256, 8, 3);
    let (or, st) = render_mode(&json, EstimatorMode::Oracle, 0, 256, 8, 4);
    assert!(st.estimators.entries > 0);
    let d = rel_diff(or.mean(), pt.mean());
    assert!(
        d < 0.02,
        "image mean differs by {:.2}%: oracle {:?} PT {:?}",
        d * 100.0,
        or.mean(),
        pt.mean()
    );
}

#[test]
fn entry_nee_leaves_objects_without_light_samples_alone() {
    // A smooth mirror and smooth glass take no light samples: every entry-NEE
    // scheme must then render them as without it. The light-only scheme
    // counted the exit's emitter hits 0 with no light sample in their place
    // (a mirror ball 34% dark).
    for material in [
        r#"{"type": "conductor", "reflectance": [1, 1, 1], "roughness": 0}"#,
        r#"{"type": "dielectric", "ior": 1.5}"#,
    ] {
        let json = room(
            r#"{"icosphere": {"center": [0, 0, 0], "radius": 1, "subdivisions": 3}}"#,
            material,
            "",
        );
        let (pt, _) = render_mode(&json, EstimatorMode::Off, 0, 128, 6, 3);
        for nee in [
            EntryNee::PickedVertexLightOnly,
            EntryNee::PickedVertex,
            EntryNee::FirstVertex,
        ] {
            let (or, st) = render_mode_nee(&json, EstimatorMode::Oracle, 0, 128, 6, 4, nee);
            assert!(st.estimators.entries > 0);
            let d = rel_diff(or.mean(), pt.mean());
            assert!(
                d < 0.02,
                "{material} {nee:?}: mean differs by {:.2}%",
                d * 100.0
            );
        }
    }
}

#[test]
fn oracle_through_a_translucent_object_matches_path_tracing() {
    // A chromatic, forward-scattering medium in a glass ball, lit from
    // behind and from above: the oracle walks the medium in mesh units (the
    // instance is scaled by 1.2) with its own spectral MIS, and must give
    // PT's image at P = 0 and 1.
    let json = room(
        r#"{"icosphere": {"center": [0, 0, 0], "radius": 1, "subdivisions": 4}}"#,
        r#"{"type": "translucent", "ior": 1.4, "sigma_s": [2, 4, 7], "sigma_a": [0.3, 0.1, 0.2], "g": 0.4}"#,
        r#", "backlight": {"quad": [[-0.5, -0.5, 2.9], [-0.5, 0.5, 2.9], [0.5, 0.5, 2.9], [0.5, -0.5, 2.9]]}"#,
    );
    let json = json.replace(
        r#"{"mesh": "light", "material": "lamp"},"#,
        r#"{"mesh": "light", "material": "lamp"}, {"mesh": "backlight", "material": "lamp"},"#,
    );
    let (pt, _) = render_mode(&json, EstimatorMode::Off, 0, 512, 64, 3);
    for p in [0, 1] {
        let (or, st) = render_mode(&json, EstimatorMode::Oracle, p, 512, 64, 4);
        assert!(st.estimators.entries > 1000, "P={p}: barely used");
        let d = rel_diff(or.mean(), pt.mean());
        assert!(
            d < 0.015,
            "P={p}: image mean differs by {:.2}%: oracle {:?} PT {:?}",
            d * 100.0,
            or.mean(),
            pt.mean()
        );
    }
}

#[test]
fn scene_without_estimators_runs_no_estimator_code() {
    let scene =
        nppp_scene::load_scene(&repo_root().join("tests/conformance/camera_pixel_grid.json"))
            .unwrap();
    assert!(
        Estimators::load(&scene, EstimatorMode::Neural, 0)
            .unwrap()
            .is_none()
    );
    let json = room(
        KNOT,
        r#"{"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}"#,
        "",
    );
    assert!(
        Estimators::load(&scene_from_str(&json), EstimatorMode::Off, 0)
            .unwrap()
            .is_none()
    );
}

#[test]
fn p_at_least_m_never_uses_the_estimator() {
    let json = room(
        KNOT,
        r#"{"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}"#,
        "",
    );
    let (_, st) = render_mode(&json, EstimatorMode::Oracle, 3, 4, 3, 1);
    assert_eq!(st.estimators.entries, 0);
}

/// The knot (thin along y) 0.65 above the floor: its bounding sphere cuts
/// the floor and a panel in front of it while the knot itself touches
/// neither. `camera` replaces the
/// room's camera.
fn room_with_sphere_in_the_floor(camera: &str) -> String {
    // A red panel standing on the floor in front of the knot, inside the
    // sphere: rays that hit it inside the chord must see the panel, not the
    // knot behind it.
    let panel = r#", "panel": {"quad": [[-1.3, -3, -1.3], [1.3, -3, -1.3], [1.3, -1.2, -1.3], [-1.3, -1.2, -1.3]]}"#;
    let json = room(
        KNOT,
        r#"{"type": "diffuse", "albedo": [0.9, 0.8, 0.6]}"#,
        panel,
    );
    let json = json.replace(
        r#""estimator": "no-file-needed-for-the-oracle.nppp"}"#,
        r#""estimator": "no-file-needed-for-the-oracle.nppp"}, {"mesh": "panel", "material": "red"}"#,
    );
    let json = json.replace(
        r#""transform": {"scale": 1.2, "rotate": {"axis": [1, 1, 0], "deg": 35}}"#,
        r#""transform": {"scale": 1.2, "translate": [0, -2.35, 0]}"#,
    );
    let old_camera = r#""camera": {"position": [0, 0, -4.5], "look_at": [0, 0, 0], "fov_y_deg": 50, "width": 32, "height": 32}"#;
    assert!(json.contains(old_camera));
    json.replace(old_camera, camera)
}

/// Where the object's sphere overlaps other geometry, rays that meet that
/// geometry inside the chord are traced for real, and rays starting inside
/// the sphere never use the estimator (a camera inside it included): the
/// oracle is then no longer exact by construction, but the image must still
/// match plain path tracing within noise.
#[test]
fn sphere_cutting_the_floor_and_camera_inside_the_sphere_match_path_tracing() {
    let scene = scene_from_str(&room_with_sphere_in_the_floor(
        r#""camera": {"position": [0, 0, -4.5], "look_at": [0, 0, 0], "fov_y_deg": 50, "width": 32, "height": 32}"#,
    ));
    // The set-up is what the test claims: sphere through the floor y = -3,
    // knot clear of it.
    let knot_y_min = scene.meshes[scene.instances[2].mesh]
        .positions
        .iter()
        .map(|p| p.y * 1.2 - 2.35)
        .fold(f32::MAX, f32::min);
    assert!(
        knot_y_min > -2.95,
        "the knot touches the floor ({knot_y_min})"
    );
    let est = Estimators::load(&scene, EstimatorMode::Oracle, 0)
        .unwrap()
        .unwrap();
    let sphere = est.list[0].sphere;
    let reach = sphere.center.y * 1.2 - 2.35 - sphere.radius * 1.2;
    assert!(reach < -3.5, "the sphere does not cut the floor ({reach})");

    for camera in [
        // Outside, looking at the knot on the floor.
        r#""camera": {"position": [0, 0, -4.5], "look_at": [0, -2.35, 0], "fov_y_deg": 50, "width": 32, "height": 32}"#,
        // Inside the sphere (above the knot), looking away from it.
        r#""camera": {"position": [0, -0.75, 0], "look_at": [0, 2, -3], "fov_y_deg": 70, "width": 32, "height": 32}"#,
        // Inside the sphere, looking down into the knot.
        r#""camera": {"position": [0.1, -0.75, 0.1], "look_at": [0, -3, 0.5], "fov_y_deg": 70, "width": 32, "height": 32}"#,
    ] {
        let json = room_with_sphere_in_the_floor(camera);
        let (pt, _) = render_mode(&json, EstimatorMode::Off, 0, 512, 5, 1);
        let (or, st) = render_mode(&json, EstimatorMode::Oracle, 0, 512, 5, 2);
        assert!(st.estimators.entries > 500, "{camera}: {:?}", st.estimators);
        assert!(st.estimators.ambiguous > 0, "{camera}: {:?}", st.estimators);
        assert_eq!(st.dropped_samples, 0);
        let d = rel_diff(or.mean(), pt.mean());
        assert!(
            d < 0.02,
            "{camera}: image mean differs by {:.2}% (oracle {:?} vs PT {:?})",
            d * 100.0,
            or.mean(),
            pt.mean()
        );
        // And locally: 8 x 8-pixel blocks (32768 samples each, noise about
        // 1%), where a wrong order of events between the floor and the
        // object would show.
        for by in 0..4 {
            for bx in 0..4 {
                let block = |img| region_sum(img, bx * 8..bx * 8 + 8, by * 8..by * 8 + 8) / 64.0;
                let (a, b) = (block(&or), block(&pt));
                assert!(
                    (a - b).abs() <= 0.06 * b + 0.01,
                    "{camera}: block ({bx}, {by}): oracle {a:.4} vs PT {b:.4}"
                );
            }
        }
    }
}

/// The tube lying on a floor, lit by a small lamp beside one mouth (an
/// unseen layout of an independent check, 2026-11-28). An exit ray
/// started at its chord's midpoint; an exit from the mouth just above the
/// floor, rising slightly towards the lamp, started under the floor and
/// was stopped by it: the oracle at P = 1 rendered 2.3% dark (z = -17 over
/// four seeds), where PT and Mitsuba 3 agree. An exit ray whose line
/// meets other geometry inside the sphere near the object now starts at
/// the object's last crossing of the line (`Estimators::exit_origin`).
/// data/meshes/tube.obj lying on a floor at y = -0.25, lit by a small
/// lamp beside one mouth, seen by `camera` (scene-format JSON): the
/// layout of an independent check (2026-11-28), whose floor lies inside
/// the tube's bounding sphere.
fn tube_on_a_floor(
    camera: &str,
    floor_albedo: f32,
    tube_albedo: [f32; 3],
    lamp: [f32; 3],
) -> String {
    format!(
        r#"{{
  "camera": {camera},
  "materials": {{"floor": {{"type": "diffuse", "albedo": [{floor_albedo}, {floor_albedo}, {floor_albedo}]}}, "tube": {{"type": "diffuse", "albedo": {tube_albedo:?}}},
                 "lamp": {{"type": "emitter", "radiance": {lamp:?}}}}},
  "meshes": {{
    "tube": {{"obj": "{}"}},
    "floor": {{"quad": [[-4, -0.25, 4], [4, -0.25, 4], [4, -0.25, -4], [-4, -0.25, -4]]}},
    "lamp": {{"quad": [[-2, -0.1, 0.1], [-2, 0.3, 0.1], [-2, 0.3, 0.5], [-2, -0.1, 0.5]]}}
  }},
  "instances": [
    {{"mesh": "floor", "material": "floor"}},
    {{"mesh": "lamp", "material": "lamp"}},
    {{"mesh": "tube", "material": "tube", "estimator": "no-file-needed-for-the-oracle.nppp"}}
  ]
}}"#,
        repo_root().join("data/meshes/tube.obj").display()
    )
}

/// The sum of all channels of `img` over the pixels `xs` x `ys`.
fn region_sum(img: &nppp_render::Image, xs: std::ops::Range<u32>, ys: std::ops::Range<u32>) -> f64 {
    ys.flat_map(|y| xs.clone().map(move |x| (x, y)))
        .map(|(x, y)| img.get(x, y).iter().map(|v| *v as f64).sum::<f64>())
        .sum()
}

#[test]
fn exits_of_an_object_lying_on_the_floor_are_not_stopped_by_it() {
    let json = tube_on_a_floor(
        r#"{"position": [-3.2, 1.6, -2.4], "look_at": [-0.2, -0.1, 0.4], "fov_y_deg": 45, "width": 48, "height": 36}"#,
        0.8,
        [0.7, 0.6, 0.5],
        [60.0, 55.0, 45.0],
    );
    let (pt, _) = render_mode(&json, EstimatorMode::Off, 1, 1024, 5, 1);
    let (or, st) = render_mode(&json, EstimatorMode::Oracle, 1, 1024, 5, 2);
    assert!(st.estimators.entries > 10_000, "{:?}", st.estimators);
    let d = rel_diff(or.mean(), pt.mean());
    assert!(
        d < 0.008,
        "image mean differs by {:.2}% (oracle {:?} vs PT {:?})",
        d * 100.0,
        or.mean(),
        pt.mean()
    );
}

/// The same tube and floor seen from the other side, at P = 0 and M = 2
/// (the independent check's layout). Exits from the tube's outside falling
/// to the floor started at their chord's midpoint, under the floor, and
/// missed it: the light the floor sends on to the camera's tube points
/// was lost, and a block beside the lit mouth rendered at 0.41 of PT's
/// brightness (z = -30 over two seeds) while the image mean was right
/// within 0.2%. They now start at the tube's last crossing of their line.
#[test]
fn exits_falling_to_the_floor_an_object_lies_on_reach_the_floor() {
    let json = tube_on_a_floor(
        r#"{"position": [1.2, 1.6, -2.6], "look_at": [0, 0, 0.6], "fov_y_deg": 35, "width": 48, "height": 36}"#,
        0.6,
        [0.9, 0.9, 0.9],
        [60.0, 50.0, 30.0],
    );
    let (pt, _) = render_mode(&json, EstimatorMode::Off, 0, 512, 2, 1);
    let (or, st) = render_mode(&json, EstimatorMode::Oracle, 0, 512, 2, 2);
    assert!(st.estimators.entries > 10_000, "{:?}", st.estimators);
    // The 8 x 8 block of the full-size image, at half its size.
    let block = |img| region_sum(img, 40..44, 16..20);
    let (a, b) = (block(&or), block(&pt));
    assert!(
        (a / b - 1.0).abs() < 0.15,
        "the block beside the lit mouth: oracle {a:.4} vs PT {b:.4}"
    );
    let d = rel_diff(or.mean(), pt.mean());
    assert!(d < 0.01, "image mean differs by {:.2}%", d * 100.0);
    assert!(
        st.estimators.exits_from_object > 1_000,
        "{:?}",
        st.estimators
    );
}
