//! OBJ faces in every form docs/scene-format.md lists, fan triangulation in file
//! order, and the `smooth` switch.

mod common;

use common::obj_mesh;
use glam::Vec3;

const SQUARE: &str = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\n";

#[test]
fn plain_vertex_indices() {
    let m = obj_mesh(&format!("{SQUARE}f 1 2 3\n"), false).expect("loads");
    assert_eq!(
        m.positions,
        [Vec3::ZERO, Vec3::X, Vec3::new(1.0, 1.0, 0.0), Vec3::Y]
    );
    assert_eq!(m.triangles, [[0, 1, 2]]);
    assert!(m.shading_normals.is_none());
}

#[test]
fn vertex_slash_texcoord() {
    let m = obj_mesh(
        &format!("{SQUARE}vt 0 0\nvt 1 0\nvt 1 1\nf 1/1 2/2 3/3\n"),
        false,
    )
    .expect("loads");
    assert_eq!(m.triangles, [[0, 1, 2]]);
}

#[test]
fn vertex_double_slash_normal() {
    let m = obj_mesh(&format!("{SQUARE}vn 0 0 1\nf 1//1 3//1 4//1\n"), false).expect("loads");
    assert_eq!(m.triangles, [[0, 2, 3]]);
    assert!(
        m.shading_normals.is_none(),
        "normals are used only with smooth: true"
    );
}

#[test]
fn vertex_texcoord_normal() {
    let text = format!("{SQUARE}vt 0 0\nvn 0 0 2\nvn 0 3 4\nf 2/1/1 3/1/2 4/1/1\n");
    let m = obj_mesh(&text, true).expect("loads");
    assert_eq!(m.triangles, [[1, 2, 3]]);
    // Normals come back per triangle corner and normalized.
    assert_eq!(
        m.shading_normals,
        Some(vec![[Vec3::Z, Vec3::new(0.0, 0.6, 0.8), Vec3::Z]])
    );
}

#[test]
fn negative_indices_are_relative_to_what_is_defined_so_far() {
    let text = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf -3 -2 -1\nv 5 5 5\nf -4 -1 -2\nvn 0 0 1\nf 1//-1 2//-1 3//-1\n";
    let m = obj_mesh(text, false).expect("loads");
    assert_eq!(m.triangles, [[0, 1, 2], [0, 3, 2], [0, 1, 2]]);
}

#[test]
fn pentagon_is_fan_triangulated_in_order() {
    let text = "v 0 0 0\nv 2 0 0\nv 3 1 0\nv 1 2 0\nv -1 1 0\nf 1 2 3 4 5\n";
    let m = obj_mesh(text, false).expect("loads");
    assert_eq!(m.triangles, [[0, 1, 2], [0, 2, 3], [0, 3, 4]]);
    // The fan starts at the face's first vertex even when it is not index 1.
    let m = obj_mesh(
        "v 0 0 0\nv 2 0 0\nv 3 1 0\nv 1 2 0\nv -1 1 0\nf 3 4 5 1 2\n",
        false,
    )
    .expect("loads");
    assert_eq!(m.triangles, [[2, 3, 4], [2, 4, 0], [2, 0, 1]]);
}

#[test]
fn smooth_polygon_normals_follow_the_fan() {
    let text = format!("{SQUARE}vn 1 0 0\nvn 0 1 0\nvn 0 0 1\nvn 0 0 -1\nf 1//1 2//2 3//3 4//4\n");
    let m = obj_mesh(&text, true).expect("loads");
    assert_eq!(m.triangles, [[0, 1, 2], [0, 2, 3]]);
    assert_eq!(
        m.shading_normals,
        Some(vec![
            [Vec3::X, Vec3::Y, Vec3::Z],
            [Vec3::X, Vec3::Z, Vec3::NEG_Z]
        ])
    );
}

#[test]
fn mixed_forms_and_ignored_statements() {
    let text = "# exported by hand\r\n\
        mtllib scene.mtl\r\n\
        o thing\r\n\
        g group1\r\n\
        s 1\r\n\
        usemtl gold\r\n\
        v 0 0 0 1.0\r\n\
        v 1 0 0 0.5 0.5 0.5\r\n\
        v 1 1 0\r\n\
        v 0 1 0 # trailing comment\r\n\
        vt 0 0\r\n\
        vn 0 0 1\r\n\
        l 1 2\r\n\
        p 3\r\n\
        \r\n\
        f 1 2/1 3//1 4/1/1\r\n";
    let m = obj_mesh(text, false).expect("loads");
    assert_eq!(m.positions.len(), 4);
    assert_eq!(m.positions[3], Vec3::Y);
    assert_eq!(m.triangles, [[0, 1, 2], [0, 2, 3]]);
}

#[test]
fn degenerate_triangles_are_kept() {
    // Zero area (repeated and collinear vertices): the renderer must cope,
    // and dropping them would change the file's triangle numbering.
    let text = "v 0 0 0\nv 1 0 0\nv 2 0 0\nv 0 1 0\nf 1 2 3\nf 1 1 4\nf 1 2 4\n";
    let m = obj_mesh(text, false).expect("loads");
    assert_eq!(m.triangles, [[0, 1, 2], [0, 0, 3], [0, 1, 3]]);
}

#[test]
fn positive_indices_may_refer_forward() {
    let m = obj_mesh("f 1 2 3\nv 0 0 0\nv 1 0 0\nv 0 1 0\n", false).expect("loads");
    assert_eq!(m.triangles, [[0, 1, 2]]);
}

#[test]
fn winding_is_kept_as_written() {
    let m = obj_mesh(&format!("{SQUARE}f 1 2 3\nf 3 2 1\n"), false).expect("loads");
    assert_eq!(m.triangles, [[0, 1, 2], [2, 1, 0]]);
}

#[test]
fn procedural_obj_export_round_trips_through_the_loader_bit_for_bit() {
    use nppp_scene::procedural::{Procedural, write_obj};
    let built = Procedural::TorusKnot {
        p: 2,
        q: 3,
        tube_radius: 0.4,
        segments: 48,
        sides: 6,
    }
    .build()
    .expect("builds");
    let dir = common::scratch_dir("roundtrip");
    let obj = dir.join("meshes/m.obj");
    write_obj(&built, &obj, true).expect("write");
    let text = std::fs::read_to_string(&obj).expect("read back");
    let _ = std::fs::remove_dir_all(&dir);
    let m = obj_mesh(&text, false).expect("loads");
    assert_eq!(m.positions, built.positions);
    assert_eq!(m.triangles, built.triangles);
}

#[test]
fn bare_cr_line_endings_load_like_lf() {
    let lf = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n";
    let cr = lf.replace('\n', "\r");
    let a = obj_mesh(lf, false).expect("LF loads");
    let b = obj_mesh(&cr, false).expect("bare CR loads");
    assert_eq!(a.positions, b.positions);
    assert_eq!(a.triangles, b.triangles);
}

#[test]
fn smooth_normals_near_f32_max_are_directions_not_zero() {
    let text = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 3e38 3e38 3e38\nf 1//1 2//1 3//1\n";
    let m = obj_mesh(text, true).expect("loads");
    let n = m.shading_normals.expect("smooth")[0][0];
    assert!(
        (n - glam::Vec3::splat(1.0 / 3f32.sqrt())).length() < 1e-6,
        "{n}"
    );
}

#[test]
fn a_byte_order_mark_does_not_hide_the_first_line() {
    // Before: the mark made the first `v` line unknown, so a vertex was
    // silently dropped and every later index meant another vertex.
    let m = obj_mesh(&format!("\u{feff}{SQUARE}f 1 2 3\n"), false).expect("loads");
    assert_eq!(m.positions.len(), 4);
    assert_eq!(m.positions[0], Vec3::ZERO);
    assert_eq!(m.triangles, [[0, 1, 2]]);
}
