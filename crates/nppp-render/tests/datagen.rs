//! Training-data generation checked against what is known exactly: a mirror
//! sphere (one bounce, mirror direction, throughput = reflectance), a convex
//! diffuse object (one bounce, cosine lobe, throughput = albedo), a glass
//! sphere (energy conserved), the mask label against a direct BVH query,
//! zero-throughput exits, determinism across thread counts and the file
//! round trip.

use glam::{DVec3, Vec3};
use nppp_estimator::dataset::OCT_MAX_ANGLE;
use nppp_estimator::{DatasetReader, RayRecord, WriterOptions};
use nppp_geom::{BoundingSphere, Ray, SpherePair};
use nppp_render::datagen::{
    GenConfig, GenError, GenObject, GenStats, SPHERE_MARGIN, exit_rng, generate, input_ray,
    material_json, trace_rays,
};
use nppp_scene::procedural::Procedural;
use nppp_scene::{Material, Mesh, icosphere_mesh};
use std::path::{Path, PathBuf};

fn tmp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("nppp-datagen-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn procedural(p: Procedural) -> Mesh {
    let m = p.build().unwrap();
    Mesh {
        positions: m.positions,
        triangles: m.triangles,
        shading_normals: None,
    }
}

fn small_knot() -> Mesh {
    procedural(Procedural::TorusKnot {
        p: 2,
        q: 3,
        tube_radius: 0.5,
        segments: 96,
        sides: 12,
    })
}

fn object(mesh: &Mesh, material: Material) -> GenObject {
    GenObject::new("test-mesh", mesh, "test-material", material).unwrap()
}

fn cfg(rays: u64, k: u32, seed: u64, cap: u32) -> GenConfig {
    GenConfig {
        rays,
        k,
        seed,
        max_internal_bounces: cap,
    }
}

fn records(obj: &GenObject, c: &GenConfig) -> Vec<RayRecord> {
    trace_rays(&obj.tracer(c.max_internal_bounces), c.seed, 0..c.rays, c.k)
}

/// Unit-frame geometry of a ray's first hit, computed here from the mesh
/// (f64 facet normal) so the expectations do not reuse the generator's normals.
struct FirstHit {
    /// Unit frame.
    point: DVec3,
    dir: DVec3,
    /// Outward facet normal.
    normal: DVec3,
}

fn first_hit(obj: &GenObject, mesh: &Mesh, ray: &Ray) -> Option<FirstHit> {
    let o = obj.sphere.from_unit_point(ray.origin);
    let h = obj
        .blas
        .intersect(o.into(), ray.dir.into(), 0.0, f32::INFINITY)?;
    let t = mesh.triangles[h.prim as usize];
    let p = |k: usize| mesh.positions[t[k] as usize].as_dvec3();
    let normal = (p(1) - p(0)).cross(p(2) - p(0)).normalize();
    let hit = o.as_dvec3() + ray.dir.as_dvec3() * f64::from(h.t);
    let c = obj.sphere.center.as_dvec3();
    let point = (hit - c) / f64::from(obj.sphere.radius);
    Some(FirstHit {
        point,
        dir: ray.dir.as_dvec3(),
        normal,
    })
}

/// Where the ray from unit-frame point `p` along unit `d` leaves the unit sphere.
fn leave_sphere(p: DVec3, d: DVec3) -> DVec3 {
    let b = p.dot(d);
    let s = -b + (b * b - (p.length_squared() - 1.0)).max(0.0).sqrt();
    p + d * s
}

fn all_exits(recs: &[RayRecord]) -> impl Iterator<Item = &nppp_estimator::Exit> {
    recs.iter().flat_map(|r| r.exits.iter())
}

#[test]
fn mirror_sphere_reflects_once_about_the_facet_normal() {
    let mesh = icosphere_mesh(Vec3::ZERO, 1.0, 5);
    let r = Vec3::new(0.9, 0.5, 0.25);
    let obj = object(
        &mesh,
        Material::Conductor {
            reflectance: r,
            roughness: 0.0,
        },
    );
    let c = cfg(600, 3, 11, 64);
    let recs = records(&obj, &c);
    let mut hits = 0;
    for (i, rec) in recs.iter().enumerate() {
        let ray = rec.pair.to_ray().unwrap();
        let Some(h) = first_hit(&obj, &mesh, &ray) else {
            assert!(!rec.hit && rec.exits.is_empty(), "ray {i}");
            continue;
        };
        hits += 1;
        assert!(rec.hit && rec.exits.len() == 3, "ray {i}");
        let mirror = h.dir - 2.0 * h.dir.dot(h.normal) * h.normal;
        let exit_pos = leave_sphere(h.point, mirror);
        for e in &rec.exits {
            assert_eq!(e.bounces, 1, "ray {i}");
            assert_eq!(e.throughput, r, "ray {i}");
            assert_eq!(e.radiance, Vec3::ZERO);
            let dir_err = e.direction.as_dvec3().angle_between(mirror);
            assert!(
                dir_err < 1e-5,
                "ray {i}: exit direction {} vs mirror {mirror} ({dir_err} rad)",
                e.direction
            );
            // The origin is moved off the surface by ~2e-5 of the radius before the exit ray.
            let pos_err = e.position.as_dvec3().distance(exit_pos);
            assert!(
                pos_err < 2e-4,
                "ray {i}: exit position {} vs {exit_pos} ({pos_err})",
                e.position
            );
        }
    }
    assert!(hits > 300, "{hits} hits of 600");
}

#[test]
fn hit_fraction_of_a_centred_sphere_is_its_relative_radius_squared() {
    // The chord between two independent uniform points on the sphere passes
    // at distance cos(psi / 2) from the centre, so a centred ball of relative
    // radius rho is hit with probability rho^2. This checks that input rays
    // are uniform in the 4D parameterization: points uniform in theta instead
    // of cos(theta) give 0.114 instead of 0.09 at rho = 0.3.
    let mesh = icosphere_mesh(Vec3::ZERO, 1.0, 5);
    let mut obj = object(
        &mesh,
        Material::Diffuse {
            albedo: Vec3::splat(0.5),
        },
    );
    // Inscribed radius of the icosphere's facets; its vertices are at radius 1.
    let rho_in = mesh
        .triangles
        .iter()
        .map(|t| {
            let p = |k: usize| mesh.positions[t[k] as usize].as_dvec3();
            p(0).dot((p(1) - p(0)).cross(p(2) - p(0)).normalize())
        })
        .fold(1.0f64, f64::min);
    let n = 40_000u64;
    for rho in [0.3f64, 0.6, 0.9] {
        // The sphere is set by hand: this is about the ray distribution, not
        // about how tight `BoundingSphere::around` is.
        obj.sphere = BoundingSphere {
            center: Vec3::ZERO,
            radius: (1.0 / rho) as f32,
        };
        let tracer = obj.tracer(64);
        let hits = (0..n).filter(|&i| tracer.hits(&input_ray(3, i).1)).count() as f64;
        let frac = hits / n as f64;
        let rr = f64::from(obj.sphere.radius);
        let (lo, hi) = ((rho_in / rr).powi(2), (1.0 / rr).powi(2));
        let tol = 5.0 * (hi * (1.0 - hi) / n as f64).sqrt();
        assert!(
            frac > lo - tol && frac < hi + tol,
            "rho {rho}: hit fraction {frac}, expected in [{lo}, {hi}] +- {tol}"
        );
    }
}

#[test]
fn convex_diffuse_object_exits_in_a_cosine_lobe() {
    let mesh = icosphere_mesh(Vec3::new(0.3, -0.2, 0.1), 2.0, 3);
    let albedo = Vec3::new(0.7, 0.5, 0.3);
    let obj = object(&mesh, Material::Diffuse { albedo });
    let c = cfg(2500, 16, 5, 64);
    let recs = records(&obj, &c);
    let (mut n, mut sum_cos) = (0usize, 0.0f64);
    let mut bins = [0usize; 10];
    for (i, rec) in recs.iter().enumerate() {
        let ray = rec.pair.to_ray().unwrap();
        let Some(h) = first_hit(&obj, &mesh, &ray) else {
            assert!(!rec.hit, "ray {i}");
            continue;
        };
        assert!(rec.hit && rec.exits.len() == 16);
        for e in &rec.exits {
            assert_eq!(e.bounces, 1, "ray {i}: a convex object scatters once");
            assert_eq!(e.throughput, albedo);
            let d = e.direction.as_dvec3();
            let cos = d.dot(h.normal);
            assert!(cos > 0.0, "ray {i}: exit into the object (cos {cos})");
            let pos_err = e.position.as_dvec3().distance(leave_sphere(h.point, d));
            assert!(pos_err < 1e-3, "ray {i}: exit position off by {pos_err}");
            n += 1;
            sum_cos += cos;
            bins[((cos * cos * 10.0) as usize).min(9)] += 1;
        }
    }
    assert!(n > 20_000, "{n} exits");
    // Cosine lobe: E[cos] = 2/3, Var[cos] = 1/2 - 4/9 = 1/18; cos^2 is uniform.
    let mean = sum_cos / n as f64;
    let se = (1.0f64 / 18.0 / n as f64).sqrt();
    assert!(
        (mean - 2.0 / 3.0).abs() < 5.0 * se,
        "mean cos {mean}, expected 2/3 +- {}",
        5.0 * se
    );
    let expect = n as f64 / 10.0;
    let chi2: f64 = bins
        .iter()
        .map(|&b| (b as f64 - expect).powi(2) / expect)
        .sum();
    // 9 degrees of freedom: P(chi2 > 33.7) = 1e-4.
    assert!(
        chi2 < 33.7,
        "cos^2 histogram {bins:?} is not uniform (chi2 {chi2})"
    );
    // A wrong lobe (uniform hemisphere: cos uniform, cos^2 not) fails this.
    let uniform_bins: Vec<f64> = (0..10)
        .map(|b| ((b as f64 + 1.0) / 10.0).sqrt() - (b as f64 / 10.0).sqrt())
        .collect();
    let chi2_uniform: f64 = bins
        .iter()
        .zip(&uniform_bins)
        .map(|(&b, p)| (b as f64 - p * n as f64).powi(2) / (p * n as f64))
        .sum();
    assert!(
        chi2_uniform > 1000.0,
        "the test cannot tell a cosine lobe from a uniform hemisphere ({chi2_uniform})"
    );
}

#[test]
fn glass_sphere_conserves_energy() {
    let mesh = icosphere_mesh(Vec3::ZERO, 1.0, 3);
    let obj = object(&mesh, Material::Dielectric { ior: 1.5 });
    // A faceted sphere, unlike a round one, can trap light by total internal
    // reflection (facet normals tilt by a few degrees); at this seed the
    // longest such orbit escapes after a few hundred bounces, so a cap of 512
    // never fires and every path must come out with all its energy.
    let recs = records(&obj, &cfg(1500, 16, 9, 512));
    let mut stats = GenStats::default();
    let (mut reflected_once, mut through) = (0u64, 0u64);
    for e in all_exits(&recs) {
        stats.exits += 1;
        // Radiance scaled by 1/eta^2 on the way in and eta^2 on the way out.
        assert!(
            (e.throughput - Vec3::ONE).abs().max_element() < 1e-5,
            "{e:?}"
        );
        for (s, t) in stats.throughput_sum.iter_mut().zip(e.throughput.to_array()) {
            *s += f64::from(t);
        }
        reflected_once += (e.bounces == 1) as u64;
        through += (e.bounces >= 2) as u64;
    }
    assert!(stats.exits > 12_000);
    let mean = stats.mean_throughput();
    assert!(
        mean.iter().all(|m| (m - 1.0).abs() < 1e-5),
        "mean throughput {mean:?}"
    );
    // Both Fresnel branches are exercised: external reflection, and refraction
    // through the sphere (at least two bounces).
    assert!(
        reflected_once > stats.exits / 50 && through > stats.exits / 2,
        "{reflected_once} reflected, {through} through"
    );

    // With the default cap the trapped orbits end as zero exits at the cap,
    // and nothing else is lost: the mean is exactly 1 - P(capped).
    let cap = 64;
    let recs = records(&obj, &cfg(1500, 16, 9, cap));
    let (mut n, mut capped, mut sum) = (0u64, 0u64, 0.0f64);
    for e in all_exits(&recs) {
        n += 1;
        sum += f64::from(e.throughput.x);
        if e.throughput == Vec3::ZERO {
            assert_eq!(
                e.bounces, cap,
                "glass absorbs nothing: a zero exit must be a capped one ({e:?})"
            );
            capped += 1;
        } else {
            assert!(
                (e.throughput - Vec3::ONE).abs().max_element() < 1e-5,
                "{e:?}"
            );
        }
    }
    assert!(capped > 0 && capped * 50 < n, "{capped} capped of {n}");
    assert!((sum / n as f64 - (1.0 - capped as f64 / n as f64)).abs() < 1e-5);
}

/// Moller-Trumbore over every triangle, in f64: an independent hit test.
fn brute_force_hits(mesh: &Mesh, o: DVec3, d: DVec3) -> bool {
    mesh.triangles.iter().any(|t| {
        let p = |k: usize| mesh.positions[t[k] as usize].as_dvec3();
        let (e1, e2) = (p(1) - p(0), p(2) - p(0));
        let q = d.cross(e2);
        let det = e1.dot(q);
        if det.abs() < 1e-14 {
            return false;
        }
        let s = o - p(0);
        let b1 = s.dot(q) / det;
        let r = s.cross(e1);
        let b2 = d.dot(r) / det;
        b1 >= 0.0 && b2 >= 0.0 && b1 + b2 <= 1.0 && e2.dot(r) / det > 0.0
    })
}

#[test]
fn mask_label_agrees_with_a_direct_bvh_query() {
    let mesh = small_knot();
    let obj = object(
        &mesh,
        Material::Diffuse {
            albedo: Vec3::splat(0.6),
        },
    );
    let dir = tmp_dir("mask");
    let path = dir.join("mask.npppdata");
    let c = cfg(4000, 1, 21, 64);
    let report = generate(&obj, &c, &path, WriterOptions::default(), &mut |_| {}).unwrap();
    let recs = DatasetReader::open(&path).unwrap().read_all().unwrap();
    assert_eq!(recs.len(), 4000);
    let (mut hits, mut disagree_brute) = (0usize, 0usize);
    for (i, rec) in recs.iter().enumerate() {
        // The pair read back from the file reproduces the traced ray exactly.
        let (pair, ray) = input_ray(c.seed, i as u64);
        assert_eq!(rec.pair, pair);
        assert_eq!(rec.pair.to_ray(), Some(ray));
        let o = obj.sphere.from_unit_point(ray.origin);
        let direct = obj
            .blas
            .intersect(o.into(), ray.dir.into(), 0.0, f32::INFINITY)
            .is_some();
        assert_eq!(rec.hit, direct, "ray {i}");
        assert_eq!(rec.exits.len(), rec.hit as usize);
        hits += rec.hit as usize;
        disagree_brute +=
            (brute_force_hits(&mesh, o.as_dvec3(), ray.dir.as_dvec3()) != rec.hit) as usize;
    }
    assert_eq!(report.stats.hits, hits as u64);
    assert!(
        hits > 400 && hits < 3600,
        "{hits} hits: the knot should be neither missed nor filling the sphere"
    );
    // Edge-grazing rays may differ between f32 BVH and f64 brute force; a
    // wrong ray mapping or sphere would disagree on a large fraction.
    assert!(
        disagree_brute <= 2,
        "{disagree_brute} of 4000 labels disagree with brute force"
    );
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn black_object_gives_zero_throughput_exits() {
    let mesh = icosphere_mesh(Vec3::ZERO, 1.0, 2);
    let obj = object(&mesh, Material::Diffuse { albedo: Vec3::ZERO });
    let dir = tmp_dir("black");
    let path = dir.join("black.npppdata");
    let report = generate(
        &obj,
        &cfg(300, 8, 2, 64),
        &path,
        WriterOptions::default(),
        &mut |_| {},
    )
    .unwrap();
    assert!(report.stats.exits > 1000);
    assert_eq!(report.stats.zero_exits, report.stats.exits);
    assert_eq!(report.stats.mean_throughput(), [0.0; 3]);
    let recs = DatasetReader::open(&path).unwrap().read_all().unwrap();
    for e in all_exits(&recs) {
        assert_eq!(e.throughput, Vec3::ZERO);
        assert_eq!(
            e.bounces, 1,
            "absorbed at the first hit, after one scattering event"
        );
        assert!(
            (e.position.length() - 1.0).abs() < 1e-4 && (e.direction.length() - 1.0).abs() < 1e-4
        );
    }
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn bounce_cap_turns_longer_paths_into_zero_exits() {
    // A white Menger sponge: no absorption, so only the cap can zero a path,
    // and the cap-1 run follows the cap-64 run's first bounce exactly (same streams).
    let mesh = procedural(Procedural::MengerSponge { level: 1 });
    let obj = object(&mesh, Material::Diffuse { albedo: Vec3::ONE });
    let long = records(&obj, &cfg(1500, 8, 4, 64));
    let short = records(&obj, &cfg(1500, 8, 4, 1));
    let (mut zero, mut n) = (0usize, 0usize);
    for (a, b) in long.iter().zip(&short) {
        assert_eq!((a.pair, a.hit), (b.pair, b.hit));
        for (ea, eb) in a.exits.iter().zip(&b.exits) {
            n += 1;
            assert!(eb.bounces <= 1);
            if ea.bounces >= 2 {
                assert_eq!(
                    eb.throughput,
                    Vec3::ZERO,
                    "a path with {} bounces must be capped at 1",
                    ea.bounces
                );
                assert_eq!(eb.bounces, 1);
                zero += 1;
            } else {
                assert_eq!(ea, eb, "a one-bounce path must not change with the cap");
                assert_eq!(eb.throughput, Vec3::ONE);
            }
            if ea.throughput == Vec3::ZERO {
                assert_eq!(ea.bounces, 64, "white sponge: only the cap zeroes a path");
            }
        }
    }
    assert!(
        zero * 20 > n,
        "only {zero} of {n} exits bounced twice: the object is not concave enough for this test"
    );
}

#[test]
fn output_is_identical_at_any_thread_count() {
    let mesh = small_knot();
    let obj = object(
        &mesh,
        Material::Conductor {
            reflectance: Vec3::splat(0.9),
            roughness: 0.3,
        },
    );
    let dir = tmp_dir("det");
    let c = cfg(1500, 24, 77, 64);
    let run = |threads: usize, name: &str, c: GenConfig| {
        let path = dir.join(name);
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        let opts = WriterOptions {
            chunk_rays: 128,
            compress: true,
            replace: true,
        };
        let report = pool
            .install(|| generate(&obj, &c, &path, opts, &mut |_| {}))
            .unwrap();
        (std::fs::read(&path).unwrap(), report.stats)
    };
    let (one, s1) = run(1, "t1.npppdata", c);
    let (two, s2) = run(2, "t2.npppdata", c);
    let (three, _) = run(3, "t3.npppdata", c);
    assert!(s1.hits > 100);
    assert!(
        one == two && one == three,
        "files differ between 1, 2 and 3 threads"
    );
    assert_eq!(
        (s1.exits, s1.throughput_sum, s1.bounce_sum),
        (s2.exits, s2.throughput_sum, s2.bounce_sum)
    );
    let (other, _) = run(2, "seed.npppdata", GenConfig { seed: 78, ..c });
    assert_ne!(one, other, "the seed must matter");
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn data_round_trips_through_the_file() {
    let mesh = small_knot();
    let material = Material::Conductor {
        reflectance: Vec3::new(1.0, 0.78, 0.34),
        roughness: 0.2,
    };
    let obj = GenObject::new("knot", &mesh, "gold", material).unwrap();
    let dir = tmp_dir("roundtrip");
    let path = dir.join("sub.npppdata");
    let c = cfg(700, 12, 8, 16);
    let mut calls = 0usize;
    let report = generate(
        &obj,
        &c,
        &path,
        WriterOptions {
            chunk_rays: 100,
            compress: true,
            replace: true,
        },
        &mut |s| {
            calls += 1;
            assert!(s.rays <= 700);
        },
    )
    .unwrap();
    assert!(calls >= 1);
    let mut reader = DatasetReader::open(&path).unwrap();
    let h = reader.header().clone();
    assert_eq!(
        (h.mesh_name.as_str(), h.material_name.as_str()),
        ("knot", "gold")
    );
    assert_eq!(h.mesh_hash, nppp_scene::mesh_content_hash(&mesh));
    assert_eq!(
        h.material_hash,
        nppp_scene::material_content_hash(&material)
    );
    assert_eq!((h.k, h.seed, h.max_internal_bounces), (12, 8, 16));
    assert_eq!(
        h.sphere.center.to_array().map(f32::to_bits),
        obj.sphere.center.to_array().map(f32::to_bits)
    );
    assert_eq!(h.sphere.radius.to_bits(), obj.sphere.radius.to_bits());
    assert_eq!(reader.hit_count(), report.stats.hits);
    assert_eq!(reader.exit_count(), report.stats.exits);
    assert_eq!(
        report.summary.file_bytes,
        std::fs::metadata(&path).unwrap().len()
    );
    // The stored material description reads back as the same material.
    let scene = format!(
        r#"{{"camera": {{"position": [0,0,-5], "look_at": [0,0,0], "fov_y_deg": 40, "width": 8, "height": 8}},
            "materials": {{"m": {}}}, "meshes": {{"b": {{"box": {{"min": [0,0,0], "max": [1,1,1]}}}}}},
            "instances": [{{"mesh": "b", "material": "m"}}]}}"#,
        h.material_json
    );
    let parsed = nppp_scene::parse_scene(&scene, Path::new("inline.json")).unwrap();
    assert_eq!(parsed.materials[0], material);

    let back = reader.read_all().unwrap();
    let mem = records(&obj, &c);
    assert_eq!(back.len(), mem.len());
    let mut exits = 0;
    for (b, m) in back.iter().zip(&mem) {
        assert_eq!(
            (b.pair, b.hit, b.exits.len()),
            (m.pair, m.hit, m.exits.len())
        );
        for (eb, em) in b.exits.iter().zip(&m.exits) {
            exits += 1;
            // In f64: acos of an f32 dot product cannot resolve 1e-4 rad.
            let max = f64::from(OCT_MAX_ANGLE) * 1.01;
            assert!(eb.position.as_dvec3().angle_between(em.position.as_dvec3()) <= max);
            assert!(
                eb.direction
                    .as_dvec3()
                    .angle_between(em.direction.as_dvec3())
                    <= max
            );
            // Half floats: 11 significant bits.
            assert!(
                (eb.throughput - em.throughput).abs().max_element()
                    <= em.throughput.max_element() * 1e-3 + 1e-7
            );
            assert_eq!(eb.bounces, em.bounces);
        }
    }
    assert_eq!(exits as u64, report.stats.exits);
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn material_json_reads_back_for_every_type() {
    for m in [
        Material::Diffuse {
            albedo: Vec3::new(0.8, 0.6, 0.35),
        },
        Material::Conductor {
            reflectance: Vec3::new(0.1, 0.2, 0.3),
            roughness: 0.0,
        },
        Material::Dielectric { ior: 1.333 },
        Material::Emitter {
            radiance: Vec3::new(17.0, 12.0, 4.0),
        },
    ] {
        let scene = format!(
            r#"{{"camera": {{"position": [0,0,-5], "look_at": [0,0,0], "fov_y_deg": 40, "width": 8, "height": 8}},
                "materials": {{"m": {}}}, "meshes": {{"b": {{"box": {{"min": [0,0,0], "max": [1,1,1]}}}}}},
                "instances": [{{"mesh": "b", "material": "m"}}]}}"#,
            material_json(&m)
        );
        let parsed = nppp_scene::parse_scene(&scene, Path::new("inline.json")).unwrap();
        assert_eq!(parsed.materials[0], m);
    }
}

#[test]
fn scene_instance_is_taken_in_mesh_space() {
    let scene = nppp_scene::parse_scene(
        r#"{"camera": {"position": [0,0,-5], "look_at": [0,0,0], "fov_y_deg": 40, "width": 8, "height": 8},
            "materials": {"white": {"type": "diffuse", "albedo": [0.7, 0.7, 0.7]}},
            "meshes": {"ball": {"icosphere": {"center": [1, 2, 3], "radius": 0.5, "subdivisions": 1}}},
            "instances": [{"mesh": "ball", "material": "white",
                           "transform": {"scale": 100, "translate": [500, 0, 0]}}]}"#,
        Path::new("inline.json"),
    )
    .unwrap();
    let obj = GenObject::from_scene_instance(&scene, 0).unwrap();
    assert_eq!(
        (obj.mesh_name.as_str(), obj.material_name.as_str()),
        ("ball", "white")
    );
    // The sphere of the untransformed mesh (the transform would put it near x = 600).
    assert_eq!(
        obj.sphere,
        BoundingSphere::around(&scene.meshes[0].positions, SPHERE_MARGIN)
    );
    assert!(obj.sphere.center.distance(Vec3::new(1.0, 2.0, 3.0)) < obj.sphere.radius);
    assert_eq!(
        obj.mesh_hash,
        nppp_scene::mesh_content_hash(&scene.meshes[0])
    );
    let e = GenObject::from_scene_instance(&scene, 3)
        .err()
        .unwrap()
        .to_string();
    assert!(
        e.contains("instance 3 does not exist") && e.contains("1 instances"),
        "{e}"
    );
}

#[test]
fn bad_input_is_an_error_not_a_panic() {
    let mesh = icosphere_mesh(Vec3::ZERO, 1.0, 1);
    let obj = object(
        &mesh,
        Material::Diffuse {
            albedo: Vec3::splat(0.5),
        },
    );
    let dir = tmp_dir("bad");
    let path = dir.join("x.npppdata");
    for (c, what) in [
        (cfg(0, 4, 0, 64), "rays = 0"),
        (cfg(10, 0, 0, 64), "k = 0"),
        (cfg(10, u32::MAX, 0, 64), "k = "),
        (cfg(10, 4, 0, 0), "max_internal_bounces = 0"),
    ] {
        let e = generate(&obj, &c, &path, WriterOptions::default(), &mut |_| {})
            .err()
            .unwrap();
        assert!(
            matches!(e, GenError::Config(_)) && e.to_string().contains(what),
            "{e}"
        );
    }
    assert!(
        !path.exists(),
        "a rejected configuration must not create the file"
    );
    let e = generate(
        &obj,
        &cfg(10, 4, 0, 64),
        &dir.join("no/such/dir/x.npppdata"),
        WriterOptions::default(),
        &mut |_| {},
    );
    assert!(e.err().unwrap().to_string().contains("no/such/dir"));
    let empty = Mesh::default();
    let e = GenObject::new(
        "nothing",
        &empty,
        "m",
        Material::Diffuse { albedo: Vec3::ONE },
    )
    .err()
    .unwrap();
    assert!(
        e.to_string().contains("\"nothing\" has no triangles"),
        "{e}"
    );
    // A lamp ends every path that reaches it: nothing to learn.
    let ball = icosphere_mesh(Vec3::ZERO, 1.0, 1);
    let e = GenObject::new(
        "ball",
        &ball,
        "lamp",
        Material::Emitter {
            radiance: Vec3::ONE,
        },
    )
    .err()
    .unwrap();
    assert!(
        e.to_string().contains("material \"lamp\" is an emitter"),
        "{e}"
    );
    // A degenerate pair (both points equal) has no ray; input_ray never returns one.
    assert!(SpherePair([0.3, 0.4, 0.3, 0.4]).to_ray().is_none());
    for i in 0..1000 {
        assert!(input_ray(0, i).0.to_ray().is_some());
    }
    let _ = std::fs::remove_dir_all(dir);
}

/// Next-event estimation through the estimator (issue 18): each exit of an
/// object with a non-delta surface comes with its walk's picked vertex. On
/// a convex diffuse object a walk has one vertex, the first hit, so the
/// picked vertex is known exactly: the first hit's point and facet normal,
/// the direction back along the ray, throughput 1 (before scattering; the
/// pick's probability is 1) and index 0. A glass object's data has none.
#[test]
fn picked_vertex_of_a_convex_diffuse_object_is_its_first_hit() {
    let mesh = icosphere_mesh(Vec3::new(0.3, -0.2, 0.1), 2.0, 3);
    let obj = object(
        &mesh,
        Material::Diffuse {
            albedo: Vec3::new(0.7, 0.5, 0.3),
        },
    );
    let c = cfg(400, 8, 9, 64);
    assert!(obj.header(&c).vertices);
    let recs = records(&obj, &c);
    let mut checked = 0;
    for (i, rec) in recs.iter().enumerate() {
        assert_eq!(rec.vertices.len(), rec.exits.len(), "ray {i}");
        let ray = rec.pair.to_ray().unwrap();
        let Some(h) = first_hit(&obj, &mesh, &ray) else {
            continue;
        };
        for v in &rec.vertices {
            let pos_err = v.position.as_dvec3().distance(h.point);
            assert!(
                pos_err < 1e-4,
                "ray {i}: vertex off the first hit by {pos_err}"
            );
            assert!(
                v.normal.as_dvec3().dot(h.normal) > 0.9999,
                "ray {i}: normal {}",
                v.normal
            );
            assert!(v.wo.as_dvec3().dot(-h.dir) > 0.9999, "ray {i}: wo {}", v.wo);
            assert_eq!((v.beta, v.index), (Vec3::ONE, 0), "ray {i}");
            checked += 1;
        }
    }
    assert!(checked > 500, "{checked} vertices");
    // The exits are those of a walk that records nothing (the pick draws
    // after the walk, from the same stream).
    let tracer = obj.tracer(c.max_internal_bounces);
    for (i, rec) in recs.iter().enumerate().filter(|(_, r)| r.hit).take(20) {
        let ray = rec.pair.to_ray().unwrap();
        for (j, e) in rec.exits.iter().enumerate() {
            let mut rng = exit_rng(c.seed, i as u64, j as u32);
            match tracer.walk(&ray, &mut rng) {
                nppp_render::object_walk::Walk::Exit(w) => assert_eq!(&w, e, "ray {i}, exit {j}"),
                nppp_render::object_walk::Walk::Miss => panic!("ray {i}: a hit that misses"),
            }
        }
    }
    let glass = object(&mesh, Material::Dielectric { ior: 1.5 });
    assert!(!glass.header(&c).vertices);
    assert!(records(&glass, &c).iter().all(|r| r.vertices.is_empty()));
}
