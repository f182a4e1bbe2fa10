//! Translucent objects (a homogeneous medium inside a smooth dielectric),
//! checked against closed forms: a non-absorbing medium conserves energy in
//! a furnace, pure absorption follows Beer-Lambert (chromatic, and invariant
//! under an instance's scale), and each scattering event counts toward M.

mod common;
use common::*;

const SPHERE: &str = r#"{"icosphere": {"center": [0, 0, 0], "radius": 1, "subdivisions": 3}}"#;

fn translucent(ior: f32, sigma_s: [f32; 3], sigma_a: [f32; 3], g: f32) -> String {
    format!(
        r#"{{"type": "translucent", "ior": {ior}, "sigma_s": {sigma_s:?}, "sigma_a": {sigma_a:?}, "g": {g}}}"#
    )
}

#[test]
fn a_non_absorbing_medium_vanishes_in_a_furnace() {
    // All light that enters leaves again (no absorption, a lossless
    // boundary), so the object is invisible: every pixel's expectation is
    // the emitters' radiance, whatever the index, phase function or colour
    // (chromatic media check the spectral MIS: with weights mixed per event
    // the dense channel came out at 1.67 instead of 2).
    for (ior, g, sigma_s) in [
        (1.0, 0.0, [2.0, 2.0, 2.0]),
        (1.5, 0.0, [2.0, 2.0, 2.0]),
        (1.0, 0.0, [1.0, 4.0, 9.0]),
        (1.5, 0.6, [1.0, 4.0, 9.0]),
        (1.33, -0.5, [6.0, 3.0, 0.5]),
    ] {
        let json = furnace_scene(&translucent(ior, sigma_s, [0.0; 3], g), 2.0, 3.0, SPHERE);
        let img = render_str(&json, 128, 100_000, 1);
        let m = mean(&img);
        for c in m {
            assert!(
                (c - 2.0).abs() < 0.02,
                "ior {ior}, g {g}, sigma_s {sigma_s:?}: mean {m:?}, expected 2"
            );
        }
    }
}

#[test]
fn an_absorbing_medium_darkens_a_furnace_and_more_at_higher_density() {
    // The same sphere with absorption: strictly darker than the emitters,
    // and darker still when its medium is denser (a check on the sign of
    // every weight, not a closed form).
    let at = |sigma_a: f32| {
        let json = furnace_scene(
            &translucent(1.5, [3.0; 3], [sigma_a; 3], 0.0),
            1.0,
            3.0,
            SPHERE,
        );
        mean(&render_str(&json, 32, 1000, 2))[1]
    };
    let (thin, thick) = (at(0.1), at(1.0));
    assert!(thick < thin && thin < 0.99, "{thin} {thick}");
}

/// A slab of medium (thickness `t` in mesh units, scaled by `scale`) in
/// front of a uniform emitter, seen through a nearly parallel pinhole.
fn slab_scene(material: &str, t: f32, scale: f32) -> String {
    slab_scene_at(material, t, scale, 0.0)
}

/// [`slab_scene`] with everything moved by `x` along the x axis.
fn slab_scene_at(material: &str, t: f32, scale: f32, x: f32) -> String {
    let h = 0.5 * t;
    format!(
        r#"{{
  "camera": {{"position": [{x}, 0, -200], "look_at": [{x}, 0, 0], "fov_y_deg": 0.3, "width": 16, "height": 16}},
  "materials": {{"lamp": {{"type": "emitter", "radiance": [1, 1, 1]}}, "slab": {material}}},
  "meshes": {{
    "slab": {{"box": {{"min": [-1, -1, -{h}], "max": [1, 1, {h}]}}}},
    "light": {{"quad": [[-50, -50, 20], [-50, 50, 20], [50, 50, 20], [50, -50, 20]]}}
  }},
  "instances": [
    {{"mesh": "slab", "material": "slab", "transform": {{"scale": {scale}, "translate": [{x}, 0, 0]}}}},
    {{"mesh": "light", "material": "lamp", "transform": {{"translate": [{x}, 0, 0]}}}}
  ]
}}"#
    )
}

#[test]
fn absorption_alone_follows_beer_lambert_in_mesh_units() {
    // Index-matched boundary (no reflection, no bending) and no scattering:
    // each pixel sees the lamp through exp(-sigma_a * thickness), the
    // thickness measured in the mesh's own units whatever the scale.
    let sigma_a = [0.5f32, 1.0, 2.0];
    for (t, scale) in [(1.0f32, 1.0f32), (0.5, 2.0), (0.25, 8.0)] {
        let json = slab_scene(&translucent(1.0, [0.0; 3], sigma_a, 0.0), t, scale);
        let img = render_str(&json, 1024, 5, 3);
        let m = mean(&img);
        for c in 0..3 {
            let expect = (-(sigma_a[c] * t) as f64).exp();
            assert!(
                (m[c] - expect).abs() < 0.01 * expect,
                "thickness {t} at scale {scale}: channel {c} is {}, Beer-Lambert gives {expect}",
                m[c]
            );
        }
    }
}

#[test]
fn absorption_follows_beer_lambert_far_from_the_origin() {
    // At x = 5000 a ray leaves a surface 0.1 off it (the offset grows with
    // the distance from the origin). The free flight into the medium must
    // still start at the surface: the 0.1 it skipped made this slab 1.1x-
    // 1.2x too bright (and dense media look like absorbers).
    let sigma_a = [0.5f32, 1.0, 2.0];
    let json = slab_scene_at(&translucent(1.0, [0.0; 3], sigma_a, 0.0), 1.0, 1.0, 5000.0);
    let m = mean(&render_str(&json, 256, 5, 3));
    for c in 0..3 {
        let expect = (-(sigma_a[c]) as f64).exp();
        assert!(
            (m[c] - expect).abs() < 0.01 * expect,
            "channel {c} is {}, Beer-Lambert gives {expect}",
            m[c]
        );
    }
}

#[test]
fn each_scattering_event_counts_toward_m() {
    // A slab that scatters strongly forward, seen head-on: at M = 2 only the
    // two refractions fit (the unscattered light), so the image is the
    // ballistic transmittance; more bounces let scattered light through too.
    let sigma_s = [1.5f32; 3];
    let json = slab_scene(&translucent(1.0, sigma_s, [0.0; 3], 0.9), 1.0, 1.0);
    let ballistic = (-1.5f64).exp();
    let m2 = mean(&render_str(&json, 1024, 2, 4))[0];
    assert!(
        (m2 - ballistic).abs() < 0.02 * ballistic,
        "M = 2: {m2}, expected exp(-1.5) = {ballistic}"
    );
    let m3 = mean(&render_str(&json, 256, 3, 4))[0];
    let m20 = mean(&render_str(&json, 256, 20, 4))[0];
    assert!(m3 > m2 * 1.1 && m20 > m3, "{m2} {m3} {m20}");
}

/// Three slabs of one chromatic absorbing medium in a row before a lamp of
/// radiance 1, index-matched, seen through a nearly parallel pinhole.
fn three_slabs_scene(material: &str) -> String {
    format!(
        r#"{{
  "camera": {{"position": [0, 0, -200], "look_at": [0, 0, 0], "fov_y_deg": 0.3, "width": 32, "height": 32}},
  "materials": {{"lamp": {{"type": "emitter", "radiance": [1, 1, 1]}}, "slab": {material}}},
  "meshes": {{
    "slab": {{"box": {{"min": [-1, -1, -0.5], "max": [1, 1, 0.5]}}}},
    "light": {{"quad": [[-50, -50, 20], [-50, 50, 20], [50, 50, 20], [50, -50, 20]]}}
  }},
  "instances": [
    {{"mesh": "slab", "material": "slab", "transform": {{"translate": [0, 0, -3]}}}},
    {{"mesh": "slab", "material": "slab"}},
    {{"mesh": "slab", "material": "slab", "transform": {{"translate": [0, 0, 3]}}}},
    {{"mesh": "light", "material": "lamp"}}
  ]
}}"#
    )
}

#[test]
fn one_hero_per_path_bounds_a_sample_through_several_media() {
    // Spectral MIS over the whole path: a sample's weight in any channel is
    // at most 3 (times the albedo product, here 1 for a surviving path),
    // however many media it crosses. With a hero picked at every entry the
    // factor compounded per visit: a path crossing the three slabs with the
    // red hero carried 2.42^3 = 14.1 in red (and a path through half a
    // dozen jade knots 67,000x in green).
    let sigma_a = [0.5f32, 2.0, 4.5];
    let json = three_slabs_scene(&translucent(1.0, [0.0; 3], sigma_a, 0.0));
    let one_spp = render_str(&json, 1, 10, 4);
    let worst = one_spp
        .pixels
        .iter()
        .flat_map(|p| p.iter().copied())
        .fold(0.0f32, f32::max);
    assert!(worst > 1.0, "some path must survive with a weight: {worst}");
    assert!(worst <= 3.0 * (1.0 + 1e-4), "a sample of {worst} > 3");
    // And the estimate is still Beer-Lambert through the three slabs.
    let m = mean(&render_str(&json, 2048, 10, 5));
    for c in 0..3 {
        let expect = (-(sigma_a[c] * 3.0) as f64).exp();
        assert!(
            (m[c] - expect).abs() < 0.03 * expect + 1e-4,
            "channel {c}: {}, Beer-Lambert gives {expect}",
            m[c]
        );
    }
}

#[test]
fn glass_inside_a_medium_keeps_the_medium_as_mitsuba_does() {
    // An index-matched glass box inside an absorbing slab (both ior 1: no
    // reflection, no bending). A surface that names no medium keeps the
    // path's (Mitsuba 3's `volpath`), so the lamp is seen through the
    // whole slab: exp(-sigma_a * 1). Ending the medium at the glass, as
    // nppp did, gave exp(-sigma_a * 0.25), the slab in front of the glass.
    let sigma_a = [0.5f32, 1.0, 2.0];
    let json = format!(
        r#"{{
  "camera": {{"position": [0, 0, -200], "look_at": [0, 0, 0], "fov_y_deg": 0.3, "width": 16, "height": 16}},
  "materials": {{
    "lamp": {{"type": "emitter", "radiance": [1, 1, 1]}},
    "slab": {},
    "glass": {{"type": "dielectric", "ior": 1.0}}
  }},
  "meshes": {{
    "slab": {{"box": {{"min": [-1, -1, -0.5], "max": [1, 1, 0.5]}}}},
    "inner": {{"box": {{"min": [-0.8, -0.8, -0.25], "max": [0.8, 0.8, 0.25]}}}},
    "light": {{"quad": [[-50, -50, 20], [-50, 50, 20], [50, 50, 20], [50, -50, 20]]}}
  }},
  "instances": [
    {{"mesh": "slab", "material": "slab"}},
    {{"mesh": "inner", "material": "glass"}},
    {{"mesh": "light", "material": "lamp"}}
  ]
}}"#,
        translucent(1.0, [0.0; 3], sigma_a, 0.0)
    );
    let m = mean(&render_str(&json, 1024, 10, 6));
    for c in 0..3 {
        let expect = (-sigma_a[c] as f64).exp();
        assert!(
            (m[c] - expect).abs() < 0.02 * expect,
            "channel {c}: {}, Beer-Lambert through the whole slab gives {expect}",
            m[c]
        );
    }
}
