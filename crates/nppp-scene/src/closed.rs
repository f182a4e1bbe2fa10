//! Whether a mesh encloses a volume: the check a `translucent` mesh must pass,
//! since its medium is "inside" only if the boundary has no holes.

use crate::Mesh;
use glam::Vec3;
use std::collections::HashMap;

/// Why a mesh does not bound a volume: one offending edge, by its end points
/// (vertices at one position count as one, as OBJ files split vertices at
/// seams of normals or texture coordinates; -0 and 0 are one coordinate).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OpenEdge {
    pub from: Vec3,
    pub to: Vec3,
    /// Triangles using the edge in this direction.
    pub uses: u32,
    /// Triangles using it the other way round.
    pub reverse_uses: u32,
}

/// `None` when the mesh is closed and consistently oriented: every directed
/// edge is used by exactly one triangle and its reverse by exactly one other.
/// Degenerate triangles (two corners at one position) are ignored: they
/// enclose nothing.
pub fn open_edge(mesh: &Mesh) -> Option<OpenEdge> {
    // Bit patterns, with -0 made 0 (adding 0 does that, and nothing else):
    // a cube with one seam vertex written `-0` was called open.
    let key = |p: Vec3| [p.x, p.y, p.z].map(|c| (c + 0.0).to_bits());
    let mut welded: HashMap<[u32; 3], u32> = HashMap::with_capacity(mesh.positions.len());
    let ids: Vec<u32> = mesh
        .positions
        .iter()
        .map(|&p| {
            let n = welded.len() as u32;
            *welded.entry(key(p)).or_insert(n)
        })
        .collect();
    let mut edges: HashMap<(u32, u32), (u32, [u32; 2])> =
        HashMap::with_capacity(mesh.triangles.len() * 3);
    for t in &mesh.triangles {
        let v = t.map(|i| ids[i as usize]);
        if v[0] == v[1] || v[1] == v[2] || v[2] == v[0] {
            continue;
        }
        for k in 0..3 {
            let e = edges
                .entry((v[k], v[(k + 1) % 3]))
                .or_insert((0, [t[k], t[(k + 1) % 3]]));
            e.0 += 1;
        }
    }
    let mut bad: Vec<OpenEdge> = edges
        .iter()
        .filter_map(|(&(a, b), &(uses, [pa, pb]))| {
            let reverse_uses = edges.get(&(b, a)).map_or(0, |r| r.0);
            (uses != 1 || reverse_uses != 1).then(|| OpenEdge {
                from: mesh.positions[pa as usize],
                to: mesh.positions[pb as usize],
                uses,
                reverse_uses,
            })
        })
        .collect();
    // The same answer every run (hash maps iterate in random order).
    bad.sort_by(|x, y| {
        let k = |e: &OpenEdge| [e.from.x, e.from.y, e.from.z, e.to.x, e.to.y, e.to.z];
        k(x).partial_cmp(&k(y)).unwrap_or(std::cmp::Ordering::Equal)
    });
    bad.first().copied()
}

impl std::fmt::Display for OpenEdge {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let p = |v: Vec3| format!("[{}, {}, {}]", v.x, v.y, v.z);
        let what = match (self.uses, self.reverse_uses) {
            (1, 0) => "is a border (a hole: no triangle on its other side)".to_string(),
            (u, r) if u > 1 && r == 0 => {
                format!("is used {u} times in the same direction (inconsistent winding)")
            }
            (u, r) => format!("is shared by {} triangles (non-manifold)", u + r),
        };
        write!(f, "the edge from {} to {} {what}", p(self.from), p(self.to))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{box_mesh, icosphere_mesh, quad_mesh};

    #[test]
    fn closed_shapes_pass() {
        assert_eq!(open_edge(&icosphere_mesh(Vec3::ZERO, 1.0, 2)), None);
        assert_eq!(open_edge(&box_mesh(Vec3::splat(-1.0), Vec3::ONE)), None);
        for object in crate::procedural::Procedural::defaults() {
            let m = object.build().unwrap();
            let mesh = Mesh {
                positions: m.positions,
                triangles: m.triangles,
                shading_normals: None,
            };
            assert_eq!(open_edge(&mesh), None, "{}", object.name());
        }
    }

    #[test]
    fn a_quad_is_open_and_a_missing_triangle_is_a_hole() {
        let q = quad_mesh([Vec3::ZERO, Vec3::X, Vec3::new(1.0, 1.0, 0.0), Vec3::Y]);
        let e = open_edge(&q).unwrap();
        assert_eq!((e.uses, e.reverse_uses), (1, 0));
        let mut s = icosphere_mesh(Vec3::ZERO, 1.0, 1);
        s.triangles.pop();
        assert!(open_edge(&s).unwrap().to_string().contains("hole"));
    }

    #[test]
    fn a_flipped_triangle_is_inconsistent() {
        let mut s = icosphere_mesh(Vec3::ZERO, 1.0, 1);
        s.triangles[0].swap(1, 2);
        let e = open_edge(&s).unwrap();
        assert!(e.uses == 2 || e.reverse_uses == 0, "{e:?}");
    }

    #[test]
    fn split_vertices_at_one_position_are_welded() {
        // Every triangle with its own three vertices, as OBJ files with
        // per-face normals come.
        let s = icosphere_mesh(Vec3::ZERO, 1.0, 1);
        let mut split = Mesh::default();
        for t in &s.triangles {
            let n = split.positions.len() as u32;
            split
                .positions
                .extend(t.iter().map(|&i| s.positions[i as usize]));
            split.triangles.push([n, n + 1, n + 2]);
        }
        assert_eq!(open_edge(&split), None);
        // One copy of a vertex at 0 written as -0.
        let at_zero = split
            .positions
            .iter()
            .position(|p| p.x == 0.0)
            .expect("an icosphere has vertices at x = 0");
        split.positions[at_zero].x = -0.0;
        assert_eq!(open_edge(&split), None);
    }
}
