//! The renderer's BLAS (crate::bvh, 8-wide, SoA) against obvhs' CWBVH on the
//! same triangles and rays, one thread, runs interleaved so that a noisy
//! machine hurts both alike. Prints Mrays/s per ray kind and the ratio.

use glam::{Vec3, Vec3A};
use nppp_render::RenderScene;
use nppp_render::bvh::MeshBvh;
use obvhs::{BvhBuildParams, ray::Ray, ray::RayHit, triangle::Triangle};
use std::time::{Duration, Instant};

fn main() {
    let scene = nppp_benches::default_scene();
    let rs = RenderScene::new(&scene);
    // The whole scene in world space, as the merged BLAS holds it.
    let mut tris = Vec::new();
    for inst in &scene.instances {
        let m = &scene.meshes[inst.mesh];
        let x = nppp_render::accel::InstanceXform::new(0, &inst.transform);
        for t in &m.triangles {
            let p = t.map(|i| Vec3A::from(x.point_to_world(m.positions[i as usize])));
            tris.push(Triangle {
                v0: p[0],
                v1: p[1],
                v2: p[2],
            });
        }
    }
    let t0 = Instant::now();
    let ours = MeshBvh::build(&tris);
    let t_ours = t0.elapsed();
    let t0 = Instant::now();
    let cw = obvhs::cwbvh::builder::build_cwbvh_from_tris(
        &tris,
        BvhBuildParams::medium_build(),
        &mut Duration::default(),
    );
    let t_cw = t0.elapsed();
    println!(
        "{} triangles; build bvh8 {:.2?} ({:.1} MiB), cwbvh {:.2?}",
        tris.len(),
        t_ours,
        ours.memory_bytes() as f64 / 1048576.0,
        t_cw
    );

    let (primary, incoherent, shadow) = nppp_benches::bench_rays(&rs, 1 << 18);
    let tri_test = |r: &Ray, id: usize| {
        let t = &tris[cw.primitive_indices[id] as usize];
        t.intersect(r)
    };
    let closest_cw = |o: Vec3, d: Vec3| {
        let mut hit = RayHit::none();
        cw.ray_traverse(
            Ray::new(o.into(), d.into(), 0.0, f32::INFINITY),
            &mut hit,
            tri_test,
        );
        hit.t
    };
    let closest_ours = |o: Vec3, d: Vec3| {
        ours.intersect(o.into(), d.into(), 0.0, f32::INFINITY)
            .map_or(f32::INFINITY, |h| h.t)
    };
    // Same answers first.
    let mut differ = 0;
    for (o, d) in primary.iter().chain(&incoherent) {
        let (a, b) = (closest_cw(*o, *d), closest_ours(*o, *d));
        if a != b && (a - b).abs() > 1e-4 * a.abs().max(1.0) {
            differ += 1;
        }
    }
    println!("closest-hit distances that differ: {differ}");
    let mut best = [[f64::MAX; 2]; 3];
    for _round in 0..5 {
        for (k, rays) in [&primary, &incoherent].iter().enumerate() {
            let t0 = Instant::now();
            let s: f32 = rays.iter().map(|(o, d)| closest_cw(*o, *d).min(1e9)).sum();
            let a = t0.elapsed().as_secs_f64();
            let t0 = Instant::now();
            let s2: f32 = rays
                .iter()
                .map(|(o, d)| closest_ours(*o, *d).min(1e9))
                .sum();
            let b = t0.elapsed().as_secs_f64();
            std::hint::black_box((s, s2));
            best[k][0] = best[k][0].min(a / rays.len() as f64);
            best[k][1] = best[k][1].min(b / rays.len() as f64);
        }
        let t0 = Instant::now();
        let c = shadow
            .iter()
            .filter(|(o, d, t)| {
                !cw.ray_traverse_miss(Ray::new((*o).into(), (*d).into(), 0.0, *t), tri_test)
            })
            .count();
        let a = t0.elapsed().as_secs_f64();
        let t0 = Instant::now();
        let c2 = shadow
            .iter()
            .filter(|(o, d, t)| ours.occluded((*o).into(), (*d).into(), 0.0, *t))
            .count();
        let b = t0.elapsed().as_secs_f64();
        assert_eq!(c, c2);
        best[2][0] = best[2][0].min(a / shadow.len() as f64);
        best[2][1] = best[2][1].min(b / shadow.len() as f64);
    }
    for (k, name) in ["primary", "incoherent", "shadow"].iter().enumerate() {
        let (a, b) = (1e-6 / best[k][0], 1e-6 / best[k][1]);
        println!(
            "{name:>10}: cwbvh {a:.2} Mrays/s, bvh8 {b:.2} Mrays/s, ratio {:.2}",
            b / a
        );
    }
}
