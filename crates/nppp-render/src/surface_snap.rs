//! Moving a network's picked vertex onto the object's real surface before
//! its light sample.
//!
//! The vertex head predicts where the skipped path scattered, but its
//! positions scatter around the surface (0.06-0.08 sphere radii from the
//! nearest real vertex on the knot's held-out rays). A light sample taken
//! from a point inside the object is shadowed by the object itself, and one
//! from a point floating above it sees light the real surface does not, so
//! how wrong the image is depended on where the light came from: a fixed
//! push along the predicted normal (`NETWORK_VERTEX_OFFSET`) suited the
//! Cornell box's ceiling lamp, and a knot lit from the side rendered 25%
//! dark at P = 0 (BENCHMARKS.md, "The picked vertex on the real surface").
//! Moved onto the real mesh (and lifted 0.01 radii off it along the real
//! normal: see `SURFACE_VERTEX_LIFT`), the vertex takes its light sample
//! where a real path could have scattered, with the real normals, and the
//! object shadows it as it would a real vertex (but for creases and
//! contacts narrower than the lift).
//!
//! The closest point comes from a grid over the sphere's cube that stores,
//! per cell, the triangle closest to the cell's centre (cells farther than
//! [`REACH`] from the surface store none), built by jump flooding from the
//! cells the triangles cross. A lookup reads one cell and one triangle and
//! projects the point onto it: the answer is always a point of the mesh,
//! at most about two cells farther from the vertex than the mesh's
//! closest point (where two sheets are equally near, it may be on the
//! other one: `network_skipped` refuses a point that faces away).

use glam::{UVec3, Vec3};
use nppp_geom::BoundingSphere;
use nppp_geom::closest_point::closest_point_on_triangle;
use nppp_scene::Mesh;
use rayon::prelude::*;

/// Cells per axis of the grid over the sphere's cube: cells of 1/32 of
/// the radius (the knot's tube is about 0.2 radii thick).
pub const RESOLUTION: u32 = 64;
/// How near the surface a cell's centre must be for the cell to know a
/// triangle, in sphere radii; a vertex is moved at most this and a cell's
/// diagonal (about 0.25 radii), and one farther keeps the fixed push
/// (`NETWORK_VERTEX_OFFSET`).
pub const REACH: f32 = 0.2;
const NONE: u32 = u32::MAX;

/// A point of the mesh with its normals, mesh space.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfacePoint {
    pub point: Vec3,
    /// Unit geometric normal, the triangle's winding side (zero for a
    /// degenerate triangle).
    pub ng: Vec3,
    /// Shading normal (the vertex normals interpolated, on `ng`'s side;
    /// `ng` for flat meshes).
    pub ns: Vec3,
}

/// One triangle some cell knows, with everything a lookup reads of it in
/// one place (two cache lines), so that a lookup is two scattered reads:
/// its cell, then this.
#[derive(Clone, Copy, Debug)]
struct Site {
    corners: [Vec3; 3],
    ng: Vec3,
    /// The triangle's vertex normals (a smooth mesh), else zero.
    vertex_normals: [Vec3; 3],
}

/// The closest-triangle grid of one mesh (see the module doc).
pub struct SurfaceSnap {
    /// Mesh-space low corner of the grid.
    origin: Vec3,
    /// Cells per mesh unit.
    inv_cell: f32,
    /// Per cell (x fastest): the site of the triangle closest to its
    /// centre, or `NONE`.
    cells: Vec<u32>,
    /// The triangles the cells know: at most one per cell, whatever the
    /// mesh's size (the knot's grid knows 12,370 of its 327,680
    /// triangles: 2.1 MB with the cells).
    sites: Vec<Site>,
    /// The squared distance a point may be moved: REACH and a cell's
    /// diagonal (mesh units).
    max_move2: f32,
}

impl SurfaceSnap {
    /// The grid of `mesh` over the cube around `sphere` (mesh space).
    pub fn build(mesh: &Mesh, sphere: &BoundingSphere) -> Self {
        let res = RESOLUTION as usize;
        let cell = 2.0 * sphere.radius / RESOLUTION as f32;
        let origin = sphere.center - Vec3::splat(sphere.radius);
        let corners = |t: u32| mesh.triangles[t as usize].map(|i| mesh.positions[i as usize]);
        let centre = |i: usize| {
            let (x, y, z) = (i % res, (i / res) % res, i / (res * res));
            origin + (Vec3::new(x as f32, y as f32, z as f32) + 0.5) * cell
        };
        let dist2 = |i: usize, t: u32| {
            let [a, b, c] = corners(t);
            let p = centre(i);
            p.distance_squared(closest_point_on_triangle(p, a, b, c).0)
        };
        let cell_of = |p: Vec3| {
            let g = ((p - origin) / cell).floor();
            g.clamp(Vec3::ZERO, Vec3::splat((res - 1) as f32))
                .as_uvec3()
        };
        // Seeds: every cell a triangle's box reaches knows that triangle.
        let mut best: Vec<(f32, u32)> = vec![(f32::INFINITY, NONE); res * res * res];
        for t in 0..mesh.triangles.len() as u32 {
            let [a, b, c] = corners(t);
            if !(a.is_finite() && b.is_finite() && c.is_finite()) {
                continue;
            }
            let (lo, hi) = (cell_of(a.min(b).min(c)), cell_of(a.max(b).max(c)));
            for z in lo.z..=hi.z {
                for y in lo.y..=hi.y {
                    for x in lo.x..=hi.x {
                        let i = index(UVec3::new(x, y, z), res);
                        let d = dist2(i, t);
                        if d < best[i].0 {
                            best[i] = (d, t);
                        }
                    }
                }
            }
        }
        // Jump flooding: each cell takes the closest of the triangles its
        // neighbours at distance `step` know; 4 + 2 + 1 cells reach past
        // REACH. A cell whose triangle is within half a cell of its centre
        // keeps it: a closer one would move a lookup by less than that.
        let settled = (0.5 * cell).powi(2);
        // Each triangle's bounding sphere (its centroid, its farthest
        // corner): a candidate whose sphere is farther from the cell's
        // centre than the cell's best triangle cannot beat it and is passed
        // over without its closest point. The grid is the same (the margin
        // covers rounding); the flooding took 160 ms of the knot's scene
        // build, most of it in closest points of triangles that lost.
        let bounds: Vec<(Vec3, f32)> = mesh
            .triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| mesh.positions[i as usize]);
                let m = (a + b + c) / 3.0;
                (m, m.distance(a).max(m.distance(b)).max(m.distance(c)))
            })
            .collect();
        let cannot_beat = |p: Vec3, t: u32, best2: f32| {
            let (m, r) = bounds[t as usize];
            let gap = p.distance(m) - r;
            gap > 0.0 && gap * gap > best2 * (1.0 + 1e-3)
        };
        for step in [4i32, 2, 1] {
            let prev = best.clone();
            best.par_chunks_mut(res * res)
                .enumerate()
                .for_each(|(z, slice)| {
                    for (k, known) in slice.iter_mut().enumerate() {
                        let (x, y) = ((k % res) as i32, (k / res) as i32);
                        let i = z * res * res + k;
                        if known.0 <= settled {
                            continue;
                        }
                        let p = centre(i);
                        for dz in -1..=1 {
                            for dy in -1..=1 {
                                for dx in -1..=1 {
                                    let n = [x + dx * step, y + dy * step, z as i32 + dz * step];
                                    if n.iter().any(|&c| c < 0 || c >= res as i32) {
                                        continue;
                                    }
                                    let t = prev[index(
                                        UVec3::new(n[0] as u32, n[1] as u32, n[2] as u32),
                                        res,
                                    )]
                                    .1;
                                    if t == NONE || t == known.1 || cannot_beat(p, t, known.0) {
                                        continue;
                                    }
                                    let d = dist2(i, t);
                                    if d < known.0 {
                                        *known = (d, t);
                                    }
                                }
                            }
                        }
                    }
                });
        }
        // Cells out of reach forget their triangle; the others point at a
        // site, one per triangle they know.
        let reach2 = (REACH * sphere.radius).powi(2);
        let mut site_of = std::collections::HashMap::new();
        let mut sites = Vec::new();
        let cells = best
            .into_iter()
            .map(|(d, t)| {
                if d > reach2 {
                    return NONE;
                }
                *site_of.entry(t).or_insert_with(|| {
                    let c = corners(t);
                    let vertex_normals = mesh
                        .shading_normals
                        .as_ref()
                        .and_then(|n| n.get(t as usize).copied())
                        .unwrap_or([Vec3::ZERO; 3]);
                    sites.push(Site {
                        corners: c,
                        ng: nppp_geom::unit_normal((c[1] - c[0]).cross(c[2] - c[0])),
                        vertex_normals,
                    });
                    (sites.len() - 1) as u32
                })
            })
            .collect();
        Self {
            origin,
            inv_cell: 1.0 / cell,
            cells,
            sites,
            max_move2: (REACH * sphere.radius + cell * 3f32.sqrt()).powi(2),
        }
    }

    /// The point of the mesh closest to mesh-space `p` as the grid knows it
    /// (the closest point of the triangle nearest the centre of `p`'s cell,
    /// or of the border cell nearest `p` outside the grid), or `None` where
    /// that triangle is farther than about [`REACH`] from `p`. The steps
    /// below, for callers that start a batch's reads before using any
    /// (each is a cache miss: the cell, then its site).
    #[inline]
    pub fn closest(&self, p: Vec3) -> Option<SurfacePoint> {
        let site = self.site_in(self.cell_of(p)?)?;
        self.closest_on(site, p)
    }

    /// The cell `p` reads (clamped to the grid), or `None` for NaN.
    #[inline]
    pub fn cell_of(&self, p: Vec3) -> Option<u32> {
        let g = ((p - self.origin) * self.inv_cell).floor();
        // `clamp` would keep a NaN.
        if !g.is_finite() {
            return None;
        }
        let g = g.clamp(Vec3::ZERO, Vec3::splat((RESOLUTION - 1) as f32));
        Some(index(g.as_uvec3(), RESOLUTION as usize) as u32)
    }

    /// The site of the triangle cell `cell` knows, if one is within reach.
    #[inline]
    pub fn site_in(&self, cell: u32) -> Option<u32> {
        self.cells
            .get(cell as usize)
            .copied()
            .filter(|&t| t != NONE)
    }

    /// The closest point of site `site`'s triangle to `p`, with its
    /// normals, if within the reach.
    #[inline]
    pub fn closest_on(&self, site: u32, p: Vec3) -> Option<SurfacePoint> {
        let s = self.sites.get(site as usize)?;
        let [a, b, c] = s.corners;
        let (point, b1, b2) = closest_point_on_triangle(p, a, b, c);
        (p.distance_squared(point) <= self.max_move2).then(|| SurfacePoint {
            point,
            ng: s.ng,
            ns: crate::surface::interpolated_normal(s.vertex_normals, b1, b2, s.ng),
        })
    }

    /// Starts reading cell `cell` and returns at once.
    #[inline]
    pub fn prefetch_cell(&self, cell: u32) {
        crate::bvh::prefetch_item(&self.cells, cell as usize);
    }

    /// Starts reading site `site` and returns at once.
    #[inline]
    pub fn prefetch_site(&self, site: u32) {
        crate::bvh::prefetch_item(&self.sites, site as usize);
    }

    /// Bytes held.
    pub fn memory_bytes(&self) -> usize {
        self.cells.len() * size_of::<u32>() + self.sites.len() * size_of::<Site>()
    }
}

#[inline(always)]
fn index(g: UVec3, res: usize) -> usize {
    (g.z as usize * res + g.y as usize) * res + g.x as usize
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sphere_mesh() -> (Mesh, BoundingSphere) {
        let mesh = nppp_scene::icosphere_mesh(Vec3::new(3.0, -2.0, 5.0), 1.0, 3);
        let sphere = BoundingSphere::around(&mesh.positions, nppp_estimator::SPHERE_MARGIN);
        (mesh, sphere)
    }

    /// Brute force: the mesh's closest point to `p`.
    fn exact(mesh: &Mesh, p: Vec3) -> Vec3 {
        mesh.triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| mesh.positions[i as usize]);
                closest_point_on_triangle(p, a, b, c).0
            })
            .min_by(|x, y| p.distance_squared(*x).total_cmp(&p.distance_squared(*y)))
            .unwrap()
    }

    #[test]
    fn points_near_the_surface_land_on_it_within_a_cell() {
        let (mesh, sphere) = sphere_mesh();
        let snap = SurfaceSnap::build(&mesh, &sphere);
        let cell = 2.0 * sphere.radius / RESOLUTION as f32;
        let mut rng = nppp_geom::SampleRng::new(7, 0, 0);
        for _ in 0..500 {
            let dir = nppp_geom::sampling::uniform_sphere(rng.uniform2());
            // Inside and outside the unit icosphere, up to 0.15 radii off.
            let r = 1.0 + (rng.uniform() - 0.5) * 0.3 * sphere.radius;
            let p = Vec3::new(3.0, -2.0, 5.0) + dir * r;
            let got = snap.closest(p).expect("near the surface");
            let want = exact(&mesh, p);
            let on = exact(&mesh, got.point);
            assert!(on.distance(got.point) < 1e-5, "the point is on the mesh");
            assert!(
                (got.ng.length() - 1.0).abs() < 1e-5 && got.ns == got.ng,
                "a flat mesh"
            );
            assert!(
                p.distance(got.point) <= p.distance(want) + 2.0 * cell,
                "{p}: {} against {}",
                p.distance(got.point),
                p.distance(want)
            );
        }
    }

    /// A smooth mesh's lookups carry its vertex normals, interpolated at
    /// the point found: on a sphere, close to the radial direction there
    /// (the flat facets' normals are up to half a facet's angle off it).
    #[test]
    fn a_smooth_mesh_gives_interpolated_normals() {
        let (mut mesh, sphere) = sphere_mesh();
        let centre = Vec3::new(3.0, -2.0, 5.0);
        mesh.shading_normals = Some(
            mesh.triangles
                .iter()
                .map(|t| t.map(|i| (mesh.positions[i as usize] - centre).normalize()))
                .collect(),
        );
        let snap = SurfaceSnap::build(&mesh, &sphere);
        let mut rng = nppp_geom::SampleRng::new(9, 0, 0);
        let (mut worst_ns, mut worst_ng) = (1.0f32, 1.0f32);
        for _ in 0..300 {
            let dir = nppp_geom::sampling::uniform_sphere(rng.uniform2());
            let got = snap.closest(centre + dir * 1.05).expect("near the surface");
            let radial = (got.point - centre).normalize();
            assert!(got.ns.dot(got.ng) > 0.0, "on the geometric normal's side");
            worst_ns = worst_ns.min(got.ns.dot(radial));
            worst_ng = worst_ng.min(got.ng.dot(radial));
        }
        assert!(
            worst_ns > 0.9995 && worst_ns > worst_ng,
            "{worst_ns} vs flat {worst_ng}"
        );
    }

    #[test]
    fn far_and_broken_points_get_none() {
        let (mesh, sphere) = sphere_mesh();
        let snap = SurfaceSnap::build(&mesh, &sphere);
        assert_eq!(
            snap.closest(sphere.center),
            None,
            "the centre is 1 radius deep"
        );
        assert_eq!(snap.closest(Vec3::splat(f32::NAN)), None);
        assert_eq!(snap.closest(Vec3::splat(1e30)), None);
    }
}
