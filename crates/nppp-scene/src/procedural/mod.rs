//! Procedural test objects that stress neural path prediction the way the
//! thesis' Stanford dragon does (hundreds of thousands of triangles, concave,
//! light bouncing many times between parts of the same object), without
//! shipping a scanned mesh: every object is a closed, consistently oriented
//! triangle mesh generated from a handful of numbers.
//!
//! All objects are centred on the origin and scaled so every vertex lies in
//! the unit sphere: an estimator is trained on the object alone, and a fixed
//! bounding sphere lets the same training setup serve every object.

use glam::{DVec3, Vec3};
use std::collections::HashMap;
use std::f64::consts::{PI, TAU};
use std::io::Write;
use std::path::Path;

/// Upper bound on generated triangles: past this a 2-core machine spends
/// minutes on the BVH alone and the mesh no longer fits comfortably in memory,
/// so such parameters are almost certainly a typo.
pub const MAX_TRIANGLES: u64 = 20_000_000;

/// The deepest Menger sponge: level 4 already has 672,768 triangles, level 5
/// would have 13 million, all of them tiny flat squares that add nothing a
/// level-4 sponge doesn't already exercise.
pub const MAX_MENGER_LEVEL: u32 = 4;

/// Torus-knot windings are capped so the self-intersection check (which
/// samples the curve densely) stays fast and meaningful.
pub const MAX_KNOT_WINDING: u32 = 100;

/// A triangle mesh as plain arrays: positions and counter-clockwise
/// (outward-facing) triangles.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TriMesh {
    pub positions: Vec<Vec3>,
    pub triangles: Vec<[u32; 3]>,
}

/// A procedural object and the few numbers that define it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Procedural {
    /// A unit icosphere pushed in and out along its normal by seeded noise
    /// whose zero set becomes a network of deep V-shaped creases between
    /// overlapping lobes (a cabbage-rose look): narrow concave folds make
    /// light bounce many times before escaping, as in the dragon's scales
    /// and coils.
    /// `subdivisions` follows the scene format's icosphere (20 * 4^n
    /// triangles), `amplitude` in [0, 1) is the relative depth of the
    /// displacement, `frequency` the angular frequency of the lowest noise
    /// octave (about 0.6 * `frequency` waves around a great circle; two
    /// more octaves reach four times that).
    DisplacedSphere {
        subdivisions: u32,
        amplitude: f32,
        frequency: f32,
        seed: u64,
    },
    /// A round tube along a (p, q) torus knot (p windings around the axis of
    /// symmetry, q around the torus' core; p and q coprime). `tube_radius`
    /// is in the knot's own units, where the torus has major radius 2 and
    /// minor radius 1, before the whole object is scaled into the unit sphere.
    /// `segments` rings of `sides` vertices each.
    TorusKnot {
        p: u32,
        q: u32,
        tube_radius: f32,
        segments: u32,
        sides: u32,
    },
    /// The Menger sponge at `level` (0 is a cube): flat faces, sharp
    /// concave corners and tunnels that light can travel through.
    MengerSponge { level: u32 },
}

/// Why a [`Procedural`] can't be built.
#[derive(Debug, thiserror::Error)]
pub enum ProceduralError {
    #[error("{name} would have {} triangles, more than the limit of {MAX_TRIANGLES}", count_text(*.triangles))]
    TooManyTriangles { name: String, triangles: u64 },
    #[error("{parameter} = {value} is invalid: {reason}")]
    InvalidParameter {
        parameter: &'static str,
        value: String,
        reason: String,
    },
    #[error(
        "torus knot p = {p}, q = {q}: p and q must be coprime, otherwise the curve closes up early or is a link of several tubes"
    )]
    NotAKnot { p: u32, q: u32 },
    #[error(
        "torus knot p = {p}, q = {q}: tube_radius = {tube_radius} makes the tube intersect itself; at most about {limit:.4} fits"
    )]
    TubeSelfIntersection {
        p: u32,
        q: u32,
        tube_radius: f32,
        limit: f32,
    },
}

impl Procedural {
    /// The objects the project uses for testing: each is about the size of
    /// the thesis' dragon (the sponge at level 3 is smaller, because level 4
    /// is already twice the dragon).
    pub fn defaults() -> [Procedural; 3] {
        [
            Procedural::DisplacedSphere {
                subdivisions: 7,
                amplitude: 0.3,
                frequency: 6.0,
                seed: 1,
            },
            Procedural::TorusKnot {
                p: 2,
                q: 3,
                tube_radius: 0.5,
                segments: 2048,
                sides: 80,
            },
            Procedural::MengerSponge { level: 3 },
        ]
    }

    /// A short, file-name-safe identifier, e.g. `torus-knot-2-3`.
    pub fn name(&self) -> String {
        match *self {
            Procedural::DisplacedSphere {
                subdivisions, seed, ..
            } => format!("displaced-sphere-{subdivisions}-seed-{seed}"),
            Procedural::TorusKnot { p, q, .. } => format!("torus-knot-{p}-{q}"),
            Procedural::MengerSponge { level } => format!("menger-sponge-{level}"),
        }
    }

    /// The number of triangles [`Procedural::build`] will produce (saturating
    /// at `u64::MAX`, which errors print as such), computed
    /// without building, so absurd parameters fail before allocating.
    pub fn triangle_count(&self) -> u64 {
        match *self {
            Procedural::DisplacedSphere { subdivisions, .. } => {
                20u64.saturating_mul(4u64.saturating_pow(subdivisions))
            }
            Procedural::TorusKnot {
                segments, sides, ..
            } => 2 * u64::from(segments) * u64::from(sides),
            // A level-L sponge's surface is 2 * 20^L + 4 * 8^L unit squares.
            Procedural::MengerSponge { level } => {
                let l = level.min(13);
                2 * (2 * 20u64.pow(l) + 4 * 8u64.pow(l))
            }
        }
    }

    /// Builds the mesh: closed, watertight, outward-facing, inside the unit sphere.
    pub fn build(&self) -> Result<TriMesh, ProceduralError> {
        self.validate()?;
        let triangles = self.triangle_count();
        if triangles > MAX_TRIANGLES {
            return Err(ProceduralError::TooManyTriangles {
                name: self.name(),
                triangles,
            });
        }
        Ok(match *self {
            Procedural::DisplacedSphere {
                subdivisions,
                amplitude,
                frequency,
                seed,
            } => displaced_sphere(subdivisions, amplitude.into(), frequency.into(), seed),
            Procedural::TorusKnot {
                p,
                q,
                tube_radius,
                segments,
                sides,
            } => torus_knot(p, q, tube_radius.into(), segments, sides),
            Procedural::MengerSponge { level } => menger_sponge(level),
        })
    }

    pub(crate) fn validate(&self) -> Result<(), ProceduralError> {
        let invalid = |parameter, value: String, reason: &str| {
            Err(ProceduralError::InvalidParameter {
                parameter,
                value,
                reason: reason.to_owned(),
            })
        };
        match *self {
            Procedural::DisplacedSphere {
                amplitude,
                frequency,
                ..
            } => {
                if !(amplitude.is_finite() && (0.0..1.0).contains(&amplitude)) {
                    return invalid(
                        "amplitude",
                        amplitude.to_string(),
                        "must be in [0, 1) so the radius stays positive and the surface can't fold through the centre",
                    );
                }
                if !(frequency.is_finite() && frequency >= 0.0) {
                    return invalid(
                        "frequency",
                        frequency.to_string(),
                        "must be finite and >= 0",
                    );
                }
            }
            Procedural::TorusKnot {
                p,
                q,
                tube_radius,
                segments,
                sides,
            } => {
                for (parameter, value) in [("p", p), ("q", q)] {
                    if value == 0 || value > MAX_KNOT_WINDING {
                        return invalid(
                            parameter,
                            value.to_string(),
                            &format!("must be in 1..={MAX_KNOT_WINDING}"),
                        );
                    }
                }
                if gcd(p, q) != 1 {
                    return Err(ProceduralError::NotAKnot { p, q });
                }
                // Below 8 rings per winding the polyline cuts corners so hard
                // that rings tilt past each other and the tube turns inside out.
                let min_segments = 8 * p.max(q);
                if segments < min_segments {
                    return invalid(
                        "segments",
                        segments.to_string(),
                        &format!("a ({p}, {q}) knot needs at least {min_segments} rings"),
                    );
                }
                if sides < 3 {
                    return invalid(
                        "sides",
                        sides.to_string(),
                        "a closed tube needs at least 3 sides",
                    );
                }
                if !(tube_radius.is_finite() && tube_radius > 0.0) {
                    return invalid(
                        "tube_radius",
                        tube_radius.to_string(),
                        "must be finite and > 0",
                    );
                }
                if !tube_fits(p, q, tube_radius.into()) {
                    let limit = tube_radius_limit(p, q);
                    return Err(ProceduralError::TubeSelfIntersection {
                        p,
                        q,
                        tube_radius,
                        limit: limit as f32,
                    });
                }
            }
            Procedural::MengerSponge { level } => {
                if level > MAX_MENGER_LEVEL {
                    return invalid(
                        "level",
                        level.to_string(),
                        &format!("at most {MAX_MENGER_LEVEL} (level 5 is 13 million tiny squares)"),
                    );
                }
            }
        }
        Ok(())
    }
}

fn gcd(mut a: u32, mut b: u32) -> u32 {
    while b != 0 {
        (a, b) = (b, a % b);
    }
    a
}

/// Scales the object so its farthest vertex sits a hair inside the unit
/// sphere: the hair absorbs f32 rounding so `|v| <= 1` holds exactly.
fn into_unit_sphere(positions: &[DVec3]) -> Vec<Vec3> {
    let max_norm = positions.iter().map(|p| p.length()).fold(0.0, f64::max);
    let scale = if max_norm > 0.0 {
        (1.0 - 1e-6) / max_norm
    } else {
        1.0
    };
    positions.iter().map(|&p| (p * scale).as_vec3()).collect()
}

// ---------------------------------------------------------------------------
// Displaced sphere

/// SplitMix64: a tiny, well-mixed generator, so the noise depends on nothing
/// but the seed (no external crates, no platform-dependent RNG).
struct SplitMix64(u64);

impl SplitMix64 {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1) with 53 random bits.
    fn next_f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }
}

struct Wave {
    direction: DVec3,
    frequency: f64,
    phase: f64,
    weight: f64,
}

/// Band-limited noise on the sphere: a few plane waves per octave over three
/// octaves. Plane waves are smooth and cheap, and with random directions
/// their sum has no visible grid or pole, unlike lattice noise on a sphere.
struct FoldNoise {
    waves: Vec<Wave>,
    inv_rms: f64,
}

impl FoldNoise {
    const OCTAVES: u32 = 3;
    const WAVES_PER_OCTAVE: u32 = 4;

    fn new(frequency: f64, seed: u64) -> Self {
        let mut rng = SplitMix64(seed);
        let mut waves = Vec::new();
        for octave in 0..Self::OCTAVES {
            for _ in 0..Self::WAVES_PER_OCTAVE {
                let z = 2.0 * rng.next_f64() - 1.0;
                let azimuth = TAU * rng.next_f64();
                let s = (1.0 - z * z).max(0.0).sqrt();
                waves.push(Wave {
                    direction: DVec3::new(s * azimuth.cos(), s * azimuth.sin(), z),
                    // Jitter keeps waves of one octave from beating into a regular pattern.
                    frequency: frequency * f64::from(1 << octave) * (0.8 + 0.4 * rng.next_f64()),
                    phase: TAU * rng.next_f64(),
                    weight: 0.5f64.powi(octave as i32),
                });
            }
        }
        let variance: f64 = waves.iter().map(|w| w.weight * w.weight / 2.0).sum();
        FoldNoise {
            waves,
            inv_rms: 1.0 / variance.sqrt(),
        }
    }

    /// In [-1, 1): -1 exactly on the zero set of the wave sum, which the
    /// absolute value turns into sharp creases (ridged noise, inverted), and
    /// approaching 1 on the rounded lobes between them. tanh bounds the
    /// result without clipping flat plateaus.
    fn fold(&self, p: DVec3) -> f64 {
        let sum: f64 = self
            .waves
            .iter()
            .map(|w| w.weight * (w.frequency * w.direction.dot(p) + w.phase).sin())
            .sum();
        2.0 * (sum * self.inv_rms).tanh().abs() - 1.0
    }
}

/// Displacing purely along the radius keeps the surface star-shaped around
/// the origin, so it can never intersect itself and every triangle keeps its
/// orientation, however deep the folds are.
fn displaced_sphere(subdivisions: u32, amplitude: f64, frequency: f64, seed: u64) -> TriMesh {
    let (mut positions, triangles) = crate::shapes::unit_icosphere(subdivisions);
    let noise = FoldNoise::new(frequency, seed);
    for p in &mut positions {
        *p *= 1.0 + amplitude * noise.fold(*p);
    }
    TriMesh {
        positions: into_unit_sphere(&positions),
        triangles,
    }
}

// ---------------------------------------------------------------------------
// Torus knot

/// Point, first and second derivative of the (p, q) torus knot on the torus
/// with major radius 2 and minor radius 1, symmetry axis along y (the scene
/// format's up), so the knot lies flat on a floor.
fn knot(p: u32, q: u32, phi: f64) -> [DVec3; 3] {
    let (p, q) = (f64::from(p), f64::from(q));
    let (sp, cp) = (p * phi).sin_cos();
    let (sq, cq) = (q * phi).sin_cos();
    let rho = 2.0 + cq;
    let d_rho = -q * sq;
    let dd_rho = -q * q * cq;
    let c = DVec3::new(rho * cp, sq, -rho * sp);
    let d = DVec3::new(
        d_rho * cp - p * rho * sp,
        q * cq,
        -d_rho * sp - p * rho * cp,
    );
    let dd = DVec3::new(
        dd_rho * cp - 2.0 * p * d_rho * sp - p * p * rho * cp,
        -q * q * sq,
        -dd_rho * sp - 2.0 * p * d_rho * cp + p * p * rho * sp,
    );
    [c, d, dd]
}

/// Dense samples of the knot with their cumulative arc length.
struct KnotSamples {
    points: Vec<DVec3>,
    arc: Vec<f64>,
    length: f64,
    min_curvature_radius: f64,
}

impl KnotSamples {
    fn new(p: u32, q: u32) -> Self {
        let n = (256 * (p + q)).max(1024) as usize;
        let mut points = Vec::with_capacity(n);
        let mut min_curvature_radius = f64::INFINITY;
        for i in 0..n {
            let [c, d, dd] = knot(p, q, TAU * i as f64 / n as f64);
            points.push(c);
            let bend = d.cross(dd).length();
            if bend > 0.0 {
                min_curvature_radius = min_curvature_radius.min(d.length().powi(3) / bend);
            }
        }
        let mut arc = Vec::with_capacity(n);
        let mut length = 0.0;
        for i in 0..n {
            arc.push(length);
            length += points[i].distance(points[(i + 1) % n]);
        }
        KnotSamples {
            points,
            arc,
            length,
            min_curvature_radius,
        }
    }

    /// A tube of radius r around a smooth curve is embedded when r is below
    /// the curvature radius everywhere and any two points farther apart than
    /// pi * r along the curve are at least 2r apart in space. (For a circle
    /// of radius r the two conditions meet exactly, so the second adds no
    /// false alarms for merely curved stretches.)
    fn fits(&self, r: f64) -> bool {
        if r >= self.min_curvature_radius {
            return false;
        }
        let (min_arc, min_dist2) = (PI * r, 4.0 * r * r);
        // Only points closer than 2r matter: bucket them in cells of that
        // size and compare each with the 27 cells around it.
        let cell_size = 2.0 * r;
        let key = |p: DVec3| (p / cell_size).floor().as_i64vec3();
        let mut grid: HashMap<glam::I64Vec3, Vec<usize>> = HashMap::new();
        for (i, &p) in self.points.iter().enumerate() {
            grid.entry(key(p)).or_default().push(i);
        }
        for (i, &p) in self.points.iter().enumerate() {
            let centre = key(p);
            for dz in -1..=1 {
                for dy in -1..=1 {
                    for dx in -1..=1 {
                        let Some(cell) = grid.get(&(centre + glam::I64Vec3::new(dx, dy, dz)))
                        else {
                            continue;
                        };
                        for &j in cell.iter().filter(|&&j| j > i) {
                            let along = self.arc[j] - self.arc[i];
                            if along.min(self.length - along) >= min_arc
                                && p.distance_squared(self.points[j]) < min_dist2
                            {
                                return false;
                            }
                        }
                    }
                }
            }
        }
        true
    }
}

fn tube_fits(p: u32, q: u32, r: f64) -> bool {
    KnotSamples::new(p, q).fits(r)
}

/// Only computed for the error message, so a bisection is fast enough.
fn tube_radius_limit(p: u32, q: u32) -> f64 {
    let samples = KnotSamples::new(p, q);
    let (mut lo, mut hi) = (0.0, samples.min_curvature_radius);
    for _ in 0..24 {
        let mid = 0.5 * (lo + hi);
        if samples.fits(mid) {
            lo = mid
        } else {
            hi = mid
        }
    }
    lo
}

/// Rotation-minimising frames (the double-reflection method of Wang et al.
/// 2008) keep the tube's vertex columns from twisting along the curve; the
/// small angle the frames have turned after one full loop (the curve's total
/// torsion) is spread evenly over all rings, so the last ring meets the
/// first without a seam.
fn torus_knot(p: u32, q: u32, tube_radius: f64, segments: u32, sides: u32) -> TriMesh {
    let n = segments as usize;
    let mut centres = Vec::with_capacity(n + 1);
    let mut tangents = Vec::with_capacity(n + 1);
    for i in 0..=n {
        let [c, d, _] = knot(p, q, TAU * (i % n) as f64 / n as f64);
        centres.push(c);
        tangents.push(d.normalize());
    }
    let mut normals = Vec::with_capacity(n + 1);
    normals.push(tangents[0].any_orthonormal_vector());
    for i in 0..n {
        let v1 = centres[i + 1] - centres[i];
        let c1 = v1.length_squared();
        let r_l = normals[i] - (2.0 / c1) * v1.dot(normals[i]) * v1;
        let t_l = tangents[i] - (2.0 / c1) * v1.dot(tangents[i]) * v1;
        let v2 = tangents[i + 1] - t_l;
        let c2 = v2.length_squared();
        let r = if c2 > 1e-30 {
            r_l - (2.0 / c2) * v2.dot(r_l) * v2
        } else {
            r_l
        };
        // Re-orthonormalise against drift over thousands of steps.
        let t = tangents[i + 1];
        normals.push((r - t.dot(r) * t).normalize());
    }
    let (t0, r0, rn) = (tangents[0], normals[0], normals[n]);
    let closure = r0.cross(rn).dot(t0).atan2(r0.dot(rn));

    let sides_n = sides as usize;
    let mut positions = Vec::with_capacity(n * sides_n);
    for i in 0..n {
        let t = tangents[i];
        let (s, c) = (-closure * i as f64 / n as f64).sin_cos();
        let normal = normals[i] * c + t.cross(normals[i]) * s;
        let binormal = t.cross(normal);
        for j in 0..sides_n {
            let (sj, cj) = (TAU * j as f64 / sides_n as f64).sin_cos();
            positions.push(centres[i] + tube_radius * (cj * normal + sj * binormal));
        }
    }
    // With (tangent, normal, binormal) right-handed, going around the ring
    // (j) then along the curve (i) turns counter-clockwise seen from outside.
    let index = |i: usize, j: usize| ((i % n) * sides_n + j % sides_n) as u32;
    let mut triangles = Vec::with_capacity(2 * n * sides_n);
    for i in 0..n {
        for j in 0..sides_n {
            let (a, b) = (index(i, j), index(i, j + 1));
            let (c, d) = (index(i + 1, j), index(i + 1, j + 1));
            triangles.push([a, b, c]);
            triangles.push([b, d, c]);
        }
    }
    TriMesh {
        positions: into_unit_sphere(&positions),
        triangles,
    }
}

// ---------------------------------------------------------------------------
// Menger sponge

/// A cell of the 3^L grid is solid unless, at some base-3 digit, two or more
/// of its coordinates are in the middle third. Emitting a square only
/// between a solid and an empty cell gives exactly the sponge's surface; it
/// is edge-manifold because two solid cells never touch along an edge alone
/// (the digit that empties one diagonal neighbour would empty the other).
fn menger_sponge(level: u32) -> TriMesh {
    let n = 3usize.pow(level);
    let solid_at = |mut x: usize, mut y: usize, mut z: usize| {
        for _ in 0..level {
            let middles =
                usize::from(x % 3 == 1) + usize::from(y % 3 == 1) + usize::from(z % 3 == 1);
            if middles >= 2 {
                return false;
            }
            (x, y, z) = (x / 3, y / 3, z / 3);
        }
        true
    };
    let cell = |x: usize, y: usize, z: usize| (z * n + y) * n + x;
    let mut solid = vec![false; n * n * n];
    for z in 0..n {
        for y in 0..n {
            for x in 0..n {
                solid[cell(x, y, z)] = solid_at(x, y, z);
            }
        }
    }
    let is_solid = |c: [i64; 3]| {
        c.iter().all(|&v| (0..n as i64).contains(&v))
            && solid[cell(c[0] as usize, c[1] as usize, c[2] as usize)]
    };

    // Lattice corners are shared by up to eight squares; a dense index map
    // welds them without hashing.
    let m = n + 1;
    let mut vertex_of = vec![u32::MAX; m * m * m];
    let mut lattice: Vec<[usize; 3]> = Vec::new();
    let mut vertex = |c: [usize; 3]| {
        let slot = &mut vertex_of[(c[2] * m + c[1]) * m + c[0]];
        if *slot == u32::MAX {
            *slot = lattice.len() as u32;
            lattice.push(c);
        }
        *slot
    };
    let mut triangles = Vec::new();
    for z in 0..n {
        for y in 0..n {
            for x in 0..n {
                if !solid[cell(x, y, z)] {
                    continue;
                }
                let c = [x, y, z];
                for axis in 0..3 {
                    let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
                    for positive in [false, true] {
                        let mut neighbour = c.map(|v| v as i64);
                        neighbour[axis] += if positive { 1 } else { -1 };
                        if is_solid(neighbour) {
                            continue;
                        }
                        let mut corner = c;
                        corner[axis] += usize::from(positive);
                        let mut cu = corner;
                        cu[u] += 1;
                        let mut cuv = cu;
                        cuv[v] += 1;
                        let mut cv = corner;
                        cv[v] += 1;
                        // e_u x e_v = e_axis: (corner, +u, +u+v, +v) faces +axis.
                        let quad = if positive {
                            [corner, cu, cuv, cv]
                        } else {
                            [corner, cv, cuv, cu]
                        }
                        .map(&mut vertex);
                        triangles.push([quad[0], quad[1], quad[2]]);
                        triangles.push([quad[0], quad[2], quad[3]]);
                    }
                }
            }
        }
    }
    let half = n as f64 / 2.0;
    let positions: Vec<DVec3> = lattice
        .iter()
        .map(|c| DVec3::new(c[0] as f64 - half, c[1] as f64 - half, c[2] as f64 - half))
        .collect();
    TriMesh {
        positions: into_unit_sphere(&positions),
        triangles,
    }
}

// ---------------------------------------------------------------------------
// OBJ output

/// Writes a plain OBJ (`v x y z`, `f a b c`, 1-based). It goes through a
/// temporary file in the same folder and a rename, so a reader (or a make
/// rule checking timestamps) never sees a half-written mesh. Unless
/// `replace`, a file that appeared at `path` while the mesh was written
/// (another export to the same name) is kept, and this one beside it
/// ([`nppp_files::AtomicFile::commit_new`]).
pub fn write_obj(mesh: &TriMesh, path: &Path, replace: bool) -> std::io::Result<()> {
    let mut out = nppp_files::AtomicFile::create(path)?;
    writeln!(
        out,
        "# {} vertices, {} triangles",
        mesh.positions.len(),
        mesh.triangles.len()
    )?;
    // f32's Display is the shortest text that parses back to the same bits.
    for p in &mesh.positions {
        writeln!(out, "v {} {} {}", p.x, p.y, p.z)?;
    }
    for t in &mesh.triangles {
        writeln!(out, "f {} {} {}", t[0] + 1, t[1] + 1, t[2] + 1)?;
    }
    if replace {
        out.commit()
    } else {
        out.commit_new()
    }
}

/// A triangle count for an error message: the saturated count of absurd
/// parameters is not a number anyone asked for.
pub(crate) fn count_text(n: u64) -> String {
    if n == u64::MAX {
        "more than 1.8e19".to_owned()
    } else {
        n.to_string()
    }
}

#[cfg(test)]
mod tests;
