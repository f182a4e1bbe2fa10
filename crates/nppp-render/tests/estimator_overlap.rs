//! Other geometry within an estimator's object (its convex hull): the
//! instance is traced for real (`nppp_render::estimator_overlap`).

mod common;

use common::{render_str, scene_from_str};
use nppp_render::estimator::EstimatorMode;
use nppp_render::estimator_overlap::Obstruction;
use nppp_render::scene_data::RenderScene;

const JADE: &str = r#"{"type": "translucent", "ior": 1.5, "sigma_s": [2, 2, 2], "sigma_a": [0.1, 0.1, 0.1], "g": 0}"#;

/// A scene with instance 0, `object` (mesh JSON) in `material`, bound to an
/// estimator, and instance 1, `other` (mesh JSON) in `other_material`.
fn scene(object: &str, material: &str, other: &str, other_material: &str) -> String {
    placed(object, material, "{}", other, other_material)
}

/// [`scene`] with the object placed by `transform` (JSON).
fn placed(
    object: &str,
    material: &str,
    transform: &str,
    other: &str,
    other_material: &str,
) -> String {
    placed_lit(object, material, transform, other, other_material, 30.0)
}

/// [`placed`] with the light at height `light_y`.
fn placed_lit(
    object: &str,
    material: &str,
    transform: &str,
    other: &str,
    other_material: &str,
    light_y: f32,
) -> String {
    format!(
        r#"{{
  "camera": {{"position": [0, 0.5, -6], "look_at": [0, 0, 0], "fov_y_deg": 40, "width": 12, "height": 12}},
  "materials": {{
    "object": {material},
    "other": {other_material},
    "lamp": {{"type": "emitter", "radiance": [4, 4, 4]}}
  }},
  "meshes": {{
    "object": {object},
    "other": {other},
    "light": {{"quad": [[-1, {light_y}, -1], [-1, {light_y}, 1], [1, {light_y}, 1], [1, {light_y}, -1]]}}
  }},
  "instances": [
    {{"mesh": "object", "material": "object", "transform": {transform}, "estimator": "unused-by-the-oracle.nppp"}},
    {{"mesh": "other", "material": "other"}},
    {{"mesh": "light", "material": "lamp"}}
  ],
  "render": {{"estimator_min_bounces": 0}}
}}"#
    )
}

const BALL: &str = r#"{"icosphere": {"center": [0, 0, 0], "radius": 1, "subdivisions": 3}}"#;
const LAMP: &str = r#"{"type": "emitter", "radiance": [3, 3, 3]}"#;
const WHITE: &str = r#"{"type": "diffuse", "albedo": [0.7, 0.7, 0.7]}"#;

fn obstructed(json: &str) -> Vec<Obstruction> {
    let scene = scene_from_str(json);
    RenderScene::with_estimators(&scene, EstimatorMode::Oracle, 0)
        .unwrap()
        .obstructed
}

#[test]
fn geometry_crossing_or_filling_a_see_through_object_releases_its_estimator() {
    let released = [Obstruction {
        instance: 0,
        other: 1,
    }];
    // A lamp inside a jade ball: no surface crosses.
    let inside = r#"{"box": {"min": [-0.2, -0.2, -0.2], "max": [0.2, 0.2, 0.2]}}"#;
    assert_eq!(obstructed(&scene(BALL, JADE, inside, LAMP)), released);
    // A floor through the ball: its edges are far outside.
    let floor = r#"{"quad": [[-50, -0.3, -50], [-50, -0.3, 50], [50, -0.3, 50], [50, -0.3, -50]]}"#;
    assert_eq!(obstructed(&scene(BALL, JADE, floor, WHITE)), released);
    // A small box poking through the ball's surface.
    let poking = r#"{"box": {"min": [0.8, -0.1, -0.1], "max": [1.4, 0.1, 0.1]}}"#;
    assert_eq!(obstructed(&scene(BALL, JADE, poking, WHITE)), released);
    let glass = r#"{"type": "dielectric", "ior": 1.5}"#;
    // A glass ball holding a lamp: glass walks go inside too.
    assert_eq!(obstructed(&scene(BALL, glass, inside, LAMP)), released);
    // A thin glass slab through a box's face: no edge of either crosses
    // the other's surface, no vertex of one is inside the other.
    let slab = r#"{"box": {"min": [-1, -0.05, -1], "max": [1, 0.05, 1]}}"#;
    let block = r#"{"box": {"min": [0.5, -1, -1.5], "max": [3, 1, 6.5]}}"#;
    assert_eq!(obstructed(&scene(slab, glass, block, WHITE)), released);
    // A jade rod through a lamp cube, turned so that none of its vertices
    // lies over a face of the cube (a vertex-based face test missed it:
    // 1.3% dark).
    let rod = r#"{"box": {"min": [-0.15, -0.15, -3], "max": [0.15, 0.15, 3]}}"#;
    let cube = r#"{"box": {"min": [-0.6, -0.6, -0.6], "max": [0.6, 0.6, 0.6]}}"#;
    let turned = r#"{"rotate": {"axis": [0, 1, 0], "deg": 30}}"#;
    assert_eq!(obstructed(&placed(rod, JADE, turned, cube, LAMP)), released);
}

#[test]
fn geometry_beside_under_or_around_an_object_keeps_its_estimator() {
    // A box in the corner of the ball's bounding box, clear of the ball
    // (the boxes overlap, the shapes do not).
    let corner = r#"{"box": {"min": [0.75, 0.75, 0.75], "max": [1.2, 1.2, 1.2]}}"#;
    assert_eq!(obstructed(&scene(BALL, JADE, corner, WHITE)), []);
    // A floor just under the ball.
    let floor =
        r#"{"quad": [[-50, -1.01, -50], [-50, -1.01, 50], [50, -1.01, 50], [50, -1.01, -50]]}"#;
    assert_eq!(obstructed(&scene(BALL, JADE, floor, WHITE)), []);
    // A glass box standing exactly on a floor, on the floor's diagonal
    // (which grazes the box's bottom face) and off it: contact, not
    // crossing.
    let unit_box = r#"{"box": {"min": [-0.5, 0, -0.5], "max": [0.5, 1, 0.5]}}"#;
    let ground = r#"{"quad": [[-500, 0, -500], [-500, 0, 500], [500, 0, 500], [500, 0, -500]]}"#;
    let glass = r#"{"type": "dielectric", "ior": 1.5}"#;
    for (at, turn) in [
        ("[5, 0, 5]", 0),
        ("[5, 0, -5]", 0),
        ("[0, 0, 0]", 0),
        // Turned and far from the origin: the floor's triangles, mapped
        // into the box's space, are off by rounding.
        ("[300, 0, 280]", 37),
    ] {
        let t = format!(r#"{{"rotate": {{"axis": [0, 1, 0], "deg": {turn}}}, "translate": {at}}}"#);
        assert_eq!(
            obstructed(&placed(unit_box, glass, &t, ground, WHITE)),
            [],
            "at {at}"
        );
    }
    // A ball inside a glass box or a closed room: indices of refraction
    // do not nest, so what holds the object changes none of its walks.
    let holder = r#"{"box": {"min": [-2, -2, -2], "max": [2, 2, 2]}}"#;
    assert_eq!(obstructed(&scene(BALL, JADE, holder, glass)), []);
    assert_eq!(obstructed(&scene(BALL, glass, holder, WHITE)), []);
}

#[test]
fn geometry_between_the_parts_of_an_object_releases_its_estimator() {
    // A knot's walks cross its hole from strand to strand, opaque or not:
    // an oracle with a lamp in a glass knot's hole rendered 26% dark, a
    // gold knot's 38%, and a plain ball there 0.4-1% (an independent
    // check against Mitsuba 3). A Menger sponge of level 1 has a tunnel
    // through its middle: a ball in it (clear of every face) is within
    // the sponge's hull.
    let sponge = r#"{"procedural": {"type": "menger_sponge", "level": 1}}"#;
    let ball = r#"{"icosphere": {"center": [0, 0, 0], "radius": 0.05, "subdivisions": 2}}"#;
    let gold = r#"{"type": "conductor", "reflectance": [1, 0.8, 0.4], "roughness": 0.2}"#;
    for material in [WHITE, gold, JADE] {
        assert_eq!(
            obstructed(&scene(sponge, material, ball, LAMP)),
            [Obstruction {
                instance: 0,
                other: 1
            }],
            "{material}"
        );
    }
    // Beside the sponge, clear of its hull, it is kept.
    let beside = r#"{"icosphere": {"center": [0.8, 0, 0], "radius": 0.05, "subdivisions": 2}}"#;
    assert_eq!(obstructed(&scene(sponge, WHITE, beside, LAMP)), []);
    // Geometry hidden inside an opaque object changes none of its walks,
    // but the hull cannot tell it from geometry in a hole: it is traced
    // for real too (the same image).
    let inside = r#"{"box": {"min": [-0.2, -0.2, -0.2], "max": [0.2, 0.2, 0.2]}}"#;
    assert_eq!(obstructed(&scene(BALL, WHITE, inside, LAMP)).len(), 1);
}

#[test]
fn a_released_instance_renders_as_plain_path_tracing_does() {
    // The oracle walks the object alone: with the lamp inside the jade
    // ball it lost the lamp's light (about 30% dark). Released, the render
    // is plain path tracing, bit for bit.
    let inside = r#"{"box": {"min": [-0.2, -0.2, -0.2], "max": [0.2, 0.2, 0.2]}}"#;
    let json = scene(BALL, JADE, inside, LAMP);
    let scene = scene_from_str(&json);
    let rs = RenderScene::with_estimators(&scene, EstimatorMode::Oracle, 0).unwrap();
    assert!(
        rs.estimators.is_none(),
        "every estimator instance released: a plain render"
    );
    let pt = render_str(&json, 16, 20, 3);
    let opts = nppp_render::render::RenderOptions {
        spp: 16,
        max_bounces: 20,
        seed: 3,
        progress: false,
    };
    let (img, _) = nppp_render::render::render(&rs, &opts);
    assert_eq!(img.pixels, pt.pixels);
}

/// An estimator named on a lamp is left unused: a path that reaches a lamp
/// ends there, and the light the estimator would return is what the
/// vertex before the entry has already sampled (an oracle on a lamp over a
/// floor rendered 6% bright). Neural mode does not read the file.
#[test]
fn an_estimator_on_a_lamp_is_not_used() {
    let floor =
        r#"{"quad": [[-50, -1.01, -50], [-50, -1.01, 50], [50, -1.01, 50], [50, -1.01, -50]]}"#;
    let json = scene(BALL, LAMP, floor, WHITE);
    let scene = scene_from_str(&json);
    let note = nppp_render::estimator::unused_on_emitters(&scene).expect("a note");
    assert!(
        note.contains("instances[0].estimator is not used") && note.contains("\"object\""),
        "{note}"
    );
    for mode in [EstimatorMode::Oracle, EstimatorMode::Neural] {
        let rs = RenderScene::with_estimators(&scene, mode, 0).unwrap();
        assert!(rs.estimators.is_none(), "{mode:?}: a plain render");
        let opts = nppp_render::render::RenderOptions {
            spp: 16,
            max_bounces: 3,
            seed: 5,
            progress: false,
        };
        let (img, _) = nppp_render::render::render(&rs, &opts);
        let pt = render_str(&json, 16, 3, 5);
        assert_eq!(img.pixels, pt.pixels, "{mode:?}");
    }
    // A lamp without an estimator, or a diffuse object with one: no note.
    let diffuse = scene_from_str(&placed(BALL, WHITE, "{}", floor, WHITE));
    assert_eq!(nppp_render::estimator::unused_on_emitters(&diffuse), None);
}

proptest::proptest! {
    #![proptest_config(proptest::prelude::ProptestConfig::with_cases(48))]

    /// Two spheres, at random sizes, places, turns and scales: the jade or
    /// glass one (with the estimator) is released exactly when the spheres
    /// cross or the other lies inside it, not when it lies inside the other
    /// or apart. Cases within 4% of tangency are skipped (the icospheres lie
    /// up to 1.5% inside their spheres).
    #[test]
    fn spheres_are_released_exactly_when_they_cross_or_fill(
        r1 in 0.3f32..2.0,
        r2 in 0.05f32..3.0,
        c1 in proptest::array::uniform3(-1.0f32..1.0),
        c2 in proptest::array::uniform3(-3.0f32..3.0),
        axis in proptest::array::uniform3(-1.0f32..1.0),
        scale in proptest::sample::select(vec![0.01f32, 1.0, 250.0]),
        glass in proptest::bool::ANY,
    ) {
        let d = glam::Vec3::from(c1).distance(glam::Vec3::from(c2));
        let near = |a: f32, b: f32| (a - b).abs() < 0.04 * a.max(b);
        proptest::prop_assume!(!near(d, r1 + r2) && !near(r2, r1 + d) && !near(r1, r2 + d));
        proptest::prop_assume!(glam::Vec3::from(axis).length() > 1e-3);
        let expect = d < r1 + r2 && r2 <= r1 + d;
        let material = if glass { r#"{"type": "dielectric", "ior": 1.4}"# } else { JADE };
        let at = |c: [f32; 3]| format!("[{}, {}, {}]", c[0] * scale, c[1] * scale, c[2] * scale);
        let object = r#"{"icosphere": {"center": [0, 0, 0], "radius": 1, "subdivisions": 3}}"#;
        let other = format!(
            r#"{{"icosphere": {{"center": {}, "radius": {}, "subdivisions": 3}}}}"#,
            at(c2),
            r2 * scale
        );
        let transform = format!(
            r#"{{"scale": {}, "rotate": {{"axis": [{}, {}, {}], "deg": 40}}, "translate": {}}}"#,
            r1 * scale,
            axis[0],
            axis[1],
            axis[2],
            at(c1)
        );
        // The light far above, whatever the scale.
        let json = placed_lit(object, material, &transform, &other, LAMP, 3000.0 * scale.max(1.0));
        let released = !obstructed(&json).is_empty();
        proptest::prop_assert_eq!(released, expect, "d {} r1 {} r2 {} scale {}: {}", d, r1, r2, scale, json);
    }
}

/// Geometry outside the object's hull but inside its estimator's sphere
/// (a floor just under a ball) is boxed in world space for the exit rule
/// (`Estimators::exit_origin`), at any place and turn of the instance;
/// geometry outside the sphere is not.
#[test]
fn other_geometry_inside_an_estimators_sphere_is_boxed_for_its_exits() {
    let boxed = |json: &str| {
        let scene = scene_from_str(json);
        let rs = RenderScene::with_estimators(&scene, EstimatorMode::Oracle, 0).unwrap();
        assert!(rs.obstructed.is_empty());
        rs.estimators.unwrap().other_geometry_in_sphere(0)
    };
    let floor = |y: f32| {
        format!(r#"{{"quad": [[-50, {y}, -50], [-50, {y}, 50], [50, {y}, 50], [50, {y}, -50]]}}"#)
    };
    // The ball's sphere has radius 1.01 (`SPHERE_MARGIN`).
    for (transform, centre, scale) in [
        ("{}", [0.0, 0.0, 0.0], 1.0),
        (
            r#"{"rotate": {"axis": [1, 2, 3], "deg": 40}, "scale": 2, "translate": [30, 0, -7]}"#,
            [30.0, 0.0, -7.0],
            2.0,
        ),
    ] {
        let y = -1.005 * scale;
        let b = boxed(&placed(BALL, WHITE, transform, &floor(y), WHITE))
            .unwrap_or_else(|| panic!("{transform}: the floor in the sphere is not found"));
        let r = 1.01 * scale;
        // The floor's disc in the sphere: flat at y, within the sphere's box.
        assert!(
            b.0.y <= y && b.1.y >= y && b.1.y - b.0.y < 1e-3 * r,
            "{transform}: {b:?}"
        );
        for k in [0, 2] {
            assert!(
                b.0[k] >= centre[k] - r * 1.001 && b.1[k] <= centre[k] + r * 1.001,
                "{transform}: {b:?}"
            );
            // The disc is the sphere's section 0.005 above its bottom.
            let half = (r * r - y * y).sqrt();
            assert!(
                b.0[k] <= centre[k] - half * 0.99 && b.1[k] >= centre[k] + half * 0.99,
                "{transform}: {b:?}"
            );
        }
        assert_eq!(
            boxed(&placed(
                BALL,
                WHITE,
                transform,
                &floor(-1.02 * scale),
                WHITE
            )),
            None,
            "{transform}"
        );
    }
}
