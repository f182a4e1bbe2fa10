//! Furnace tests: inside a closed enclosure of uniform emitters, a lossless
//! object is invisible (every pixel equals the emitter radiance), and a lossy
//! one darkens by exactly its albedo. These catch MIS weights that do not
//! sum to one, wrong pdfs, and energy gains or losses in the BSDFs.

mod common;
use common::*;

const SPHERE: &str = r#"{"icosphere": {"center": [0, 0, 0], "radius": 1, "subdivisions": 3}}"#;

fn max_dev(img: &nppp_render::Image, target: f32) -> f32 {
    img.pixels
        .iter()
        .flat_map(|p| p.iter())
        .map(|v| (v - target).abs())
        .fold(0.0, f32::max)
}

#[test]
fn white_diffuse_sphere_vanishes() {
    // Convex albedo-1 object: one bounce reaches the walls, so any M >= 1 gives exactly Le on average.
    let json = furnace_scene(
        r#"{"type": "diffuse", "albedo": [1, 1, 1]}"#,
        2.0,
        3.0,
        SPHERE,
    );
    let img = render_str(&json, 64, 8, 1);
    let m = mean(&img);
    for c in m {
        assert!((c - 2.0).abs() < 0.01, "mean {m:?}");
    }
    assert!(
        max_dev(&img, 2.0) < 0.4,
        "a pixel strays by {}",
        max_dev(&img, 2.0)
    );
}

#[test]
fn half_albedo_sphere_reflects_half() {
    // The sphere's pixels should be albedo * Le; walls Le. Check image mean bounds and that it is darker.
    let json = furnace_scene(
        r#"{"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}"#,
        1.0,
        3.0,
        SPHERE,
    );
    let img = render_str(&json, 64, 8, 2);
    // The centre pixel sees the sphere.
    let c = img.get(12, 12);
    assert!((c[0] - 0.5).abs() < 0.06, "centre {c:?}");
}

#[test]
fn mirror_conductor_with_unit_reflectance_vanishes() {
    let json = furnace_scene(
        r#"{"type": "conductor", "reflectance": [1, 1, 1], "roughness": 0}"#,
        1.0,
        3.0,
        SPHERE,
    );
    let img = render_str(&json, 16, 8, 3);
    assert!(max_dev(&img, 1.0) < 1e-3, "dev {}", max_dev(&img, 1.0));
}

/// Directional albedo of single-scattering GGX at normal incidence, by
/// midpoint quadrature of the textbook formulas (independent of bsdf.rs).
fn ggx_albedo_normal_incidence(alpha: f64) -> f64 {
    let g1 = |z: f64| {
        if z <= 0.0 {
            0.0
        } else {
            2.0 / (1.0 + (1.0 + alpha * alpha * (1.0 - z * z) / (z * z)).sqrt())
        }
    };
    let n = 20_000;
    let mut e = 0.0;
    for i in 0..n {
        // wi at polar angle theta; the half vector is at theta / 2.
        let theta = (i as f64 + 0.5) / n as f64 * std::f64::consts::FRAC_PI_2;
        let (mz, mr) = ((theta / 2.0).cos(), (theta / 2.0).sin());
        let t = mr * mr / (alpha * alpha) + mz * mz;
        let d = 1.0 / (std::f64::consts::PI * alpha * alpha * t * t);
        let f_cos = d * g1(1.0) * g1(theta.cos()) / 4.0;
        e += f_cos * theta.sin() * std::f64::consts::TAU * std::f64::consts::FRAC_PI_2 / n as f64;
    }
    e
}

#[test]
fn rough_conductor_matches_its_directional_albedo() {
    // A conductor wall fills the view at normal incidence; with unit emitters
    // all around, each pixel is the BSDF's directional albedo (single-scattering
    // GGX loses energy, like Mitsuba's roughconductor: 31% left at alpha 1).
    let wall = r#"{"quad": [[-2.5, -2.5, 0], [2.5, -2.5, 0], [2.5, 2.5, 0], [-2.5, 2.5, 0]]}"#;
    for alpha in [0.2f64, 0.5, 1.0] {
        let json = furnace_scene(
            &format!(r#"{{"type": "conductor", "reflectance": [1, 1, 1], "roughness": {alpha}}}"#),
            1.0,
            3.0,
            wall,
        );
        let img = render_str(&json, 256, 1, 4);
        let want = ggx_albedo_normal_incidence(alpha);
        let got =
            (img.get(11, 11)[0] + img.get(12, 12)[0] + img.get(11, 12)[0] + img.get(12, 11)[0])
                as f64
                / 4.0;
        assert!(
            (got - want).abs() < 0.02,
            "alpha {alpha}: got {got}, want {want}"
        );
    }
}

#[test]
fn glass_sphere_conserves_energy() {
    // Lossless dielectric: what enters leaves; the 1/eta^2 radiance scalings cancel.
    let json = furnace_scene(r#"{"type": "dielectric", "ior": 1.5}"#, 1.0, 3.0, SPHERE);
    let img = render_str(&json, 128, 64, 5);
    let m = mean(&img);
    assert!((m[0] - 1.0).abs() < 0.01, "mean {m:?}");
}

#[test]
fn camera_inside_glass_sees_outside_brighter_by_eta_squared() {
    // docs/scene-format.md: a camera inside glass of ior 1.5 sees the outside 2.25 times as bright, before Fresnel.
    // A glass sphere around the camera, looking straight out at normal incidence: T = 1 - ((1.5-1)/(1.5+1))^2 = 0.96.
    let json = furnace_scene(
        r#"{"type": "dielectric", "ior": 1.5}"#,
        1.0,
        3.0,
        r#"{"icosphere": {"center": [0, 0, -2.7], "radius": 0.5, "subdivisions": 5}}"#,
    );
    let img = render_str(&json, 256, 1, 6);
    // Path to the walls through one interface with M = 1: 2.25 * 0.96 (transmission), reflection stays inside (no more bounces).
    let c = img.get(12, 12)[0];
    assert!((c - 2.25 * 0.96).abs() < 0.12, "centre {c}");
}
