//! Numerical stress tests of the renderer: extreme scales, radiances,
//! albedos, roughnesses and indices of refraction, degenerate geometry,
//! grazing rays, rays that start on surfaces, and accumulation precision.
//! Every image must be finite, and wherever the right answer is known (a
//! furnace, an albedo-0 object, a constant emitter) it must be that answer.
//! docs/robustness.md lists what is tried here and what the renderer does.

mod common;
use common::*;
use nppp_render::film::PixelSum;
use nppp_render::{Image, RenderOptions, RenderScene, RenderStats};
use serde_json::{Value, json};
use std::path::{Path, PathBuf};

const SPHERE: &str = r#"{"icosphere": {"center": [0, 0, 0], "radius": 1, "subdivisions": 3}}"#;

fn render_scene(
    scene: &nppp_scene::Scene,
    spp: u32,
    max_bounces: u32,
    seed: u64,
) -> (Image, RenderStats) {
    nppp_render::render(
        &RenderScene::new(scene),
        &RenderOptions {
            spp,
            max_bounces,
            seed,
            progress: false,
        },
    )
}

fn render_json(json: &str, spp: u32, max_bounces: u32, seed: u64) -> (Image, RenderStats) {
    render_scene(&scene_from_str(json), spp, max_bounces, seed)
}

fn assert_finite(img: &Image, what: &str) {
    let bad = img
        .pixels
        .iter()
        .filter(|p| !p.iter().all(|c| c.is_finite() && *c >= 0.0))
        .count();
    assert_eq!(bad, 0, "{what}: {bad} pixels are negative, NaN or infinite");
}

/// Largest |pixel - target| over all pixels and channels.
fn max_dev(img: &Image, target: f32) -> f32 {
    img.pixels
        .iter()
        .flat_map(|p| p.iter())
        .map(|v| (v - target).abs())
        .fold(0.0, f32::max)
}

fn luminance_mean(img: &Image) -> f64 {
    let m = img.mean();
    (m[0] + m[1] + m[2]) / 3.0
}

/// Per-block means (blocks of `b` x `b` pixels, channels averaged).
fn block_means(img: &Image, b: u32) -> Vec<f64> {
    let mut out = Vec::new();
    for by in 0..img.height / b {
        for bx in 0..img.width / b {
            let mut s = 0.0;
            for y in by * b..(by + 1) * b {
                for x in bx * b..(bx + 1) * b {
                    s += img.get(x, y).iter().map(|&c| c as f64).sum::<f64>() / 3.0;
                }
            }
            out.push(s / (b * b) as f64);
        }
    }
    out
}

fn temp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("nppp-stress-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

// ---------------------------------------------------------------------------
// Scale invariance
// ---------------------------------------------------------------------------

/// Multiplies every length of a scene (camera, quad/box/icosphere points,
/// instance translations; instances of procedural and OBJ meshes get their
/// scale multiplied instead) by `s`.
fn scale_scene(scene: &Value, s: f64) -> Value {
    let mut v = scene.clone();
    let sv = |x: &Value| json!(x.as_f64().unwrap() * s);
    let s3 = |p: &mut Value| {
        for c in p.as_array_mut().unwrap() {
            *c = sv(c);
        }
    };
    s3(&mut v["camera"]["position"]);
    s3(&mut v["camera"]["look_at"]);
    let mut intrinsic = Vec::new();
    for (name, m) in v["meshes"].as_object_mut().unwrap() {
        if let Some(q) = m.get_mut("quad") {
            q.as_array_mut().unwrap().iter_mut().for_each(s3);
        } else if let Some(b) = m.get_mut("box") {
            s3(&mut b["min"]);
            s3(&mut b["max"]);
        } else if let Some(ico) = m.get_mut("icosphere") {
            s3(&mut ico["center"]);
            ico["radius"] = sv(&ico["radius"]);
        } else {
            // Procedural and OBJ geometry has its own size: scale the instances.
            intrinsic.push(name.clone());
        }
    }
    for inst in v["instances"].as_array_mut().unwrap() {
        let by_instance = intrinsic.iter().any(|n| inst["mesh"] == *n);
        let t = inst
            .as_object_mut()
            .unwrap()
            .entry("transform")
            .or_insert(json!({}));
        if let Some(tr) = t.get_mut("translate") {
            s3(tr);
        }
        if by_instance {
            let old = t.get("scale").and_then(Value::as_f64).unwrap_or(1.0);
            t["scale"] = json!(old * s);
        }
    }
    v
}

fn cornell_small(size: u32) -> Value {
    let text = std::fs::read_to_string(repo_root().join("data/scenes/cornell-box.json")).unwrap();
    let mut v: Value = serde_json::from_str(&text).unwrap();
    v["camera"]["width"] = json!(size);
    v["camera"]["height"] = json!(size);
    v
}

/// The default Cornell box (with its torus knot) at 1e-4, 1 and 1e4 renders
/// the same image: the mean within 0.5%, every 8x8 block within 2% (measured:
/// 0.02% and 0.1% at 1e-4; a different seed moves blocks by ~3%; Mitsuba 3
/// is 5% too bright at 1e-4).
/// Self-intersection at small scales brightens (light leaks through the
/// ceiling gap of 0.1 units around the lamp) or darkens (shadow rays hit
/// their own surface); either shows here.
#[test]
fn cornell_box_renders_alike_at_1e_minus4_1_and_1e4() {
    let base = cornell_small(32);
    let render = |s: f64, seed: u64| {
        let json = scale_scene(&base, s).to_string();
        let (img, st) = render_json(&json, 64, 5, seed);
        assert_finite(&img, &format!("scale {s}"));
        assert_eq!(st.dropped_samples, 0, "scale {s}: non-finite samples");
        img
    };
    let reference = render(1.0, 7);
    let m_ref = luminance_mean(&reference);
    let b_ref = block_means(&reference, 8);
    // The noise floor: the same scene with another seed.
    let other = render(1.0, 8);
    let noise: f64 = block_means(&other, 8)
        .iter()
        .zip(&b_ref)
        .map(|(a, b)| (a - b).abs() / b.max(1e-3))
        .fold(0.0, f64::max);
    for s in [1e-4, 1e4] {
        let img = render(s, 7);
        let m = luminance_mean(&img);
        assert!(
            (m / m_ref - 1.0).abs() < 0.005,
            "scale {s}: mean {m} vs {m_ref} at scale 1"
        );
        for (i, (a, b)) in block_means(&img, 8).iter().zip(&b_ref).enumerate() {
            let rel = (a - b).abs() / b.max(1e-3);
            assert!(
                rel < 0.02,
                "scale {s}: block {i} differs by {:.2}% ({a} vs {b}; seed-to-seed noise {:.2}%)",
                rel * 100.0,
                noise * 100.0
            );
        }
    }
}

/// A dense, lossless translucent ball in a furnace of emitting walls: each
/// walk takes about 10^4 medium events (sigma_s 100, radius 1) and leaves
/// with its throughput intact, so the image is Le (up to the floor's rare
/// kills at the ball's surface, which are reweighted). The roulette's
/// termination floor (0.2% an event from event 64) applied to medium
/// events, and its survivors' weights (up to e^20) were never sampled: the
/// ball rendered 2.4% dark at every seed.
#[test]
fn dense_lossless_medium_in_a_furnace_is_exact() {
    let ball = r#"{"icosphere": {"center": [0, 0, 0], "radius": 1, "subdivisions": 3}}"#;
    let medium = r#"{"type": "translucent", "ior": 1.2, "sigma_s": [100, 100, 100], "sigma_a": [0, 0, 0], "g": 0}"#;
    let json = furnace_scene(medium, 1.0, 3.0, ball)
        .replace(r#""width": 24, "height": 24"#, r#""width": 8, "height": 8"#);
    assert!(json.contains(r#""width": 8"#));
    let (img, st) = render_json(&json, 16, 1_000_000, 7);
    assert_eq!(st.dropped_samples, 0);
    assert_finite(&img, "dense lossless medium");
    let m = mean(&img)[0];
    assert!((m - 1.0).abs() < 0.005, "image mean {m}, want 1");
}

/// An albedo-0.5 sphere in a furnace at 3e-4, 3 and 3e4: the walls are
/// exactly Le and the sphere's pixels 0.5 Le at every scale.
#[test]
fn furnace_is_exact_at_every_scale() {
    for h in [3e-4f32, 3.0, 3e4] {
        let mesh = format!(
            r#"{{"icosphere": {{"center": [0, 0, 0], "radius": {}, "subdivisions": 3}}}}"#,
            h / 3.0
        );
        let json = furnace_scene(
            r#"{"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}"#,
            1.0,
            h,
            &mesh,
        );
        let (img, st) = render_json(&json, 64, 4, 3);
        assert_finite(&img, &format!("h {h}"));
        assert_eq!(st.dropped_samples, 0);
        // Centre 4x4 pixels see only the sphere; the corner pixels only walls.
        let mut centre = 0.0;
        for y in 10..14 {
            for x in 10..14 {
                centre += img.get(x, y)[0] / 16.0;
            }
        }
        assert!(
            (centre - 0.5).abs() < 0.02,
            "h {h}: sphere centre {centre}, want 0.5"
        );
        for (x, y) in [(0, 0), (23, 0), (0, 23), (23, 23)] {
            assert_eq!(img.get(x, y), [1.0; 3], "h {h}: wall pixel ({x}, {y})");
        }
    }
}

// ---------------------------------------------------------------------------
// Extreme radiance
// ---------------------------------------------------------------------------

/// Emitters of 1e6: finite, and the image is exactly 1e6 times the image
/// with radiance 1 (same paths: light selection and Russian roulette never
/// look at the emitters' absolute radiance).
#[test]
fn radiance_1e6_scales_linearly() {
    let mut scene = cornell_small(24);
    scene["materials"]["lamp"]["radiance"] = json!([1, 1, 1]);
    let (one, _) = render_json(&scene.to_string(), 32, 5, 1);
    scene["materials"]["lamp"]["radiance"] = json!([1e6, 1e6, 1e6]);
    let (big, st) = render_json(&scene.to_string(), 32, 5, 1);
    assert_finite(&big, "radiance 1e6");
    assert_eq!(st.dropped_samples, 0);
    for (a, b) in one.pixels.iter().zip(&big.pixels) {
        for c in 0..3 {
            let want = a[c] as f64 * 1e6;
            assert!(
                (b[c] as f64 - want).abs() <= 1e-4 * want + 1e-3,
                "{} vs {want}",
                b[c]
            );
        }
    }
    assert!(luminance_mean(&one) > 0.01);
}

/// Radiance near the largest f32 (3e38) scales the image linearly: the same
/// seed draws the same paths, so every pixel is 3e38 times the pixel at
/// radiance 1. (The lamp's power, area times radiance, used to overflow in
/// f32 and silently drop the lamp from next-event estimation: only the lamp
/// itself stayed visible, every wall went black.)
#[test]
fn radiance_near_f32_max_scales_the_image_linearly() {
    let mut scene = cornell_small(16);
    scene["materials"]["lamp"]["radiance"] = json!([1, 1, 1]);
    let (one, _) = render_json(&scene.to_string(), 16, 5, 1);
    scene["materials"]["lamp"]["radiance"] = json!([3e38, 3e38, 3e38]);
    let (big, st) = render_json(&scene.to_string(), 16, 5, 1);
    assert_finite(&big, "radiance 3e38");
    assert_eq!(st.dropped_samples, 0);
    for (a, b) in one.pixels.iter().zip(&big.pixels) {
        for c in 0..3 {
            let scaled = b[c] as f64 / 3e38;
            assert!(
                (scaled - a[c] as f64).abs() <= 1e-4 * a[c] as f64 + 1e-30,
                "{} at radiance 3e38 is not 3e38 x {}",
                b[c],
                a[c]
            );
        }
    }
}

/// A sample that went non-finite anyway is dropped and counted, never
/// averaged in. (MIS keeps even a 3e38 lamp's samples finite in a render,
/// so this is checked on the film directly.)
#[test]
fn non_finite_samples_are_dropped_and_counted() {
    let mut px = nppp_render::film::PixelSum::default();
    px.add(glam::Vec3::splat(2.0));
    px.add(glam::Vec3::new(f32::INFINITY, 1.0, 1.0));
    px.add(glam::Vec3::new(1.0, f32::NAN, 1.0));
    px.add(glam::Vec3::splat(4.0));
    assert_eq!((px.valid, px.dropped), (2, 2));
    assert_eq!(px.mean(), [3.0; 3]);
}

// ---------------------------------------------------------------------------
// Albedo 0 and 1, roughness 0 and 1, ior close to 1
// ---------------------------------------------------------------------------

/// Albedo exactly 0: the sphere's pixels are exactly black, the walls exactly Le.
#[test]
fn albedo_zero_is_exactly_black() {
    let json = furnace_scene(
        r#"{"type": "diffuse", "albedo": [0, 0, 0]}"#,
        1.0,
        3.0,
        SPHERE,
    );
    let (img, st) = render_json(&json, 16, 8, 1);
    assert_eq!(st.dropped_samples, 0);
    // The sphere subtends ~8 pixels of radius around the image centre.
    for y in 0..24u32 {
        for x in 0..24u32 {
            let r = ((x as f32 + 0.5 - 12.0).powi(2) + (y as f32 + 0.5 - 12.0).powi(2)).sqrt();
            if r < 6.5 {
                assert_eq!(img.get(x, y), [0.0; 3], "sphere pixel ({x}, {y})");
            } else if r > 11.0 {
                assert_eq!(img.get(x, y), [1.0; 3], "wall pixel ({x}, {y})");
            }
        }
    }
}

/// Albedo exactly 1 on a concave object (the torus knot) with many
/// bounces: Russian roulette does not fire before depth 64 (q = 0), paths
/// still end, and the object vanishes in the furnace.
#[test]
fn albedo_one_concave_object_vanishes() {
    let knot = r#"{"procedural": {"type": "torus_knot", "segments": 96, "sides": 12}}"#;
    let json = furnace_scene(
        r#"{"type": "diffuse", "albedo": [1, 1, 1]}"#,
        1.0,
        3.0,
        knot,
    );
    let (img, st) = render_json(&json, 32, 200, 2);
    assert_finite(&img, "albedo 1");
    assert_eq!(st.dropped_samples, 0);
    let m = luminance_mean(&img);
    assert!((m - 1.0).abs() < 0.01, "mean {m}");
}

/// `max_bounces` at u32::MAX on a lossless object: without a floor on the
/// termination probability, Russian roulette would never end these paths
/// (the albedo-1 knot traps them) and the render would not finish. With
/// it, the render ends and is still the furnace's exact answer in the mean.
#[test]
fn unbounded_max_bounces_on_a_lossless_object_ends_and_is_unbiased() {
    let knot = r#"{"procedural": {"type": "torus_knot", "segments": 96, "sides": 12}}"#;
    for material in [
        r#"{"type": "diffuse", "albedo": [1, 1, 1]}"#,
        r#"{"type": "conductor", "reflectance": [1, 1, 1], "roughness": 0}"#,
    ] {
        let json = furnace_scene(material, 1.0, 3.0, knot);
        let (img, st) = render_json(&json, 16, u32::MAX, 5);
        assert_finite(&img, material);
        assert_eq!(st.dropped_samples, 0);
        let m = luminance_mean(&img);
        assert!((m - 1.0).abs() < 0.02, "{material}: mean {m}");
    }
}

#[test]
fn roughness_zero_and_below_min_alpha_is_an_exact_mirror() {
    for r in ["0", "1e-5", "0.00009"] {
        let json = furnace_scene(
            &format!(r#"{{"type": "conductor", "reflectance": [1, 1, 1], "roughness": {r}}}"#),
            1.0,
            3.0,
            SPHERE,
        );
        let (img, st) = render_json(&json, 4, 8, 1);
        assert_eq!(st.dropped_samples, 0);
        assert!(
            max_dev(&img, 1.0) < 1e-5,
            "roughness {r}: a pixel strays by {}",
            max_dev(&img, 1.0)
        );
    }
}

/// Just above the mirror threshold the GGX lobe is a needle: pdfs near 1e7.
/// Finite, nothing dropped, and still (almost) lossless.
#[test]
fn roughness_just_above_mirror_threshold_is_finite_and_lossless() {
    let json = furnace_scene(
        r#"{"type": "conductor", "reflectance": [1, 1, 1], "roughness": 0.00015}"#,
        1.0,
        3.0,
        SPHERE,
    );
    let (img, st) = render_json(&json, 16, 8, 1);
    assert_finite(&img, "roughness 1.5e-4");
    assert_eq!(st.dropped_samples, 0);
    let m = luminance_mean(&img);
    assert!((m - 1.0).abs() < 2e-3, "mean {m}");
    // Single pixels carry the GGX tail's noise (NEE vs BSDF sampling), a few percent at 16 spp.
    assert!(
        max_dev(&img, 1.0) < 0.08,
        "a pixel strays by {}",
        max_dev(&img, 1.0)
    );
}

/// Roughness exactly 1: finite, nothing dropped, and the single-scattering
/// GGX energy loss keeps the sphere between 0.3 and 1 (at alpha = 1 about
/// 0.31 at normal incidence is left, more at grazing).
#[test]
fn roughness_one_is_finite_and_loses_energy_as_single_scattering_ggx() {
    let json = furnace_scene(
        r#"{"type": "conductor", "reflectance": [1, 1, 1], "roughness": 1}"#,
        1.0,
        3.0,
        SPHERE,
    );
    let (img, st) = render_json(&json, 64, 8, 1);
    assert_finite(&img, "roughness 1");
    assert_eq!(st.dropped_samples, 0);
    let c =
        (img.get(11, 11)[0] + img.get(12, 12)[0] + img.get(11, 12)[0] + img.get(12, 11)[0]) / 4.0;
    assert!(c > 0.2 && c < 0.45, "centre {c}");
    assert!(
        img.pixels.iter().all(|p| p[0] <= 1.0 + 1e-5),
        "a pixel is brighter than the furnace"
    );
}

/// ior 1.0001, 1 and 0.9999: the glass is (almost) not there. Every pixel,
/// not only the mean, stays within 0.5% of Le.
#[test]
fn ior_close_to_one_makes_glass_invisible() {
    for ior in ["1.0001", "1", "0.9999"] {
        let json = furnace_scene(
            &format!(r#"{{"type": "dielectric", "ior": {ior}}}"#),
            1.0,
            3.0,
            SPHERE,
        );
        let (img, st) = render_json(&json, 16, 16, 1);
        assert_finite(&img, ior);
        assert_eq!(st.dropped_samples, 0, "ior {ior}");
        assert!(
            max_dev(&img, 1.0) < 5e-3,
            "ior {ior}: a pixel strays by {}",
            max_dev(&img, 1.0)
        );
    }
}

// ---------------------------------------------------------------------------
// Degenerate geometry, grazing rays, rays starting on surfaces
// ---------------------------------------------------------------------------

/// An octahedron as OBJ text with unshared (duplicated) vertices per face.
fn octahedron_obj(extra: &str) -> String {
    let v = [
        [1.0, 0.0, 0.0],
        [-1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [0.0, -1.0, 0.0],
        [0.0, 0.0, 1.0],
        [0.0, 0.0, -1.0],
    ];
    let faces = [
        [0, 2, 4],
        [2, 1, 4],
        [1, 3, 4],
        [3, 0, 4],
        [2, 0, 5],
        [1, 2, 5],
        [3, 1, 5],
        [0, 3, 5],
    ];
    let mut s = String::new();
    for f in faces {
        for k in f {
            let p: [f64; 3] = v[k];
            s += &format!("v {} {} {}\n", p[0], p[1], p[2]);
        }
    }
    for i in 0..faces.len() {
        s += &format!("f {} {} {}\n", 3 * i + 1, 3 * i + 2, 3 * i + 3);
    }
    s + extra
}

fn obj_furnace(dir: &Path, name: &str, obj: &str, material: &str) -> nppp_scene::Scene {
    std::fs::write(dir.join(format!("{name}.obj")), obj).unwrap();
    let json = furnace_scene(material, 1.0, 3.0, &format!(r#"{{"obj": "{name}.obj"}}"#));
    nppp_scene::parse_scene(&json, &dir.join(format!("{name}.json"))).unwrap()
}

/// Zero-area triangles (a repeated index, three coincident vertices, three
/// collinear vertices, collinear along an edge of the mesh, a huge sliver)
/// and duplicated vertices: they render finite and exactly like the mesh
/// without them.
#[test]
fn degenerate_triangles_and_duplicate_vertices_change_nothing() {
    let dir = temp_dir("degenerate");
    let degenerate = "\
v 0.3 0.3 0.3
v 0.3 0.3 0.3
v 0.3 0.3 0.3
v 0 0 0
v 0.5 0.5 0.5
v 1 1 1
v 1 0 0
v 0 1 0
v 0.5 0.5 0
v -1e6 0.25 0.25
v 1e6 0.25 0.25
v 0 0.25 0.25
f 25 26 27
f 25 25 28
f 28 29 30
f 31 32 33
f 34 35 36
f 1 1 2
f 3 3 3
";
    let material = r#"{"type": "diffuse", "albedo": [0.6, 0.6, 0.6]}"#;
    let clean = obj_furnace(&dir, "clean", &octahedron_obj(""), material);
    let dirty = obj_furnace(&dir, "dirty", &octahedron_obj(degenerate), material);
    assert_eq!(
        dirty.meshes.last().unwrap().triangles.len(),
        clean.meshes.last().unwrap().triangles.len() + 7
    );
    let (a, sa) = render_scene(&clean, 32, 6, 5);
    let (b, sb) = render_scene(&dirty, 32, 6, 5);
    assert_finite(&b, "degenerate triangles");
    assert_eq!((sa.dropped_samples, sb.dropped_samples), (0, 0));
    let worst = a
        .pixels
        .iter()
        .zip(&b.pixels)
        .flat_map(|(p, q)| (0..3).map(move |c| (p[c] - q[c]).abs()))
        .fold(0.0, f32::max);
    assert_eq!(
        worst, 0.0,
        "the degenerate triangles changed a pixel by {worst}"
    );
    // And the octahedron is really there: its centre pixel is darker than the walls.
    assert!(a.get(12, 12)[0] < 0.9);
    let _ = std::fs::remove_dir_all(&dir);
}

/// A two-sided albedo-1 sheet through the middle of a furnace, tilted so
/// that its points are not exactly representable, seen exactly edge-on
/// (camera in its plane, so the middle rows graze it), from a hair above
/// it, and from a camera lying on the sheet itself: every pixel is Le. A
/// ray that re-hits the surface it starts on, or slips through it, darkens
/// pixels.
#[test]
fn grazing_rays_and_cameras_on_a_surface_stay_exact() {
    let sheet = r#"{"quad": [[-2.8, 0, -2.8], [-2.8, 0, 2.8], [2.8, 0, 2.8], [2.8, 0, -2.8]]}"#;
    let json = furnace_scene(
        r#"{"type": "diffuse", "albedo": [1, 1, 1]}"#,
        1.0,
        3.0,
        sheet,
    );
    let mut v: Value = serde_json::from_str(&json).unwrap();
    let last = v["instances"].as_array().unwrap().len() - 1;
    v["instances"][last]["transform"] = json!({"rotate": {"axis": [1, 0.3, 0.2], "deg": 17}});
    let mut scene = scene_from_str(&v.to_string());
    scene.camera.width = 16;
    scene.camera.height = 16;
    let t = scene.instances.last().unwrap().transform;
    let p = |x: f32, y: f32, z: f32| t.point_to_world(glam::Vec3::new(x, y, z));
    let cams = [
        // In the sheet's plane, looking along it: the middle rows graze.
        (p(0.0, 0.0, -2.5), p(0.0, 0.0, 0.0)),
        // A hair above it, looking along it.
        (p(0.0, 1e-6, -2.5), p(0.3, 1e-6, 0.0)),
        // On the sheet, looking down into it at a slant, and up away from it.
        (p(0.1, 0.0, -1.0), p(0.4, -1.0, 0.5)),
        (p(0.1, 0.0, -1.0), p(0.4, 1.0, 0.5)),
    ];
    for (pos, look) in cams {
        scene.camera.position = pos;
        scene.camera.look_at = look;
        let (img, st) = render_scene(&scene, 64, 3, 9);
        assert_finite(&img, "grazing");
        assert_eq!(st.dropped_samples, 0);
        let m = luminance_mean(&img);
        assert!((m - 1.0).abs() < 0.01, "camera at {pos}: mean {m}");
        // Single pixels are noisy (NEE vs BSDF paths), but a systematic leak
        // or occlusion shows as a row far from 1.
        for y in 0..16 {
            let row: f32 = (0..16).map(|x| img.get(x, y)[0]).sum::<f32>() / 16.0;
            assert!(
                (row - 1.0).abs() < 0.06,
                "camera at {pos}: row {y} mean {row}"
            );
        }
    }
}

/// A thin albedo-1 slab (two sheets 1e-4 apart relative to a box of 6):
/// nearly coincident surfaces, where too large an offset would skip the
/// second sheet and too small one would re-hit the first.
#[test]
fn nearly_coincident_surfaces_stay_exact() {
    let slab = r#"{"box": {"min": [-1, -0.00005, -1], "max": [1, 0.00005, 1]}}"#;
    let json = furnace_scene(
        r#"{"type": "diffuse", "albedo": [1, 1, 1]}"#,
        1.0,
        3.0,
        slab,
    );
    let mut v: Value = serde_json::from_str(&json).unwrap();
    v["camera"]["position"] = json!([0, 1.5, -1.5]);
    let (img, st) = render_json(&v.to_string(), 64, 8, 4);
    assert_finite(&img, "slab");
    assert_eq!(st.dropped_samples, 0);
    let m = luminance_mean(&img);
    assert!((m - 1.0).abs() < 0.01, "mean {m}");
}

// ---------------------------------------------------------------------------
// Accumulation precision
// ---------------------------------------------------------------------------

/// 2x2 pixels at 65,536 samples each of a constant emitter (radiance 0.1,
/// not a binary fraction): each pixel is exactly the f32 radiance. An f32
/// accumulator would be off in the 4th digit by then.
#[test]
fn high_spp_constant_emitter_is_exact() {
    let mut v: Value = serde_json::from_str(&furnace_scene(
        r#"{"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}"#,
        0.1,
        3.0,
        SPHERE,
    ))
    .unwrap();
    // Look at a wall away from the sphere.
    v["camera"]["look_at"] = json!([0, 0, -10]);
    v["camera"]["width"] = json!(2);
    v["camera"]["height"] = json!(2);
    let (img, st) = render_json(&v.to_string(), 1 << 16, 0, 1);
    assert_eq!(st.samples, 4 << 16);
    for p in &img.pixels {
        assert_eq!(*p, [0.1f32; 3], "pixel drifted");
    }
    // What an f32 running sum would have given: visibly off.
    let mut s = 0.0f32;
    for _ in 0..1 << 16 {
        s += 0.1;
    }
    assert_ne!(
        s / (1 << 16) as f32,
        0.1,
        "the f32 control no longer drifts: pick another value"
    );
}

/// The accumulator itself over 10^8 samples: no drift, and non-finite
/// samples are counted, not averaged in.
#[test]
fn pixel_sum_does_not_drift_and_drops_non_finite() {
    let mut p = PixelSum::default();
    for i in 0..100_000_000u32 {
        p.add(glam::Vec3::new(
            0.1,
            1e-7,
            if i % 2 == 0 { 3.0 } else { 5.0 },
        ));
    }
    assert_eq!(p.mean(), [0.1, 1e-7, 4.0]);
    p.add(glam::Vec3::new(f32::NAN, 0.0, 0.0));
    p.add(glam::Vec3::new(0.0, f32::INFINITY, 0.0));
    p.add(glam::Vec3::new(0.0, 0.0, f32::NEG_INFINITY));
    assert_eq!(p.dropped, 3);
    assert_eq!(p.valid, 100_000_000);
    assert_eq!(p.mean(), [0.1, 1e-7, 4.0]);
    // All samples non-finite: black, not NaN.
    let mut q = PixelSum::default();
    q.add(glam::Vec3::NAN);
    assert_eq!(q.mean(), [0.0; 3]);
}

/// A long render's mean does not move as the sample count grows: a white
/// furnace at 256 and 4096 spp agrees with Le to within its noise.
#[test]
fn high_spp_mean_does_not_drift() {
    let mut v: Value = serde_json::from_str(&furnace_scene(
        r#"{"type": "diffuse", "albedo": [1, 1, 1]}"#,
        0.7,
        3.0,
        SPHERE,
    ))
    .unwrap();
    v["camera"]["width"] = json!(4);
    v["camera"]["height"] = json!(4);
    v["camera"]["fov_y_deg"] = json!(20);
    for spp in [256, 8192] {
        let (img, st) = render_json(&v.to_string(), spp, 4, 11);
        assert_eq!(st.dropped_samples, 0);
        let m = luminance_mean(&img);
        let tol = if spp == 256 { 5e-3 } else { 1e-3 };
        assert!((m / 0.7 - 1.0).abs() < tol, "{spp} spp: mean {m}, want 0.7");
    }
}

/// A vertex far away that no triangle uses (or only a zero-area one)
/// leaves the Cornell box's image bit for bit unchanged. It used to set the
/// scene's extent, and with it the ray-offset floor: a stray vertex at 1e9
/// made the box 24% brighter through light leaks.
#[test]
fn stray_far_vertices_change_nothing() {
    let dir = temp_dir("stray");
    let mut base = cornell_small(24);
    base["meshes"]["tri"] = json!({"obj": "tri.obj"});
    base["instances"]
        .as_array_mut()
        .unwrap()
        .push(json!({"mesh": "tri", "material": "white"}));
    let render = |obj: &str| {
        std::fs::write(dir.join("tri.obj"), obj).unwrap();
        let scene = nppp_scene::parse_scene(&base.to_string(), &dir.join("scene.json")).unwrap();
        render_scene(&scene, 32, 5, 7).0
    };
    let tri = "v 100 10 100\nv 150 10 100\nv 100 10 150\nf 1 3 2\n";
    let clean = render(tri);
    for extra in [
        "v 1e9 1e9 1e9\n",
        "v 1e9 1e9 1e9\nv 2e9 2e9 2e9\nv 3e9 3e9 3e9\nf 4 5 6\nf 1 4 4\n",
    ] {
        let img = render(&format!("{tri}{extra}"));
        assert!(
            img == clean,
            "{extra:?} changed the image: mean {:?} vs {:?}",
            img.mean(),
            clean.mean()
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// Smooth-shading normals that disagree wildly with the geometry (tangent,
/// inverted, random) on a diffuse and a glass object: never a NaN, nothing
/// dropped, and no energy from nowhere in a furnace.
#[test]
fn wild_shading_normals_stay_finite() {
    let dir = temp_dir("normals");
    let mut obj = octahedron_obj("");
    let normals = [
        [1.0, 0.0, 0.0],
        [0.0, -1.0, 0.0],
        [0.3, 0.3, -0.9],
        [1e-20, 0.0, 1e-20],
        [0.577, 0.577, 0.577],
    ];
    for n in normals {
        obj += &format!("vn {} {} {}\n", n[0], n[1], n[2]);
    }
    // Re-emit the faces with normals, cycling through the list.
    let faces: String = (0..8)
        .map(|i| {
            let v = |k: usize| format!("{}//{}", 3 * i + k + 1, (i + k) % normals.len() + 1);
            format!("f {} {} {}\n", v(0), v(1), v(2))
        })
        .collect();
    let obj = obj
        .lines()
        .filter(|l| !l.starts_with("f "))
        .collect::<Vec<_>>()
        .join("\n")
        + "\n"
        + &faces;
    std::fs::write(dir.join("wild.obj"), obj).unwrap();
    for material in [
        r#"{"type": "diffuse", "albedo": [1, 1, 1]}"#,
        r#"{"type": "dielectric", "ior": 1.5}"#,
        r#"{"type": "conductor", "reflectance": [1, 1, 1], "roughness": 0.3}"#,
    ] {
        let json = furnace_scene(material, 1.0, 3.0, r#"{"obj": "wild.obj", "smooth": true}"#);
        let scene = nppp_scene::parse_scene(&json, &dir.join("scene.json")).unwrap();
        let (img, st) = render_scene(&scene, 32, 16, 3);
        assert_finite(&img, material);
        assert_eq!(st.dropped_samples, 0, "{material}");
        let m = luminance_mean(&img);
        assert!(m > 0.5 && m < 1.05, "{material}: mean {m}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// Cameras at the edges of what the contract allows: a field of view of
/// 179.9 and 0.001 degrees, a 1024 x 1 strip and a single pixel.
#[test]
fn extreme_cameras_render_finite() {
    let json = furnace_scene(
        r#"{"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}"#,
        1.0,
        3.0,
        SPHERE,
    );
    let mut scene = scene_from_str(&json);
    for (fov, w, h) in [
        (179.9f32, 16, 16),
        (0.001, 4, 4),
        (60.0, 1024, 1),
        (60.0, 1, 1),
    ] {
        scene.camera.fov_y_deg = fov;
        scene.camera.width = w;
        scene.camera.height = h;
        let (img, st) = render_scene(&scene, 8, 4, 1);
        assert_finite(&img, &format!("fov {fov}, {w}x{h}"));
        assert_eq!(st.dropped_samples, 0);
        assert_eq!(img.pixels.len(), (w * h) as usize);
    }
    // Looking at the sphere's centre through a 0.001-degree pinhole: 0.5 Le.
    scene.camera.fov_y_deg = 0.001;
    scene.camera.width = 2;
    scene.camera.height = 2;
    let (img, _) = render_scene(&scene, 64, 4, 2);
    assert!(
        (luminance_mean(&img) - 0.5).abs() < 0.05,
        "{:?}",
        img.mean()
    );
}
