//! Analytic objects whose exits are known in closed form, for the tests and
//! for measuring training behaviour before (or without) real path-traced
//! data: a mirror ball (each ray has one exact exit) and a diffuse ball that
//! absorbs a position-dependent fraction of paths (a real distribution whose
//! mean throughput varies per ray, the case where Chamfer alone is biased).

use nppp_estimator::{Exit, PickedVertex};
use nppp_geom::sampling::cosine_hemisphere;
use nppp_geom::{Frame, Ray, SampleRng, SpherePair, Vec3};

use crate::data::RaySample;

/// Which analytic object.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum SyntheticObject {
    /// A perfect mirror ball with a Schlick-Fresnel throughput: every exit of
    /// a ray is the same, a deterministic function of the ray.
    Mirror { radius: f32 },
    /// A Lambertian ball (albedo 0.8) that absorbs a fraction of paths rising
    /// from 20% at its bottom to 70% at its top; absorbed paths are exits
    /// with zero throughput, as the data generator writes them.
    AbsorbingDiffuse { radius: f32 },
}

/// The picked vertex the data generator records for a ray that hits a
/// centred convex ball of `radius`: every walk's only lit vertex is the first
/// hit (throughput 1 before scattering, index 0). For tests of the vertex head.
pub fn first_hit_vertex(pair: &SpherePair, radius: f32) -> Option<PickedVertex> {
    let (ray, h) = hit_ball(pair, radius)?;
    Some(PickedVertex {
        position: h,
        normal: h / radius,
        wo: -ray.dir,
        beta: Vec3::ONE,
        index: 0,
    })
}

/// Where a ray leaving `p` along unit `d` (from inside) crosses the unit sphere.
fn leave_unit_sphere(p: Vec3, d: Vec3) -> Vec3 {
    let b = p.dot(d);
    let c = p.length_squared() - 1.0;
    let t = -b + (b * b - c).max(0.0).sqrt();
    (p + d * t).normalize()
}

/// Hit point on a centred ball of `radius` of the ray through the pair's
/// chord, if any.
fn hit_ball(pair: &SpherePair, radius: f32) -> Option<(Ray, Vec3)> {
    let ray = pair.to_ray()?;
    let b = ray.origin.dot(ray.dir);
    let c = ray.origin.length_squared() - radius * radius;
    let disc = b * b - c;
    if disc <= 0.0 {
        return None;
    }
    let t = -b - disc.sqrt();
    (t > 0.0).then(|| (ray, ray.at(t)))
}

impl SyntheticObject {
    /// The exits of one ray (`k` of them) or `None` for a miss.
    pub fn exits(&self, pair: &SpherePair, k: usize, rng: &mut SampleRng) -> Option<Vec<Exit>> {
        match *self {
            Self::Mirror { radius } => {
                let (ray, h) = hit_ball(pair, radius)?;
                let n = h / radius;
                let cos = -ray.dir.dot(n);
                let r = ray.dir + 2.0 * cos * n;
                let f = 0.04 + 0.96 * (1.0 - cos).powi(5);
                let e = Exit {
                    position: leave_unit_sphere(h, r),
                    direction: r.normalize(),
                    throughput: Vec3::new(0.9, 0.7, 0.5) * (0.5 + 0.5 * f),
                    radiance: Vec3::ZERO,
                    bounces: 1,
                };
                Some(vec![e; k])
            }
            Self::AbsorbingDiffuse { radius } => {
                let (_, h) = hit_ball(pair, radius)?;
                let n = h / radius;
                let absorb = 0.2 + 0.5 * 0.5 * (n.z + 1.0);
                let frame = Frame::from_normal(n);
                Some(
                    (0..k)
                        .map(|_| {
                            let d = frame.to_world(cosine_hemisphere(rng.uniform2()));
                            let alive = rng.uniform() >= absorb;
                            Exit {
                                position: leave_unit_sphere(h, d),
                                direction: d,
                                throughput: if alive { Vec3::splat(0.8) } else { Vec3::ZERO },
                                radiance: Vec3::ZERO,
                                bounces: 1,
                            }
                        })
                        .collect(),
                )
            }
        }
    }

    /// `n` rays drawn uniformly in (u1, v1, u2, v2), as the data generator
    /// draws them, with `k` exits per hit.
    pub fn rays(&self, n: usize, k: usize, seed: u64) -> Vec<RaySample> {
        (0..n)
            .map(|i| {
                let mut rng = SampleRng::new(seed, i as u64, 0x5717);
                let (a, b) = (rng.uniform2(), rng.uniform2());
                let pair = SpherePair([a.x, a.y, b.x, b.y]);
                match self.exits(&pair, k, &mut rng) {
                    Some(exits) => RaySample {
                        pair,
                        hit: true,
                        exits,
                        vertices: Vec::new(),
                    },
                    None => RaySample {
                        pair,
                        hit: false,
                        exits: Vec::new(),
                        vertices: Vec::new(),
                    },
                }
            })
            .collect()
    }
}
