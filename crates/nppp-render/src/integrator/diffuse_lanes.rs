//! One diffuse bounce for up to eight paths at once, in SIMD lanes
//! (`wide::f32x8`): the arithmetic a path tracer spends on every
//! Lambertian vertex (the shading frame, the light sample, the BSDF's value
//! and pdf, the MIS weight, the cosine-weighted sample). Mitsuba 3's LLVM
//! variant runs it 16 paths wide; one path at a time it is a long chain of
//! dependent scalar operations (issue 23: `shade` and the light sample were
//! 24% of a plain-PT render in perf). What is per path and branchy stays
//! scalar: the random numbers (each path's own stream, drawn in `shade`'s
//! order), the light triangle's pick, the shadow rays, Russian roulette.
//!
//! Each lane computes exactly what `shade` computes for its path,
//! operation for operation in the same order and without fused
//! multiply-adds, so an image is bit for bit the same whichever way its
//! paths are shaded (`tests::lanes_match_scalar_shading`).

use super::{IntegratorSettings, Next, WorkCounts, russian_roulette};
use crate::accel::{NO_SKIP, SceneHit};
use crate::bsdf::Bsdf;
use crate::path::PathState;
use crate::scene_data::RenderScene;
use crate::surface::{OFFSET_REL, SurfaceKind, offset_ray_origin};
use glam::Vec3;
use nppp_geom::sampling::{QUARTER_COS, QUARTER_SIN};
use std::f32::consts::{FRAC_1_PI, PI};
use wide::f32x8;

/// Paths shaded together.
pub(super) const LANES: usize = 8;

/// The albedo of `hit`'s surface if a path arriving there can be shaded in
/// lanes: a diffuse surface, the path outside any medium and below M, and
/// lights to sample (without them `shade` takes no light sample).
#[inline]
pub(super) fn lane_albedo(
    scene: &RenderScene,
    s: &IntegratorSettings,
    path: &PathState,
    hit: &SceneHit,
) -> Option<Vec3> {
    match scene.surface[hit.instance as usize] {
        SurfaceKind::Scatter(Bsdf::Diffuse { albedo })
            if path.medium.is_none() && path.depth < s.max_bounces && !scene.lights.is_empty() =>
        {
            Some(albedo)
        }
        _ => None,
    }
}

/// Three lanes of vectors.
#[derive(Clone, Copy)]
struct V3 {
    x: f32x8,
    y: f32x8,
    z: f32x8,
}

impl V3 {
    fn from_lanes(v: &[Vec3; LANES]) -> Self {
        Self {
            x: f32x8::new(std::array::from_fn(|k| v[k].x)),
            y: f32x8::new(std::array::from_fn(|k| v[k].y)),
            z: f32x8::new(std::array::from_fn(|k| v[k].z)),
        }
    }

    fn lanes(self) -> [Vec3; LANES] {
        let (x, y, z) = (self.x.to_array(), self.y.to_array(), self.z.to_array());
        std::array::from_fn(|k| Vec3::new(x[k], y[k], z[k]))
    }

    /// glam's order: (x x' + y y') + z z'.
    #[inline(always)]
    fn dot(self, o: V3) -> f32x8 {
        self.x * o.x + self.y * o.y + self.z * o.z
    }

    #[inline(always)]
    fn add(self, o: V3) -> V3 {
        V3 {
            x: self.x + o.x,
            y: self.y + o.y,
            z: self.z + o.z,
        }
    }

    #[inline(always)]
    fn sub(self, o: V3) -> V3 {
        V3 {
            x: self.x - o.x,
            y: self.y - o.y,
            z: self.z - o.z,
        }
    }

    #[inline(always)]
    fn scale(self, s: f32x8) -> V3 {
        V3 {
            x: self.x * s,
            y: self.y * s,
            z: self.z * s,
        }
    }

    #[inline(always)]
    fn div(self, s: f32x8) -> V3 {
        V3 {
            x: self.x / s,
            y: self.y / s,
            z: self.z / s,
        }
    }

    #[inline(always)]
    fn neg(self) -> V3 {
        V3 {
            x: -self.x,
            y: -self.y,
            z: -self.z,
        }
    }

    /// `mask ? a : b`, per lane.
    #[inline(always)]
    fn select(mask: f32x8, a: V3, b: V3) -> V3 {
        V3 {
            x: mask.select(a.x, b.x),
            y: mask.select(a.y, b.y),
            z: mask.select(a.z, b.z),
        }
    }
}

/// glam's `if a > b { a } else { b }`.
#[inline(always)]
fn max_gt(a: f32x8, b: f32x8) -> f32x8 {
    a.simd_gt(b).select(a, b)
}

/// What one lane reads before the arithmetic: its path's hit and random
/// numbers, and the light triangle its sample picked.
#[derive(Clone, Copy, Default)]
struct LaneInput {
    p: Vec3,
    ng: Vec3,
    ns: Vec3,
    wo_world: Vec3,
    eps: f32,
    u_light2: [f32; 2],
    u_dir: [f32; 2],
    u_rr: f32,
    light_v0: Vec3,
    light_e1: Vec3,
    light_e2: Vec3,
    light_normal: Vec3,
    light_pdf_area: f32,
    light_floor: f32,
    light_radiance: Vec3,
}

/// Shades `lanes` (at most `LANES` paths, each with its hit and its
/// surface's albedo from `lane_albedo`) as `shade` would, and
/// writes each path's outcome to `outcome[path]`.
pub(super) fn shade_diffuse_lanes(
    scene: &RenderScene,
    paths: &mut [PathState],
    lanes: &[(u32, SceneHit, Vec3)],
    outcome: &mut [Next],
    work: &mut WorkCounts,
) {
    let n = lanes.len();
    debug_assert!(n > 0 && n <= LANES);
    let mut input = [LaneInput::default(); LANES];
    for (k, &(pi, hit, _)) in lanes.iter().enumerate() {
        let path = &mut paths[pi as usize];
        let p = path.origin + path.dir * hit.t;
        let (ng, ns) = scene.normals_at(&hit);
        // `shade`'s draws, in its order (u_lobe is drawn and unused by a
        // diffuse sample).
        let u_light = path.rng.uniform();
        let u_light2 = path.rng.uniform2();
        let _u_lobe = path.rng.uniform();
        let u_dir = path.rng.uniform2();
        let u_rr = path.rng.uniform();
        let li = scene.lights.pick(u_light);
        let t = &scene.lights.triangles[li];
        input[k] = LaneInput {
            p,
            ng,
            ns,
            wo_world: -path.dir,
            eps: scene.offset_at(p, hit.instance),
            u_light2: u_light2.into(),
            u_dir: u_dir.into(),
            u_rr,
            light_v0: t.v0,
            light_e1: t.e1,
            light_e2: t.e2,
            light_normal: t.normal,
            light_pdf_area: scene.lights.pdf_area(li),
            light_floor: t.offset_floor,
            light_radiance: t.radiance,
        };
    }
    // Unused lanes repeat the first; their results are never read.
    for k in n..LANES {
        input[k] = input[0];
    }
    let v3 = |f: fn(&LaneInput) -> Vec3| V3::from_lanes(&std::array::from_fn(|k| f(&input[k])));
    let f1 = |f: fn(&LaneInput) -> f32| f32x8::new(std::array::from_fn(|k| f(&input[k])));
    let zero = f32x8::ZERO;
    let one = f32x8::ONE;

    // The shading frame (`shading_frame`; diffuse is two-sided).
    let (p, ng, ns, wo_world) = (v3(|l| l.p), v3(|l| l.ng), v3(|l| l.ns), v3(|l| l.wo_world));
    let flip = wo_world.dot(ng).simd_lt(zero);
    let ng_side = V3::select(flip, ng.neg(), ng);
    let n = V3::select(flip, ns.neg(), ns);
    // `Frame::from_normal` (Duff et al.).
    let sign = one.copysign(n.z);
    let a = f32x8::splat(-1.0) / (sign + n.z);
    let b = n.x * n.y * a;
    let fs = V3 {
        x: one + sign * n.x * n.x * a,
        y: sign * b,
        z: -sign * n.x,
    };
    let ft = V3 {
        x: b,
        y: sign + n.y * n.y * a,
        z: -n.y,
    };
    let to_local = |v: V3| V3 {
        x: v.dot(fs),
        y: v.dot(ft),
        z: v.dot(n),
    };
    let wo = to_local(wo_world);

    // The light sample (`sample_ld_weighted`, `Lights::sample`).
    let eps = f1(|l| l.eps);
    let origin = p.add(ng_side.scale(eps));
    let (ux, uy) = (f1(|l| l.u_light2[0]), f1(|l| l.u_light2[1]));
    // `uniform_triangle`.
    let lower = ux.simd_lt(uy);
    let two = f32x8::splat(2.0);
    let (b0_l, b1_u) = (ux / two, uy / two);
    let mut b0 = lower.select(b0_l, ux - b1_u);
    let mut b1 = lower.select(uy - b0_l, b1_u);
    b0 = b0.simd_lt(zero).select(zero, b0);
    b0 = b0.simd_gt(one).select(one, b0);
    b1 = b1.simd_lt(zero).select(zero, b1);
    let b1_max = one - b0;
    b1 = b1.simd_gt(b1_max).select(b1_max, b1);
    let point = v3(|l| l.light_v0)
        .add(v3(|l| l.light_e1).scale(b0))
        .add(v3(|l| l.light_e2).scale(b1));
    let d = point.sub(origin);
    let dist2 = d.dot(d);
    let mut ok = dist2.simd_gt(zero);
    let dist = dist2.sqrt();
    let wi = d.div(dist);
    let cos_light = -wi.dot(v3(|l| l.light_normal));
    let light_pdf = cos_light
        .simd_le(zero)
        .select(zero, f1(|l| l.light_pdf_area) * dist * dist / cos_light);
    ok &= light_pdf.simd_gt(zero) & light_pdf.is_finite();
    ok &= !wi.dot(ng_side).simd_le(zero);
    // The diffuse BSDF's value (f |cos|) and pdf.
    let wi_local = to_local(wi);
    ok &= !(wo.z.simd_le(zero) | wi_local.z.simd_le(zero));
    let f_scale = f32x8::splat(FRAC_1_PI) * wi_local.z;
    let bsdf_pdf = max_gt(wi_local.z, zero) * f32x8::splat(FRAC_1_PI);
    let light_eps = max_gt(
        max_gt(max_gt(point.x.abs(), point.y.abs()), point.z.abs()) * f32x8::splat(OFFSET_REL),
        f1(|l| l.light_floor),
    );
    let tmax = dist - light_eps;
    ok &= !tmax.simd_le(zero);
    // `power_heuristic(light_pdf, bsdf_pdf) / light_pdf`.
    let (pa, pb) = (light_pdf * light_pdf, bsdf_pdf * bsdf_pdf);
    let w = pa
        .is_inf()
        .select(one, (pa + pb).simd_le(zero).select(zero, pa / (pa + pb)));
    let light_weight = w / light_pdf;

    // The cosine-weighted direction (`cosine_hemisphere`: the concentric
    // disk with `sin_cos_quarter`'s polynomials).
    let (ux, uy) = (f1(|l| l.u_dir[0]), f1(|l| l.u_dir[1]));
    let (ox, oy) = (ux * two - one, uy * two - one);
    let centre = ox.simd_eq(zero) & oy.simd_eq(zero);
    let x_wedge = ox.abs().simd_gt(oy.abs());
    let r = x_wedge.select(ox, oy);
    let other = x_wedge.select(oy, ox);
    let x = f32x8::splat(PI / 4.0) * (other / r);
    let z = x * x;
    let (cs, cc) = (QUARTER_SIN.map(f32x8::splat), QUARTER_COS.map(f32x8::splat));
    let sin = x + x * z * (cs[0] + z * (cs[1] + z * cs[2]));
    let cos = one - f32x8::splat(0.5) * z + z * z * (cc[0] + z * (cc[1] + z * cc[2]));
    let (along, across) = (r * cos, r * sin);
    let dx = centre.select(zero, x_wedge.select(along, across));
    let dy = centre.select(zero, x_wedge.select(across, along));
    let s2 = one - (dx * dx + dy * dy);
    let dz = s2.simd_gt(zero).select(s2, zero).sqrt();
    let scatter_ok = !dz.simd_le(zero);
    let scatter_pdf = max_gt(dz, zero) * f32x8::splat(FRAC_1_PI);
    // `Frame::to_world`: (s x + t y) + n z.
    let wi_scatter = fs.scale(dx).add(ft.scale(dy)).add(n.scale(dz));
    let reflects = (wi_scatter.dot(ng) * wo_world.dot(ng)).simd_gt(zero);
    let scatter_ok = scatter_ok & reflects;

    let ok = ok.to_bitmask();
    let scatter_ok = scatter_ok.to_bitmask();
    let (f_scale, light_weight, tmax) =
        (f_scale.to_array(), light_weight.to_array(), tmax.to_array());
    let scatter_pdf = scatter_pdf.to_array();
    let (origin, wi, wi_scatter) = (origin.lanes(), wi.lanes(), wi_scatter.lanes());
    for (k, &(pi, _, albedo)) in lanes.iter().enumerate() {
        let path = &mut paths[pi as usize];
        let l = &input[k];
        let mut ld = Vec3::ZERO;
        if ok & (1 << k) != 0 {
            let f = albedo * f_scale[k];
            if f != Vec3::ZERO {
                work.shadow_rays += 1;
                if !scene.plain().occluded(origin[k], wi[k], tmax[k]) {
                    ld = f * l.light_radiance * light_weight[k];
                }
            }
        }
        path.radiance += path.beta * ld;
        if scatter_ok & (1 << k) == 0 {
            outcome[pi as usize] = Next::Terminate;
            continue;
        }
        path.beta *= albedo;
        path.prev_pdf = scatter_pdf[k];
        path.prev_delta = false;
        path.prev_point = l.p;
        path.depth += 1;
        path.origin = offset_ray_origin(l.p, l.ng, wi_scatter[k], l.eps);
        path.dir = wi_scatter[k];
        path.skip_instance = NO_SKIP;
        outcome[pi as usize] = russian_roulette(path, l.u_rr);
    }
}

#[cfg(test)]
mod tests {
    use super::super::shade;
    use super::*;
    use nppp_geom::SampleRng;

    /// A box of diffuse walls with a diffuse ball, a tilted diffuse quad, a
    /// black pillar (no light sample reaches a shadow ray), a smooth gem
    /// whose shading normals lean away from its faces ([`GEM_OBJ`]) and two
    /// lamps of different power (so light picks differ per lane).
    const SCENE: &str = r#"{
      "camera": {"position": [0, 0, -0.95], "look_at": [0, 0, 0], "fov_y_deg": 70, "width": 8, "height": 8},
      "materials": {
        "white": {"type": "diffuse", "albedo": [0.7, 0.7, 0.7]},
        "red": {"type": "diffuse", "albedo": [0.6, 0.1, 0.05]},
        "dark": {"type": "diffuse", "albedo": [0.02, 0.3, 0.01]},
        "black": {"type": "diffuse", "albedo": [0, 0, 0]},
        "lamp": {"type": "emitter", "radiance": [5, 4, 3]},
        "lamp2": {"type": "emitter", "radiance": [0.5, 1, 2]}
      },
      "meshes": {
        "room": {"box": {"min": [-1, -1, -1], "max": [1, 1, 1]}},
        "ball": {"icosphere": {"center": [0.3, -0.5, 0.2], "radius": 0.4, "subdivisions": 2}},
        "tilted": {"quad": [[-0.8, -0.2, -0.5], [-0.2, 0.3, 0.1], [-0.3, 0.6, 0.4], [-0.9, 0.1, -0.2]]},
        "pillar": {"box": {"min": [0.5, -1, -0.9], "max": [0.7, 0.2, -0.6]}},
        "gem": {"obj": "gem.obj", "smooth": true},
        "light": {"quad": [[-0.3, 0.99, -0.3], [0.3, 0.99, -0.3], [0.3, 0.99, 0.3], [-0.3, 0.99, 0.3]]},
        "light2": {"quad": [[0.99, -0.2, -0.2], [0.99, 0.2, -0.2], [0.99, 0.2, 0.2], [0.99, -0.2, 0.2]]}
      },
      "instances": [
        {"mesh": "room", "material": "white"},
        {"mesh": "ball", "material": "red"},
        {"mesh": "tilted", "material": "dark"},
        {"mesh": "pillar", "material": "black"},
        {"mesh": "gem", "material": "dark"},
        {"mesh": "light", "material": "lamp"},
        {"mesh": "light2", "material": "lamp2"}
      ]
    }"#;

    /// Whole wavefronts (every bounce to the end of every path, the films'
    /// exact sums, the work counted) are the same with the lanes as with
    /// scalar shading alone.
    #[test]
    fn a_wavefront_with_lanes_renders_what_scalar_shading_renders() {
        let dir = std::env::temp_dir().join(format!("nppp-wavefront-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("gem.obj"), GEM_OBJ).unwrap();
        let scene = nppp_scene::parse_scene(SCENE, &dir.join("scene.json")).unwrap();
        let _ = std::fs::remove_dir_all(&dir);
        let rs = RenderScene::new(&scene);
        let settings = IntegratorSettings {
            max_bounces: 8,
            seed: 1,
        };
        let (w, h) = (rs.camera.width, rs.camera.height);
        let render = |scalar_only: bool| {
            let mut wf = super::super::Wavefront {
                scalar_only,
                ..Default::default()
            };
            for y in 0..h {
                for x in 0..w {
                    for s in 0..37 {
                        let pixel = u64::from(y * w + x);
                        let mut rng = SampleRng::new(settings.seed, pixel, s);
                        let dir = rs.camera.ray_dir(crate::camera::jitter(&mut rng, x, y));
                        wf.paths
                            .push(PathState::camera(y * w + x, rng, rs.camera.origin, dir));
                    }
                }
            }
            let mut film = vec![crate::film::PixelSum::default(); (w * h) as usize];
            wf.run(&rs, &settings, &mut film);
            (film, wf.work.shadow_rays, wf.work.rays)
        };
        let (lanes, scalar) = (render(false), render(true));
        assert!(lanes.1 > 1000, "too few light samples: {}", lanes.1);
        assert_eq!(lanes, scalar);
    }

    /// An octahedron around (-0.4, 0.2, 0.3) with vertex normals tilted off
    /// its corners' directions: shading frames differ from the faces'.
    const GEM_OBJ: &str = "v -0.1 0.2 0.3\nv -0.7 0.2 0.3\nv -0.4 0.5 0.3\nv -0.4 -0.1 0.3\n\
        v -0.4 0.2 0.6\nv -0.4 0.2 0\n\
        vn 1 0.4 0\nvn -1 -0.3 0.2\nvn 0.3 1 0\nvn 0 -1 0.5\nvn -0.4 0 1\nvn 0.2 0.3 -1\n\
        f 1//1 3//3 5//5\nf 3//3 2//2 5//5\nf 2//2 4//4 5//5\nf 4//4 1//1 5//5\n\
        f 3//3 1//1 6//6\nf 2//2 3//3 6//6\nf 4//4 2//2 6//6\nf 1//1 4//4 6//6\n";

    /// Every field of every path, every outcome and the shadow-ray count are
    /// bit for bit what scalar `shade` gives, for full and partial groups,
    /// with the scene at three scales (ray offsets and light distances
    /// scale with it).
    #[test]
    fn lanes_match_scalar_shading() {
        for scale in [1.0f32, 1e-3, 3e4] {
            lanes_match_at(scale);
        }
    }

    fn lanes_match_at(scale: f32) {
        let json = SCENE.replace(
            r#""material": "white"}"#,
            &format!(r#""material": "white", "transform": {{"scale": {scale}}}}}"#),
        );
        let json = ["red", "dark", "black", "lamp", "lamp2"]
            .iter()
            .fold(json, |j, m| {
                j.replace(
                    &format!(r#""material": "{m}"}}"#),
                    &format!(r#""material": "{m}", "transform": {{"scale": {scale}}}}}"#),
                )
            });
        assert_eq!(
            json.matches("transform").count(),
            7,
            "every instance scaled"
        );
        let dir = std::env::temp_dir().join(format!("nppp-lanes-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("gem.obj"), GEM_OBJ).unwrap();
        let scene = nppp_scene::parse_scene(&json, &dir.join("scene.json")).unwrap();
        let _ = std::fs::remove_dir_all(&dir);
        let rs = RenderScene::new(&scene);
        let settings = IntegratorSettings {
            max_bounces: 6,
            seed: 1,
        };
        let mut draw = SampleRng::new(7, 0, 0);
        let mut paths = Vec::new();
        let mut hits = Vec::new();
        let mut smooth_hits = 0;
        while paths.len() < 2000 {
            let o = (Vec3::new(draw.uniform(), draw.uniform(), draw.uniform()) * 1.6 - 0.8) * scale;
            let d = nppp_geom::sampling::uniform_sphere(draw.uniform2());
            let Some(hit) = rs.plain().intersect(o, d, f32::INFINITY) else {
                continue;
            };
            let mut path = PathState::camera(
                paths.len() as u32,
                SampleRng::new(3, paths.len() as u64, 1),
                o,
                d,
            );
            path.depth = (draw.uniform() * 6.0) as u32;
            path.beta = Vec3::new(draw.uniform(), draw.uniform(), draw.uniform()) * 1.2;
            path.radiance = Vec3::splat(draw.uniform());
            if lane_albedo(&rs, &settings, &path, &hit).is_some() {
                let (ng, ns) = rs.normals_at(&hit);
                smooth_hits += usize::from((ns - ng).length() > 1e-3);
                paths.push(path);
                hits.push(hit);
            }
        }
        assert!(
            smooth_hits > 20,
            "too few hits on the smooth gem: {smooth_hits}"
        );
        let mut scalar = paths.clone();
        let mut scalar_work = WorkCounts::default();
        let scalar_next: Vec<Next> = scalar
            .iter_mut()
            .zip(&hits)
            .map(|(p, h)| shade(&rs, &settings, p, *h, &mut scalar_work))
            .collect();
        let mut lanes_work = WorkCounts::default();
        let mut lanes_next = vec![Next::Continue; paths.len()];
        // Groups of 8, then 3, 1 and 5 paths (unused lanes).
        let mut start = 0;
        for size in [8, 8, 3, 1, 5].into_iter().cycle() {
            if start >= paths.len() {
                break;
            }
            let end = (start + size).min(paths.len());
            let group: Vec<(u32, SceneHit, Vec3)> = (start..end)
                .map(|i| {
                    (
                        i as u32,
                        hits[i],
                        lane_albedo(&rs, &settings, &paths[i], &hits[i]).unwrap(),
                    )
                })
                .collect();
            shade_diffuse_lanes(&rs, &mut paths, &group, &mut lanes_next, &mut lanes_work);
            start = end;
        }
        assert_eq!(scalar_work.shadow_rays, lanes_work.shadow_rays);
        assert!(
            scalar_work.shadow_rays > 500,
            "too few light samples reached a shadow ray"
        );
        let mut continued = 0;
        for (i, (a, b)) in scalar.iter_mut().zip(&mut paths).enumerate() {
            assert_eq!(scalar_next[i], lanes_next[i], "scale {scale}, path {i}");
            assert_eq!(
                format!("{a:?}"),
                format!("{b:?}"),
                "scale {scale}, path {i}"
            );
            assert_eq!(
                a.rng.uniform().to_bits(),
                b.rng.uniform().to_bits(),
                "path {i}"
            );
            continued += usize::from(scalar_next[i] == Next::Continue);
        }
        assert!(continued > 100 && continued < paths.len(), "{continued}");
    }
}
