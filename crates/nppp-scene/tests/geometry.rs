//! Mesh sources and transforms against the conventions of docs/scene-format.md.

mod common;

use common::{FILE, base, parse};
use glam::{DVec3, Vec3};
use nppp_scene::{Mesh, box_mesh, icosphere_mesh, parse_scene, quad_mesh};
use serde_json::json;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

fn tri(m: &Mesh, t: usize) -> [Vec3; 3] {
    m.triangles[t].map(|i| m.positions[i as usize])
}

fn normal(m: &Mesh, t: usize) -> Vec3 {
    let [a, b, c] = tri(m, t);
    (b - a).cross(c - a)
}

/// Every directed edge appears once and its reverse once: closed and
/// consistently wound.
fn assert_watertight(m: &Mesh) {
    let mut edges: HashMap<(u32, u32), usize> = HashMap::new();
    for t in &m.triangles {
        for k in 0..3 {
            *edges.entry((t[k], t[(k + 1) % 3])).or_default() += 1;
        }
    }
    for (&(a, b), &n) in &edges {
        assert_eq!(n, 1, "directed edge {a}->{b} used {n} times");
        assert_eq!(
            edges.get(&(b, a)),
            Some(&1),
            "edge {a}->{b} has no opposite"
        );
    }
}

// ---------------------------------------------------------------- icosphere

#[test]
fn icosphere_counts_follow_20_times_4_to_the_n() {
    for n in 0..=5u32 {
        let m = icosphere_mesh(Vec3::ZERO, 1.0, n);
        assert_eq!(m.triangles.len(), 20 * 4usize.pow(n), "level {n}");
        // Shared midpoints: V = 10 * 4^n + 2 (Euler, closed genus 0).
        assert_eq!(m.positions.len(), 10 * 4usize.pow(n) + 2, "level {n}");
        assert_watertight(&m);
    }
}

#[test]
fn icosphere_level_8_is_allowed_and_has_1310720_triangles() {
    let m = icosphere_mesh(Vec3::ZERO, 1.0, 8);
    assert_eq!(m.triangles.len(), 1_310_720);
}

#[test]
fn icosphere_vertices_lie_on_the_sphere_and_faces_point_out() {
    let center = Vec3::new(1.0, -2.0, 3.5);
    let radius = 2.5;
    for n in 0..=4 {
        let m = icosphere_mesh(center, radius, n);
        for p in &m.positions {
            let d = (*p - center).length();
            assert!(
                (d - radius).abs() < 1e-5 * radius,
                "level {n}: |p - c| = {d}"
            );
        }
        for t in 0..m.triangles.len() {
            let [a, b, c] = tri(&m, t);
            let centroid = (a + b + c) / 3.0;
            assert!(
                normal(&m, t).dot(centroid - center) > 0.0,
                "level {n} triangle {t} faces in"
            );
        }
    }
}

#[test]
fn icosphere_level_0_has_the_contracts_vertices() {
    let t = (1.0 + 5f64.sqrt()) / 2.0;
    let mut want = Vec::new();
    for s1 in [-1.0, 1.0] {
        for s2 in [-1.0, 1.0] {
            want.push(DVec3::new(s1, s2 * t, 0.0));
            want.push(DVec3::new(0.0, s1, s2 * t));
            want.push(DVec3::new(s2 * t, 0.0, s1));
        }
    }
    let m = icosphere_mesh(Vec3::ZERO, 1.0, 0);
    assert_eq!(m.positions.len(), 12);
    for w in want {
        let w = w.normalize().as_vec3();
        assert!(m.positions.contains(&w), "missing vertex {w}");
    }
    // Every face is an equilateral triangle of the icosahedron (edge 1.0515).
    let edge = 4.0 / (10.0 + 2.0 * 5f32.sqrt()).sqrt();
    for i in 0..20 {
        let [a, b, c] = tri(&m, i);
        for l in [(b - a).length(), (c - b).length(), (a - c).length()] {
            assert!((l - edge).abs() < 1e-5, "edge {l} vs {edge}");
        }
    }
}

#[test]
fn icosphere_subdivision_rule_and_projection_order() {
    // (a, b, c) -> (a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca), with
    // each midpoint projected onto the unit sphere as soon as it is made.
    let m0 = icosphere_mesh(Vec3::ZERO, 1.0, 0);
    let m1 = icosphere_mesh(Vec3::ZERO, 1.0, 1);
    let m2 = icosphere_mesh(Vec3::ZERO, 1.0, 2);
    let mid = |p: Vec3, q: Vec3| ((p.as_dvec3() + q.as_dvec3()) * 0.5).normalize();
    for (parent_mesh, child_mesh) in [(&m0, &m1), (&m1, &m2)] {
        for f in 0..parent_mesh.triangles.len() {
            let [a, b, c] = tri(parent_mesh, f);
            let (ab, bc, ca) = (mid(a, b), mid(b, c), mid(c, a));
            let want = [
                [a.as_dvec3(), ab, ca],
                [b.as_dvec3(), bc, ab],
                [c.as_dvec3(), ca, bc],
                [ab, bc, ca],
            ];
            for (k, w) in want.iter().enumerate() {
                let got = tri(child_mesh, 4 * f + k);
                for (g, w) in got.iter().zip(w) {
                    assert!(
                        (g.as_dvec3() - *w).length() < 1e-6,
                        "face {f} child {k}: {g} vs {w}"
                    );
                }
            }
        }
    }
}

#[test]
fn icosphere_from_scene_uses_center_and_radius() {
    let mut v = base();
    v["meshes"]["ball"]["icosphere"] =
        json!({"center": [1, 2, 3], "radius": 0.5, "subdivisions": 2});
    let s = parse(&v).expect("loads");
    let i = s.mesh_names.iter().position(|n| n == "ball").expect("ball");
    let m = &s.meshes[i];
    assert_eq!(m.triangles.len(), 320);
    assert!(m.shading_normals.is_none(), "icospheres are flat shaded");
    for p in &m.positions {
        assert!(((*p - Vec3::new(1.0, 2.0, 3.0)).length() - 0.5).abs() < 1e-6);
    }
}

// ---------------------------------------------------------------- box

#[test]
fn box_has_12_outward_triangles_covering_its_surface() {
    let (min, max) = (Vec3::new(100.0, 0.0, 100.0), Vec3::new(200.0, 150.0, 220.0));
    let m = box_mesh(min, max);
    assert_eq!(m.triangles.len(), 12);
    assert_eq!(m.positions.len(), 8);
    assert_watertight(&m);
    let center = (min + max) / 2.0;
    let mut area_per_axis = [0f32; 6];
    for t in 0..12 {
        let n = normal(&m, t);
        let [a, b, c] = tri(&m, t);
        let centroid = (a + b + c) / 3.0;
        assert!(n.dot(centroid - center) > 0.0, "triangle {t} faces in");
        // Axis aligned: exactly one non-zero component.
        assert_eq!(n.to_array().iter().filter(|x| **x != 0.0).count(), 1, "{n}");
        let axis = n.abs().max_position();
        let side = usize::from(n[axis] > 0.0);
        area_per_axis[2 * axis + side] += n.length() / 2.0;
    }
    let size = max - min;
    let want = [size.y * size.z, size.x * size.z, size.x * size.y];
    for (k, got) in area_per_axis.iter().enumerate() {
        assert!((got - want[k / 2]).abs() < 1e-2, "face {k}: area {got}");
    }
}

// ---------------------------------------------------------------- quad

#[test]
fn quad_splits_into_012_and_023_with_the_contracts_normal() {
    let p = [
        Vec3::new(0.0, 0.0, 0.0),
        Vec3::new(0.0, 0.0, 559.0),
        Vec3::new(556.0, 0.0, 559.0),
        Vec3::new(556.0, 0.0, 0.0),
    ];
    let m = quad_mesh(p);
    assert_eq!(m.positions, p);
    assert_eq!(m.triangles, [[0, 1, 2], [0, 2, 3]]);
    // The Cornell floor: (p1-p0) x (p2-p0) = +y, the room's inside.
    let front = (p[1] - p[0]).cross(p[2] - p[0]).normalize();
    assert_eq!(front, Vec3::Y);
    for t in 0..2 {
        assert!(normal(&m, t).normalize().dot(front) > 0.999);
    }
    // Through the loader, with the point order kept.
    let s = parse(&base()).expect("loads");
    let i = s
        .mesh_names
        .iter()
        .position(|n| n == "floor")
        .expect("floor");
    assert_eq!(s.meshes[i], m);
}

#[test]
fn quad_reversed_points_face_the_other_way() {
    let p = [Vec3::ZERO, Vec3::X, Vec3::new(1.0, 1.0, 0.0), Vec3::Y];
    let m = quad_mesh(p);
    assert!(normal(&m, 0).z > 0.0 && normal(&m, 1).z > 0.0);
    let mut r = p;
    r.reverse();
    let m = quad_mesh(r);
    assert!(normal(&m, 0).z < 0.0 && normal(&m, 1).z < 0.0);
}

#[test]
fn non_planar_quad_is_two_triangles_not_an_error() {
    let mut v = base();
    v["meshes"]["floor"]["quad"] = json!([[0, 0, 0], [1, 0, 0], [1, 1, 0.3], [0, 1, 0]]);
    parse(&v).expect("a slightly non-planar quad is well defined by the split rule");
}

// ---------------------------------------------------------------- transforms

fn transform_of(t: serde_json::Value) -> nppp_scene::Transform {
    let mut v = base();
    v["instances"] = json!([{"mesh": "floor", "material": "white", "transform": t}]);
    parse(&v).expect("loads").instances[0].transform
}

fn close(a: Vec3, b: Vec3) -> bool {
    (a - b).length() < 1e-6
}

#[test]
fn rotation_about_y_by_90_sends_x_to_minus_z() {
    let t = transform_of(json!({"rotate": {"axis": [0, 1, 0], "deg": 90}}));
    let p = t.point_to_world(Vec3::X);
    assert!(close(p, Vec3::new(0.0, 0.0, -1.0)), "{p}");
}

#[test]
fn rotation_is_right_handed_about_every_axis() {
    let cases = [
        ([0, 0, 1], Vec3::X, Vec3::Y),
        ([1, 0, 0], Vec3::Y, Vec3::Z),
        ([0, 1, 0], Vec3::Z, Vec3::X),
    ];
    for (axis, from, to) in cases {
        let t = transform_of(json!({"rotate": {"axis": axis, "deg": 90}}));
        let p = t.point_to_world(from);
        assert!(close(p, to), "axis {axis:?}: {from} -> {p}, expected {to}");
    }
}

#[test]
fn rotation_axis_is_normalized() {
    let a = transform_of(json!({"rotate": {"axis": [0, 7.5, 0], "deg": 30}}));
    let b = transform_of(json!({"rotate": {"axis": [0, 1, 0], "deg": 30}}));
    assert!((a.rotation.dot(b.rotation) - 1.0).abs() < 1e-6);
    assert!(a.rotation.is_normalized());
    let c = transform_of(json!({"rotate": {"axis": [1, 1, 1], "deg": 120}}));
    // 120 degrees about the diagonal cycles the axes x -> y -> z.
    assert!(close(c.point_to_world(Vec3::X), Vec3::Y));
}

#[test]
fn transform_scales_then_rotates_then_translates() {
    let t = transform_of(json!({
        "scale": 2, "rotate": {"axis": [0, 0, 1], "deg": 90}, "translate": [1, 2, 3]
    }));
    // (1,0,0) -> scale (2,0,0) -> rotate (0,2,0) -> translate (1,4,3).
    let p = t.point_to_world(Vec3::X);
    assert!(close(p, Vec3::new(1.0, 4.0, 3.0)), "{p}");
    assert!(close(t.point_to_object(p), Vec3::X));
    assert_eq!(t.scale, 2.0);
    assert_eq!(t.translation, Vec3::new(1.0, 2.0, 3.0));
}

#[test]
fn transform_defaults() {
    let identity = nppp_scene::Transform::default();
    assert_eq!(transform_of(json!({})), identity);
    let s = transform_of(json!({"scale": 3}));
    assert_eq!(
        (s.scale, s.rotation, s.translation),
        (3.0, identity.rotation, Vec3::ZERO)
    );
    let tr = transform_of(json!({"translate": [1, 2, 3]}));
    assert_eq!((tr.scale, tr.rotation), (1.0, identity.rotation));
    // No transform key at all.
    let s = parse(&base()).expect("loads");
    assert_eq!(s.instances[0].transform, identity);
}

// ---------------------------------------------------------------- scene-level

#[test]
fn up_defaults_to_plus_y_and_render_keys_default() {
    let mut v = base();
    v["camera"].as_object_mut().expect("camera").remove("up");
    v.as_object_mut().expect("top").remove("render");
    let s = parse(&v).expect("loads");
    assert_eq!(s.camera.up, Vec3::Y);
    assert_eq!(s.render, nppp_scene::RenderSettings::default());
    let mut v = base();
    v["render"] = json!({"seed": 18446744073709551615u64});
    let s = parse(&v).expect("loads");
    assert_eq!(s.render.seed, u64::MAX, "seeds are exact 64-bit integers");
    assert_eq!(s.render.spp, 64);
    assert_eq!(s.render.max_bounces, 5);
    assert_eq!(s.render.estimator_min_bounces, 2);
    let mut v = base();
    v["render"] = json!({"spp": 16.0, "max_bounces": 0});
    let s = parse(&v).expect("integral floats are integers");
    assert_eq!((s.render.spp, s.render.max_bounces), (16, 0));
}

#[test]
fn empty_instances_are_allowed() {
    let mut v = base();
    v["instances"] = json!([]);
    let s = parse(&v).expect("an empty scene renders black");
    assert!(s.instances.is_empty());
    let text = r#"{"camera": {"position": [0,0,0], "look_at": [0,0,-1], "fov_y_deg": 60,
                   "width": 4, "height": 4}, "materials": {}, "meshes": {}, "instances": []}"#;
    parse_scene(text, Path::new(FILE)).expect("minimal scene");
}

#[test]
fn names_keep_file_order_and_instances_resolve_to_indices() {
    let text = r#"{
      "camera": {"position": [0,0,5], "look_at": [0,0,0], "fov_y_deg": 45, "width": 8, "height": 8},
      "materials": {"zeta": {"type": "dielectric", "ior": 1.33},
                    "alpha": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}},
      "meshes": {"z": {"box": {"min": [0,0,0], "max": [1,1,1]}},
                 "a": {"quad": [[0,0,0],[1,0,0],[1,1,0],[0,1,0]]}},
      "instances": [{"mesh": "a", "material": "zeta"}, {"mesh": "z", "material": "alpha"}]
    }"#;
    let s = parse_scene(text, Path::new(FILE)).expect("loads");
    assert_eq!(s.material_names, ["zeta", "alpha"]);
    assert_eq!(s.mesh_names, ["z", "a"]);
    assert_eq!((s.instances[0].mesh, s.instances[0].material), (1, 0));
    assert_eq!((s.instances[1].mesh, s.instances[1].material), (0, 1));
    assert_eq!(s.path, PathBuf::from(FILE));
}

#[test]
fn estimator_path_is_relative_to_the_scene_folder() {
    let s = parse(&base()).expect("loads");
    assert_eq!(
        s.instances[1].estimator,
        Some(PathBuf::from("scenes/models/block-gold.nppp"))
    );
    assert_eq!(s.instances[0].estimator, None);
    // A bare file name resolves against the current directory.
    let s = parse_scene(&base().to_string(), Path::new("scene.json")).expect("loads");
    assert_eq!(
        s.instances[1].estimator,
        Some(PathBuf::from("models/block-gold.nppp"))
    );
}

#[test]
fn procedural_meshes_load_with_defaults_and_overrides() {
    let mut v = base();
    v["meshes"]["sponge"] = json!({"procedural": {"type": "menger_sponge", "level": 1}});
    v["meshes"]["knot"] = json!({"procedural": {"type": "torus_knot", "segments": 64, "sides": 6}});
    v["meshes"]["bumpy"] =
        json!({"procedural": {"type": "displaced_sphere", "subdivisions": 2, "seed": 9}});
    let s = parse(&v).expect("loads");
    let get = |name: &str| &s.meshes[s.mesh_names.iter().position(|n| n == name).expect(name)];
    let sponge = get("sponge");
    assert!(!sponge.triangles.is_empty());
    assert_eq!(get("knot").triangles.len(), 2 * 64 * 6);
    assert_eq!(get("bumpy").triangles.len(), 320);
    for m in [sponge, get("knot"), get("bumpy")] {
        assert!(m.shading_normals.is_none());
        assert!(
            m.triangles
                .iter()
                .flatten()
                .all(|&i| (i as usize) < m.positions.len())
        );
    }
}
