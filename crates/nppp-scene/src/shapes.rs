//! The built-in mesh sources of docs/scene-format.md (`quad`, `box`, `icosphere`)
//! as pure functions of already validated numbers. Vertex order and
//! triangle winding follow the contract exactly, because other renderers
//! compare images against ours and the front side of an emitter or a
//! dielectric depends on the winding.

use crate::Mesh;
use glam::{DVec3, Vec3};
use std::collections::HashMap;

/// The deepest icosphere the format allows: level 8 is 1.3 million triangles.
pub const MAX_ICOSPHERE_SUBDIVISIONS: u32 = 8;

/// The contract's split of a quad: (0,1,2) and (0,2,3), so the front side is
/// the one `(p1-p0) x (p2-p0)` points to.
pub fn quad_mesh(p: [Vec3; 4]) -> Mesh {
    Mesh {
        positions: p.to_vec(),
        triangles: vec![[0, 1, 2], [0, 2, 3]],
        shading_normals: None,
    }
}

/// An axis-aligned box with its 12 triangles wound counter-clockwise seen
/// from outside. Corner `i` takes `max` on axis k when bit k of `i` is set.
pub fn box_mesh(min: Vec3, max: Vec3) -> Mesh {
    let positions = (0..8u32)
        .map(|i| {
            Vec3::new(
                if i & 1 != 0 { max.x } else { min.x },
                if i & 2 != 0 { max.y } else { min.y },
                if i & 4 != 0 { max.z } else { min.z },
            )
        })
        .collect();
    // Each face as a counter-clockwise quad seen from outside.
    const FACES: [[u32; 4]; 6] = [
        [0, 4, 6, 2], // -x
        [1, 3, 7, 5], // +x
        [0, 1, 5, 4], // -y
        [2, 6, 7, 3], // +y
        [0, 2, 3, 1], // -z
        [4, 5, 7, 6], // +z
    ];
    let triangles = FACES
        .iter()
        .flat_map(|&[a, b, c, d]| [[a, b, c], [a, c, d]])
        .collect();
    Mesh {
        positions,
        triangles,
        shading_normals: None,
    }
}

/// The contract's unit icosphere in f64, vertex order and winding as the
/// contract gives them (the `icosphere` shape, and the procedural displaced
/// sphere, which displaces its vertices before rounding). `subdivisions` is
/// not clamped: callers check it.
pub(crate) fn unit_icosphere(subdivisions: u32) -> (Vec<DVec3>, Vec<[u32; 3]>) {
    let t = (1.0 + 5f64.sqrt()) / 2.0;
    let mut verts: Vec<DVec3> = [
        (-1.0, t, 0.0),
        (1.0, t, 0.0),
        (-1.0, -t, 0.0),
        (1.0, -t, 0.0),
        (0.0, -1.0, t),
        (0.0, 1.0, t),
        (0.0, -1.0, -t),
        (0.0, 1.0, -t),
        (t, 0.0, -1.0),
        (t, 0.0, 1.0),
        (-t, 0.0, -1.0),
        (-t, 0.0, 1.0),
    ]
    .iter()
    .map(|&(x, y, z)| DVec3::new(x, y, z).normalize())
    .collect();
    let mut tris: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..subdivisions {
        // Midpoints are shared between the two triangles of an edge, so the
        // sphere stays watertight; keyed by the unordered edge.
        let mut midpoints: HashMap<(u32, u32), u32> = HashMap::with_capacity(tris.len() * 3 / 2);
        let mut midpoint = |a: u32, b: u32, verts: &mut Vec<DVec3>| -> u32 {
            let key = (a.min(b), a.max(b));
            *midpoints.entry(key).or_insert_with(|| {
                let m = ((verts[a as usize] + verts[b as usize]) * 0.5).normalize();
                verts.push(m);
                (verts.len() - 1) as u32
            })
        };
        let mut next = Vec::with_capacity(tris.len() * 4);
        for &[a, b, c] in &tris {
            let ab = midpoint(a, b, &mut verts);
            let bc = midpoint(b, c, &mut verts);
            let ca = midpoint(c, a, &mut verts);
            next.extend_from_slice(&[[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
        }
        tris = next;
    }
    (verts, tris)
}

/// The contract's icosphere. Computed in f64 and rounded once at the end so
/// that an implementation in any language lands on the same f32 positions
/// (up to the last bit), whatever order it does the arithmetic in.
/// `subdivisions` must already be checked against
/// [`MAX_ICOSPHERE_SUBDIVISIONS`]; larger values are clamped so that no
/// input can make this allocate without bound.
pub fn icosphere_mesh(center: Vec3, radius: f32, subdivisions: u32) -> Mesh {
    let (verts, tris) = unit_icosphere(subdivisions.min(MAX_ICOSPHERE_SUBDIVISIONS));
    let c = center.as_dvec3();
    let r = f64::from(radius);
    Mesh {
        positions: verts.iter().map(|v| (c + r * *v).as_vec3()).collect(),
        triangles: tris,
        shading_normals: None,
    }
}
