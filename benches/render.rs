//! BVH ray throughput (primary = coherent camera rays, incoherent = random
//! directions from surface points, occlusion = shadow rays to the light),
//! BSDF sampling, and whole-path samples per second on the default scene.

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use glam::Vec3;
use nppp_geom::SampleRng;
use nppp_render::bsdf::Bsdf;
use nppp_render::{RenderOptions, RenderScene};
use rayon::prelude::*;

const RAYS: usize = 1 << 16;

fn bvh(c: &mut Criterion) {
    let rs = RenderScene::new(&nppp_benches::default_scene());
    let (primary, incoherent, shadow) = nppp_benches::bench_rays(&rs, RAYS);
    let mut g = c.benchmark_group("bvh_2_threads");
    g.throughput(Throughput::Elements(primary.len() as u64));
    g.bench_function("closest_hit_primary", |b| {
        b.iter(|| {
            primary
                .par_iter()
                .filter(|(o, d)| rs.accel.intersect(*o, *d, f32::INFINITY).is_some())
                .count()
        })
    });
    g.throughput(Throughput::Elements(incoherent.len() as u64));
    g.bench_function("closest_hit_incoherent", |b| {
        b.iter(|| {
            incoherent
                .par_iter()
                .filter(|(o, d)| rs.accel.intersect(*o, *d, f32::INFINITY).is_some())
                .count()
        })
    });
    g.throughput(Throughput::Elements(shadow.len() as u64));
    g.bench_function("occlusion", |b| {
        b.iter(|| {
            shadow
                .par_iter()
                .filter(|(o, d, t)| rs.accel.occluded(*o, *d, *t))
                .count()
        })
    });
    g.finish();
}

fn bsdf(c: &mut Criterion) {
    let mut g = c.benchmark_group("bsdf_sample");
    g.throughput(Throughput::Elements(1024));
    let wo = Vec3::new(0.3, 0.2, 0.9).normalize();
    for (name, b) in [
        (
            "diffuse",
            Bsdf::Diffuse {
                albedo: Vec3::splat(0.5),
            },
        ),
        (
            "ggx",
            Bsdf::Conductor {
                reflectance: Vec3::ONE,
                alpha: 0.3,
            },
        ),
        ("dielectric", Bsdf::Dielectric { ior: 1.5 }),
    ] {
        let mut rng = SampleRng::from_seed(2);
        g.bench_function(name, |bch| {
            bch.iter(|| {
                let mut acc = 0.0f32;
                for _ in 0..1024 {
                    if let Some(s) = b.sample(wo, rng.uniform(), rng.uniform2()) {
                        acc += s.weight.x;
                    }
                }
                acc
            })
        });
    }
    g.finish();
}

fn path_tracing(c: &mut Criterion) {
    let mut scene = nppp_benches::default_scene();
    scene.camera.width = 64;
    scene.camera.height = 64;
    let rs = RenderScene::new(&scene);
    let spp = 4;
    let mut g = c.benchmark_group("path_tracing_default_scene");
    g.sample_size(10);
    g.throughput(Throughput::Elements(64 * 64 * spp as u64));
    g.bench_function("samples_M5", |b| {
        b.iter(|| {
            nppp_render::render(
                &rs,
                &RenderOptions {
                    spp,
                    max_bounces: 5,
                    seed: 1,
                    progress: false,
                },
            )
        })
    });
    g.finish();
}

criterion_group!(benches, bvh, bsdf, path_tracing);
criterion_main!(benches);
