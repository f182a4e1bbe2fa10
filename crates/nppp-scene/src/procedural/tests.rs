use super::*;

fn sphere(subdivisions: u32, seed: u64) -> Procedural {
    Procedural::DisplacedSphere {
        subdivisions,
        amplitude: 0.3,
        frequency: 4.0,
        seed,
    }
}

fn knot_with(p: u32, q: u32, tube_radius: f32, segments: u32, sides: u32) -> Procedural {
    Procedural::TorusKnot {
        p,
        q,
        tube_radius,
        segments,
        sides,
    }
}

/// Every check a closed, welded, outward-facing, non-degenerate mesh in
/// the unit sphere must pass; returns the enclosed volume.
fn check_closed_mesh(mesh: &TriMesh) -> f64 {
    assert!(!mesh.triangles.is_empty());
    for (i, p) in mesh.positions.iter().enumerate() {
        assert!(p.is_finite(), "vertex {i} is {p}");
        assert!(p.length() <= 1.0, "vertex {i} at radius {}", p.length());
    }
    // Welded: no two vertices at the same place, otherwise the index-based
    // edge check below could pass on a mesh with cracks. (Sorting instead
    // of hashing keeps the checks of large meshes fast.)
    let mut bits: Vec<[u32; 3]> = mesh
        .positions
        .iter()
        .map(|p| p.to_array().map(f32::to_bits))
        .collect();
    bits.sort_unstable();
    if let Some(w) = bits.windows(2).find(|w| w[0] == w[1]) {
        panic!("duplicate vertex {:?}", w[0].map(f32::from_bits));
    }
    // Each directed edge once, and its reverse once: every edge is shared
    // by exactly two triangles that traverse it in opposite directions.
    let mut directed = Vec::with_capacity(mesh.triangles.len() * 3);
    let mut used = vec![false; mesh.positions.len()];
    let mut volume6 = 0.0f64;
    for (t, &[a, b, c]) in mesh.triangles.iter().enumerate() {
        assert!(a != b && b != c && c != a, "triangle {t} repeats a vertex");
        for (x, y) in [(a, b), (b, c), (c, a)] {
            directed.push((x, y));
            used[x as usize] = true;
        }
        let [pa, pb, pc] = [a, b, c].map(|i| mesh.positions[i as usize].as_dvec3());
        let area = 0.5 * (pb - pa).cross(pc - pa).length();
        assert!(area > 1e-9, "triangle {t} has area {area}");
        volume6 += pa.dot(pb.cross(pc));
    }
    directed.sort_unstable();
    if let Some(w) = directed.windows(2).find(|w| w[0] == w[1]) {
        panic!("edge {:?} used twice in one direction", w[0]);
    }
    let mut reversed: Vec<(u32, u32)> = directed.iter().map(|&(x, y)| (y, x)).collect();
    reversed.sort_unstable();
    if let Some((e, _)) = directed.iter().zip(&reversed).find(|(e, r)| e != r) {
        panic!("edge {e:?} or its reverse has no partner");
    }
    let volume = volume6 / 6.0;
    assert!(volume > 0.0, "signed volume {volume}: faces point inward");
    volume
}

#[test]
fn procedural_defaults_build_clean() {
    for object in Procedural::defaults() {
        let mesh = object.build().unwrap();
        assert_eq!(
            mesh.triangles.len() as u64,
            object.triangle_count(),
            "{}",
            object.name()
        );
        check_closed_mesh(&mesh);
        // Normalised to fill the unit sphere, not merely fit inside it.
        let max = mesh
            .positions
            .iter()
            .map(|p| p.length())
            .fold(0.0, f32::max);
        assert!(max > 0.9999, "{} reaches only {max}", object.name());
    }
}

#[test]
fn procedural_triangle_counts() {
    assert_eq!(sphere(0, 1).build().unwrap().triangles.len(), 20);
    assert_eq!(sphere(3, 1).build().unwrap().triangles.len(), 1280);
    assert_eq!(sphere(7, 1).triangle_count(), 327_680);
    let mesh = sphere(4, 1).build().unwrap();
    assert_eq!(mesh.positions.len(), 10 * 4usize.pow(4) + 2);
    assert_eq!(
        knot_with(2, 3, 0.5, 64, 12)
            .build()
            .unwrap()
            .triangles
            .len(),
        2 * 64 * 12
    );
    for (level, triangles) in [
        (0, 12),
        (1, 2 * (40 + 32)),
        (2, 2 * (800 + 256)),
        (3, 36_096),
    ] {
        let sponge = Procedural::MengerSponge { level };
        assert_eq!(
            sponge.build().unwrap().triangles.len(),
            triangles,
            "level {level}"
        );
    }
    assert_eq!(
        Procedural::MengerSponge { level: 4 }.triangle_count(),
        672_768
    );
}

#[test]
fn procedural_menger_level_4_is_closed() {
    let mesh = Procedural::MengerSponge { level: 4 }.build().unwrap();
    assert_eq!(mesh.triangles.len(), 672_768);
    let volume = check_closed_mesh(&mesh);
    // Solid fraction (20/27)^4 of a cube whose half-diagonal is 1.
    let cube = (2.0 / 3f64.sqrt()).powi(3);
    let expected = cube * (20.0f64 / 27.0).powi(4);
    assert!(
        (volume - expected).abs() < 1e-4 * expected,
        "{volume} vs {expected}"
    );
}

#[test]
fn procedural_small_variants_are_closed() {
    check_closed_mesh(&sphere(0, 3).build().unwrap());
    check_closed_mesh(&sphere(5, 99).build().unwrap());
    check_closed_mesh(
        &Procedural::DisplacedSphere {
            subdivisions: 4,
            amplitude: 0.0,
            frequency: 0.0,
            seed: 0,
        }
        .build()
        .unwrap(),
    );
    for (p, q, r) in [
        (2, 3, 0.4),
        (3, 2, 0.3),
        (3, 5, 0.2),
        (1, 1, 0.5),
        (5, 2, 0.15),
    ] {
        check_closed_mesh(&knot_with(p, q, r, 512, 16).build().unwrap());
    }
    check_closed_mesh(&knot_with(2, 3, 0.5, 24, 3).build().unwrap());
    check_closed_mesh(&knot_with(5, 2, 0.15, 40, 3).build().unwrap());
    for level in 0..=2 {
        check_closed_mesh(&Procedural::MengerSponge { level }.build().unwrap());
    }
}

#[test]
fn procedural_displaced_sphere_has_deep_folds() {
    let mesh = sphere(6, 1).build().unwrap();
    let radii: Vec<f32> = mesh.positions.iter().map(|p| p.length()).collect();
    let (lo, hi) = radii
        .iter()
        .fold((f32::MAX, 0.0f32), |(lo, hi), &r| (lo.min(r), hi.max(r)));
    // Creases reach 1 - amplitude, lobes up to 1 + amplitude (before scaling).
    assert!(lo / hi < 0.6, "radius range {lo}..{hi} is too shallow");
    // Many concave edges, not a few dents: count edges whose opposite
    // vertex lies outside the neighbouring triangle's plane.
    let mut opposite = HashMap::new();
    for &[a, b, c] in &mesh.triangles {
        for (x, y, z) in [(a, b, c), (b, c, a), (c, a, b)] {
            opposite.insert((x, y), z);
        }
    }
    let p = |i: u32| mesh.positions[i as usize];
    let mut concave = 0;
    for (&(x, y), &z) in &opposite {
        if x < y {
            let w = opposite[&(y, x)];
            let normal = (p(y) - p(x)).cross(p(z) - p(x));
            if normal.dot(p(w) - p(x)) > 0.0 {
                concave += 1;
            }
        }
    }
    let fraction = concave as f64 / (opposite.len() / 2) as f64;
    assert!(fraction > 0.2, "only {fraction} of the edges are concave");
}

#[test]
fn procedural_displacement_is_deterministic() {
    let a = sphere(5, 7).build().unwrap();
    let b = sphere(5, 7).build().unwrap();
    assert_eq!(a, b);
    let c = sphere(5, 8).build().unwrap();
    assert_eq!(a.triangles, c.triangles);
    assert_ne!(a.positions, c.positions);
}

#[test]
fn procedural_torus_knot_has_no_twist_seam() {
    let (segments, sides) = (400usize, 12usize);
    let mesh = knot_with(2, 3, 0.5, segments as u32, sides as u32)
        .build()
        .unwrap();
    // The edge from ring i to ring i + 1 along one vertex column: a seam
    // where the frame jumps would make the closing one much longer.
    let lengths: Vec<f32> = (0..segments)
        .map(|i| {
            let next = (i + 1) % segments;
            mesh.positions[i * sides].distance(mesh.positions[next * sides])
        })
        .collect();
    let mut sorted = lengths.clone();
    sorted.sort_by(f32::total_cmp);
    let median = sorted[segments / 2];
    let max = sorted[segments - 1];
    assert!(max < 2.5 * median, "max {max} vs median {median}");
    let seam = lengths[segments - 1];
    let before = lengths[segments - 2];
    assert!(
        (seam - before).abs() < 0.2 * before,
        "seam {seam} vs {before}"
    );
}

#[test]
fn procedural_invalid_parameters_are_errors() {
    let too_fine = sphere(10, 1).build();
    assert!(
        matches!(too_fine, Err(ProceduralError::TooManyTriangles { .. })),
        "{too_fine:?}"
    );
    assert!(sphere(u32::MAX, 1).build().is_err());
    for amplitude in [1.0, -0.1, f32::NAN] {
        let object = Procedural::DisplacedSphere {
            subdivisions: 2,
            amplitude,
            frequency: 1.0,
            seed: 0,
        };
        assert!(matches!(
            object.build(),
            Err(ProceduralError::InvalidParameter { .. })
        ));
    }
    for (p, q, r, segments, sides) in [
        (2, 3, 0.5, 0, 16),
        (2, 3, 0.5, 64, 0),
        (2, 3, 0.5, 2, 16),
        (2, 3, 0.5, 23, 16),
        (0, 3, 0.5, 64, 16),
        (2, 3, 0.0, 64, 16),
        (2, 3, f32::INFINITY, 64, 16),
        (2, 101, 0.1, 64, 16),
    ] {
        let result = knot_with(p, q, r, segments, sides).build();
        assert!(
            matches!(result, Err(ProceduralError::InvalidParameter { .. })),
            "{result:?}"
        );
    }
    assert!(matches!(
        knot_with(2, 4, 0.1, 64, 16).build(),
        Err(ProceduralError::NotAKnot { .. })
    ));
    assert!(matches!(
        knot_with(2, 3, 0.5, 100_000, 1000).build(),
        Err(ProceduralError::TooManyTriangles { .. })
    ));
    match knot_with(2, 3, 1.5, 64, 16).build() {
        Err(ProceduralError::TubeSelfIntersection { limit, .. }) => {
            assert!(limit > 0.5 && limit < 1.5, "limit {limit}");
            assert!(knot_with(2, 3, 0.98 * limit, 64, 16).build().is_ok());
            assert!(knot_with(2, 3, 1.02 * limit, 64, 16).build().is_err());
        }
        other => panic!("{other:?}"),
    }
    let deep = Procedural::MengerSponge { level: 5 }.build();
    assert!(
        matches!(deep, Err(ProceduralError::InvalidParameter { .. })),
        "{deep:?}"
    );
    assert!(deep.unwrap_err().to_string().contains("level = 5"));
}

#[test]
fn procedural_names() {
    assert_eq!(knot_with(2, 3, 0.5, 64, 8).name(), "torus-knot-2-3");
    assert_eq!(
        Procedural::MengerSponge { level: 3 }.name(),
        "menger-sponge-3"
    );
    assert_eq!(sphere(7, 42).name(), "displaced-sphere-7-seed-42");
}

fn parse_obj(text: &str) -> TriMesh {
    let mut mesh = TriMesh::default();
    for line in text.lines() {
        let mut words = line.split_whitespace();
        match words.next() {
            Some("v") => {
                let v: Vec<f32> = words.map(|w| w.parse().unwrap()).collect();
                assert_eq!(v.len(), 3, "{line}");
                mesh.positions.push(Vec3::new(v[0], v[1], v[2]));
            }
            Some("f") => {
                let f: Vec<u32> = words.map(|w| w.parse::<u32>().unwrap() - 1).collect();
                assert_eq!(f.len(), 3, "{line}");
                mesh.triangles.push([f[0], f[1], f[2]]);
            }
            Some(w) if w.starts_with('#') => {}
            None => {}
            Some(other) => panic!("unexpected OBJ line {other}"),
        }
    }
    mesh
}

#[test]
fn procedural_write_obj_round_trip() {
    let dir = std::env::temp_dir().join(format!("nppp-procedural-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    for object in [
        sphere(3, 5),
        knot_with(3, 5, 0.2, 96, 10),
        Procedural::MengerSponge { level: 1 },
    ] {
        let mesh = object.build().unwrap();
        let path = dir.join(format!("{}.obj", object.name()));
        write_obj(&mesh, &path, true).unwrap();
        assert_eq!(
            parse_obj(&std::fs::read_to_string(&path).unwrap()),
            mesh,
            "{}",
            object.name()
        );
        // The scene loader reads OBJ through tobj; it must agree too.
        let (models, _) = tobj::load_obj(&path, &tobj::LoadOptions::default()).unwrap();
        assert_eq!(models.len(), 1);
        assert_eq!(models[0].mesh.positions.len(), 3 * mesh.positions.len());
        assert_eq!(models[0].mesh.indices.len(), 3 * mesh.triangles.len());
    }
    // Only the finished files remain: no temporaries left behind.
    let names: Vec<String> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert!(
        names
            .iter()
            .all(|n| n.ends_with(".obj") && !n.starts_with('.')),
        "{names:?}"
    );
    assert!(
        write_obj(
            &TriMesh::default(),
            &dir.join("missing-dir").join("x.obj"),
            true
        )
        .is_err()
    );
    assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 3);
    // Not told to replace: a file at the path (one that appeared while the
    // mesh was written: two `nppp mesh` runs to one name) stays, and this
    // mesh is kept beside it.
    let hand = dir.join("hand.obj");
    std::fs::write(&hand, "# by hand\n").unwrap();
    let e = write_obj(&sphere(3, 5).build().unwrap(), &hand, false).unwrap_err();
    assert_eq!(e.kind(), std::io::ErrorKind::AlreadyExists);
    assert_eq!(std::fs::read_to_string(&hand).unwrap(), "# by hand\n");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Build times of the defaults, for the record: `cargo test -p nppp-scene
/// procedural_timings -- --ignored --nocapture`.
#[test]
#[ignore]
fn procedural_timings() {
    let extra = [Procedural::MengerSponge { level: 4 }];
    for object in Procedural::defaults().iter().chain(&extra) {
        let start = std::time::Instant::now();
        let mesh = object.build().unwrap();
        println!(
            "{}: {} triangles, {} vertices, {:.3} s",
            object.name(),
            mesh.triangles.len(),
            mesh.positions.len(),
            start.elapsed().as_secs_f64()
        );
    }
}
