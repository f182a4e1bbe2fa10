use super::*;
use nppp_geom::SampleRng;

#[test]
fn the_recorded_material_tells_the_exits_bounds() {
    let mut h = header(4);
    assert!(!h.has_medium());
    assert_eq!(h.exit_bounds(), crate::ExitBounds::SURFACE);
    h.material_json = r#"{"type": "translucent", "ior": 1.6, "sigma_s": [9, 9, 9], "sigma_a": [0, 0, 0], "g": 0}"#.into();
    assert!(h.has_medium());
    assert_eq!(h.exit_bounds(), crate::ExitBounds { throughput: crate::EXIT_THROUGHPUT_BOUND_MEDIUM, radiance: 0.0 });
    h.material_json = r#"{"type": "emitter", "radiance": [17, 12, 4]}"#.into();
    assert_eq!(h.exit_bounds(), crate::ExitBounds::new(false, 17.0));
    h.material_json = "{}".into();
    assert!(!h.has_medium());
    assert_eq!(h.exit_bounds(), crate::ExitBounds::SURFACE);
}

fn header(k: u32) -> DatasetHeader {
    DatasetHeader {
        mesh_name: "bunny.obj".into(),
        mesh_hash: 42,
        material_name: "white".into(),
        material_hash: 7,
        material_json: r#"{"type":"diffuse","albedo":[0.8,0.6,0.4]}"#.into(),
        sphere: BoundingSphere { center: Vec3::new(0.1, 0.2, -0.3), radius: 1.2345678 },
        k,
        seed: 1234,
        max_internal_bounces: 64,
        shard: None,
        vertices: false,
    }
}

fn unit(rng: &mut SampleRng) -> Vec3 {
    nppp_geom::sampling::uniform_sphere(rng.uniform2())
}

/// Exits shaped like a diffuse object's: albedo^bounces throughput, some
/// absorbed, zero radiance except now and then.
pub(crate) fn synthetic_record(rng: &mut SampleRng, k: u32, hit_rate: f32) -> RayRecord {
    let pair = SpherePair([rng.uniform(), rng.uniform(), rng.uniform(), rng.uniform()]);
    if rng.uniform() >= hit_rate {
        return RayRecord { pair, hit: false, exits: vec![], vertices: vec![] };
    }
    let exits = (0..k)
        .map(|_| {
            let position = unit(rng);
            let mut direction = unit(rng);
            if direction.dot(position) < 0.0 {
                direction = -direction;
            }
            let mut b = 1u32;
            while rng.uniform() < 0.5 && b < 64 {
                b += 1;
            }
            let absorbed = rng.uniform() < 0.1;
            let throughput =
                if absorbed { Vec3::ZERO } else { Vec3::new(0.8f32.powi(b as i32), 0.6f32.powi(b as i32), 0.4f32.powi(b as i32)) };
            let radiance = if rng.uniform() < 0.02 { Vec3::splat(rng.uniform() * 5.0) } else { Vec3::ZERO };
            Exit { position, direction, throughput, radiance, bounces: b }
        })
        .collect();
    RayRecord { pair, hit: true, exits, vertices: vec![] }
}

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("nppp-data-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d.join("d.nppd")
}

fn color_close(a: Vec3, b: Vec3) -> bool {
    // Half precision: 2^-11 relative, 2^-25 absolute below the normals.
    (a - b).abs().cmple(a.abs() * (1.0 / 2048.0) + Vec3::splat(3.0e-8)).all()
}

/// Angle between directions, accurate near 0 (unlike acos of a dot).
fn angle(a: Vec3, b: Vec3) -> f32 {
    2.0 * (0.5 * (a.normalize() - b.normalize()).length()).asin()
}

fn assert_close(a: &RayRecord, b: &RayRecord) {
    assert_eq!(a.pair, b.pair);
    assert_eq!(a.hit, b.hit);
    assert_eq!(a.exits.len(), b.exits.len());
    for (x, y) in a.exits.iter().zip(&b.exits) {
        assert!(angle(x.position, y.position) <= OCT_MAX_ANGLE, "{x:?} {y:?}");
        assert!(angle(x.direction, y.direction) <= OCT_MAX_ANGLE);
        assert!(color_close(x.throughput, y.throughput), "{x:?} {y:?}");
        assert!(color_close(x.radiance, y.radiance));
        assert_eq!(x.bounces.min(64), y.bounces);
    }
}

/// The encoder before it used the `half` crate: files written today
/// carry the same bits.
fn f32_to_f16_by_hand(x: f32) -> u16 {
    if x.is_nan() || x <= 0.0 {
        return 0;
    }
    if x >= 65504.0 {
        return 0x7bff;
    }
    if x < 6.103_515_6e-5 {
        return (x * 16_777_216.0).round_ties_even() as u16;
    }
    let a = x.to_bits();
    let mant = a & 0x7f_ffff;
    let exp = (a >> 23) + 15 - 127;
    let mut h = (exp << 10) | (mant >> 13);
    let rem = mant & 0x1fff;
    if rem > 0x1000 || (rem == 0x1000 && h & 1 == 1) {
        h += 1;
    }
    h as u16
}

#[test]
fn f16_encoding_is_unchanged_by_the_half_crate() {
    // Every 61st f32 bit pattern, both signs, and every half's
    // neighbourhood (where rounding ties live).
    for bits in (0..=u32::MAX).step_by(61) {
        let x = f32::from_bits(bits);
        assert_eq!(f32_to_f16(x), f32_to_f16_by_hand(x), "{x:e} ({bits:#x})");
    }
    for h in 0..0x7c00u32 {
        let base = ((h + 112) << 23) | 0x1000;
        for bits in [base.wrapping_sub(1), base, base + 1, base + 0x2000] {
            let x = f32::from_bits(bits);
            assert_eq!(f32_to_f16(x), f32_to_f16_by_hand(x), "{x:e}");
        }
    }
}

#[test]
fn f16_round_trips() {
    for h in 0u16..0x7c00 {
        assert_eq!(f32_to_f16(f16_to_f32(h)), h, "{h:#x}");
    }
    assert_eq!(f32_to_f16(1e9), 0x7bff);
    assert_eq!(f32_to_f16(-1.0), 0);
    assert_eq!(f32_to_f16(f32::NAN), 0);
    assert_eq!(f32_to_f16(1.0), 0x3c00);
    // Ties to even, and rounding that carries into the exponent.
    assert_eq!(f32_to_f16(1.0 + 1.0 / 2048.0), 0x3c00);
    assert_eq!(f32_to_f16(1.0 + 3.0 / 2048.0), 0x3c02);
    assert_eq!(f32_to_f16(2.0 - 1.0 / 4096.0), 0x4000);
    let mut rng = SampleRng::from_seed(3);
    for _ in 0..100_000 {
        let x = (rng.uniform() * 30.0 - 20.0).exp2();
        assert!(color_close(Vec3::splat(x), Vec3::splat(f16_to_f32(f32_to_f16(x)))), "{x}");
    }
}

#[test]
fn octahedral_error_is_bounded() {
    let mut rng = SampleRng::from_seed(9);
    let mut worst = 0.0f32;
    let mut sum = 0.0f64;
    let mut axes = vec![Vec3::X, Vec3::Y, Vec3::Z, -Vec3::X, -Vec3::Y, -Vec3::Z, Vec3::ONE.normalize(), -Vec3::ONE.normalize()];
    axes.extend((0..200_000).map(|_| unit(&mut rng)));
    for v in axes {
        let back = oct_decode(oct_encode(v));
        let a = angle(back, v);
        worst = worst.max(a);
        sum += a as f64;
    }
    eprintln!("octahedral 2x16 bit: worst angle {worst:e} rad, mean {:e} rad", sum / 200_008.0);
    assert!(worst <= OCT_MAX_ANGLE, "{worst}");
}

#[test]
fn round_trip_within_tolerance_and_chunked() {
    let path = tmp("rt");
    let mut rng = SampleRng::from_seed(1);
    let k = 16;
    let mut recs: Vec<RayRecord> = (0..300).map(|_| synthetic_record(&mut rng, k, 0.4)).collect();
    // Edge cases: huge and tiny colours, bounces over the cap, an unnormalized position.
    recs[0] = synthetic_record(&mut rng, k, 1.0);
    recs[0].exits[0].throughput = Vec3::new(1e-7, 7e4, 0.0);
    recs[0].exits[1].bounces = 1000;
    recs[0].exits[2].position *= 3.0;
    let opts = WriterOptions { chunk_rays: 64, compress: true, replace: true };
    let mut w = DatasetWriter::create_with(&path, header(k), opts).unwrap();
    for r in &recs {
        w.write(r).unwrap();
    }
    // Nothing at the final path before finish.
    assert!(!path.exists());
    let summary = w.finish().unwrap();
    assert_eq!(summary.rays, 300);
    assert_eq!(summary.chunks, 5);
    assert_eq!(summary.file_bytes, std::fs::metadata(&path).unwrap().len());

    let mut r = DatasetReader::open(&path).unwrap();
    assert_eq!(r.header(), &header(k));
    assert_eq!(r.len(), 300);
    assert_eq!(r.chunk_count(), 5);
    assert_eq!(r.hit_count(), summary.hits);
    let mut seen = 0;
    while let Some(chunk) = r.next_chunk() {
        let chunk = chunk.unwrap();
        assert!(chunk.len() <= 64);
        for rec in &chunk {
            let want = &recs[seen];
            if seen == 0 {
                let t = rec.exits[0].throughput;
                assert!(t.x > 0.0 && (t.x - 1e-7).abs() < 3e-8 && t.y == 65504.0 && t.z == 0.0, "{t}");
                assert_eq!(rec.exits[1].bounces, 64);
            } else {
                assert_close(want, rec);
            }
            seen += 1;
        }
    }
    assert_eq!(seen, 300);
    let all = r.read_all().unwrap();
    assert_eq!(all.len(), 300);
    assert_eq!(all[299], r.read_chunk(4).unwrap()[299 - 256]);
    // Raw and compressed files decode to the same records.
    let path2 = tmp("rt-raw");
    let mut w = DatasetWriter::create_with(&path2, header(k), WriterOptions { chunk_rays: 100, compress: false, replace: true }).unwrap();
    recs.iter().for_each(|rec| w.write(rec).unwrap());
    let s2 = w.finish().unwrap();
    assert!(s2.file_bytes > summary.file_bytes);
    assert_eq!(DatasetReader::open(&path2).unwrap().read_all().unwrap(), all);
    let _ = std::fs::remove_dir_all(path.parent().unwrap());
    let _ = std::fs::remove_dir_all(path2.parent().unwrap());
}

#[test]
fn empty_and_invalid_records() {
    let path = tmp("empty");
    let w = DatasetWriter::create(&path, header(4)).unwrap();
    assert!(w.is_empty());
    w.finish().unwrap();
    let mut r = DatasetReader::open(&path).unwrap();
    assert!(r.is_empty() && r.next_chunk().is_none());

    let mut w = DatasetWriter::create(&path, header(4)).unwrap();
    let mut rng = SampleRng::from_seed(2);
    let mut rec = synthetic_record(&mut rng, 4, 1.0);
    rec.exits.pop();
    assert!(w.write(&rec).unwrap_err().to_string().contains("ray 0: 3 exits for a hit (k = 4)"));
    let mut rec = synthetic_record(&mut rng, 4, 1.0);
    rec.exits[2].throughput.y = f32::NAN;
    assert!(w.write(&rec).unwrap_err().to_string().contains("exit 2: throughput"));
    rec.exits[2].throughput.y = -0.5;
    assert!(w.write(&rec).is_err());
    let rec = RayRecord { pair: SpherePair([0.1; 4]), hit: false, exits: vec![Exit::default()], vertices: vec![] };
    assert!(w.write(&rec).is_err());
    // Dropping an unfinished writer leaves the old file alone and no temp file.
    drop(w);
    assert!(DatasetReader::open(&path).unwrap().is_empty());
    assert_eq!(std::fs::read_dir(path.parent().unwrap()).unwrap().count(), 1);
    let mut h = header(0);
    assert!(DatasetWriter::create(&path, h.clone()).is_err());
    h.k = 2;
    h.sphere.radius = 0.0;
    assert!(DatasetWriter::create(&path, h).is_err());
    let _ = std::fs::remove_dir_all(path.parent().unwrap());
}

fn small_file(compress: bool) -> (PathBuf, Vec<u8>) {
    let path = tmp(if compress { "corrupt-z" } else { "corrupt" });
    let mut rng = SampleRng::from_seed(5);
    let mut w = DatasetWriter::create_with(&path, header(4), WriterOptions { chunk_rays: 8, compress, replace: true }).unwrap();
    for _ in 0..30 {
        w.write(&synthetic_record(&mut rng, 4, 0.5)).unwrap();
    }
    w.finish().unwrap();
    let bytes = std::fs::read(&path).unwrap();
    (path, bytes)
}

/// Opens and reads everything; the first error as text.
fn first_error(path: &Path) -> Option<String> {
    match DatasetReader::open(path) {
        Err(e) => Some(e.to_string()),
        Ok(mut r) => r.read_all().err().map(|e| e.to_string()),
    }
}

/// The same from memory (rewriting a file thousands of times is slow).
fn first_error_mem(bytes: &[u8], path: &Path) -> Option<String> {
    match DatasetReader::from_bytes(bytes.to_vec(), path) {
        Err(e) => Some(e.to_string()),
        Ok(mut r) => r.read_all().err().map(|e| e.to_string()),
    }
}

#[test]
fn corruption_is_detected_everywhere() {
    for compress in [false, true] {
        let (path, good) = small_file(compress);
        assert_eq!(first_error(&path), None);
        let name = path.display().to_string();
        for i in 0..good.len() {
            let mut b = good.clone();
            b[i] ^= 0x04;
            let e = first_error_mem(&b, &path).unwrap_or_else(|| panic!("flipped byte {i} not detected"));
            assert!(e.starts_with(&name), "{e}");
        }
        for n in (0..good.len()).chain([good.len() - 1, good.len() - 40, 15, 16]) {
            assert!(first_error_mem(&good[..n], &path).is_some(), "truncated at {n} accepted");
        }
        // A damaged chunk is named, and reported once.
        let mut b = good.clone();
        let hlen = le_u32(&good, 12) as usize;
        let second_chunk_payload = {
            let first = 16 + hlen + 4;
            let stored = le_u32(&good, first + 16) as usize;
            first + CHUNK_HEADER_LEN + stored + CHUNK_HEADER_LEN + 3
        };
        b[second_chunk_payload] ^= 0xff;
        std::fs::write(&path, &b).unwrap();
        let mut r = DatasetReader::open(&path).unwrap();
        assert!(r.next_chunk().unwrap().is_ok());
        let e = r.next_chunk().unwrap().unwrap_err().to_string();
        assert!(e.contains("chunk 1 (at byte") && e.contains("checksum mismatch"), "{e}");
        assert!(r.next_chunk().is_none());
        // Random access still reaches the good chunks.
        assert!(r.read_chunk(2).is_ok());

        let mut b = good.clone();
        b[8] = 9;
        std::fs::write(&path, &b).unwrap();
        assert!(first_error(&path).unwrap().contains("version 9 not supported (this build reads 1 to 2"));
        let mut b = good.clone();
        b[0] = b'X';
        std::fs::write(&path, &b).unwrap();
        assert!(first_error(&path).unwrap().contains("wrong magic"));
        std::fs::write(&path, &good[..good.len() - 10]).unwrap();
        assert!(first_error(&path).unwrap().contains("no chunk index"));
        let _ = std::fs::remove_dir_all(path.parent().unwrap());
    }
}

#[test]
fn absurd_index_values_do_not_allocate() {
    let (path, good) = small_file(true);
    let n = good.len();
    // Trailer with a huge chunk count, checksum recomputed over what it covers.
    let edit = |at: usize, v: u64| {
        let mut b = good.clone();
        b[n - TRAILER_LEN + at..n - TRAILER_LEN + at + 8].copy_from_slice(&v.to_le_bytes());
        std::fs::write(&path, &b).unwrap();
        first_error(&path).unwrap()
    };
    assert!(edit(8, u64::MAX / 2).contains("does not fit"));
    assert!(edit(0, u64::MAX).contains("does not fit"));
    assert!(edit(16, 1 << 40).contains("checksum"));
    // A chunk that claims a huge uncompressed size, with a valid chunk CRC.
    let hlen = le_u32(&good, 12) as usize;
    let first = 16 + hlen + 4;
    let mut b = good.clone();
    b[first + 20..first + 24].copy_from_slice(&u32::MAX.to_le_bytes());
    let mut h = crc32fast::Hasher::new();
    h.update(&b[first + 4..first + 24]);
    let stored = le_u32(&b, first + 16) as usize;
    h.update(&b[first + CHUNK_HEADER_LEN..first + CHUNK_HEADER_LEN + stored]);
    b[first + 24..first + 28].copy_from_slice(&h.finalize().to_le_bytes());
    std::fs::write(&path, &b).unwrap();
    assert!(first_error(&path).unwrap().contains("uncompressed bytes (limit"));
    let _ = std::fs::remove_dir_all(path.parent().unwrap());
}

/// A picked vertex per exit, shaped like a diffuse walk's.
fn synthetic_vertex(rng: &mut SampleRng) -> PickedVertex {
    PickedVertex {
        position: unit(rng) * (0.2 + 0.6 * rng.uniform()),
        normal: unit(rng),
        wo: unit(rng),
        beta: Vec3::new(rng.uniform(), rng.uniform(), rng.uniform()) * 3.0,
        index: (rng.uniform() * 5.0) as u32,
    }
}

#[test]
fn picked_vertices_round_trip_and_are_checked() {
    let path = tmp("vertices");
    let mut h = header(8);
    h.vertices = true;
    let mut rng = SampleRng::from_seed(11);
    let recs: Vec<RayRecord> = (0..100)
        .map(|_| {
            let mut r = synthetic_record(&mut rng, 8, 0.5);
            r.vertices = r.exits.iter().map(|_| synthetic_vertex(&mut rng)).collect();
            r
        })
        .collect();
    let mut w = DatasetWriter::create_with(&path, h.clone(), WriterOptions { chunk_rays: 32, compress: true, replace: true }).unwrap();
    recs.iter().for_each(|r| w.write(r).unwrap());
    // A hit without its vertices, or vertices in data that has none, is refused.
    let mut bad = synthetic_record(&mut rng, 8, 1.0);
    assert!(w.write(&bad).unwrap_err().to_string().contains("0 picked vertices for 8 exits"), "vertices missing");
    bad.vertices = bad.exits.iter().map(|_| synthetic_vertex(&mut rng)).collect();
    bad.vertices[3].normal = Vec3::ZERO;
    assert!(w.write(&bad).unwrap_err().to_string().contains("vertex 3: normal"));
    bad.vertices[3].normal = Vec3::Z;
    bad.vertices[5].beta.y = -1.0;
    assert!(w.write(&bad).unwrap_err().to_string().contains("vertex 5: throughput"));
    w.finish().unwrap();
    let got = DatasetReader::open(&path).unwrap().read_all().unwrap();
    assert_eq!(got.len(), recs.len());
    for (a, b) in recs.iter().zip(&got) {
        assert_close(a, b);
        assert_eq!(a.vertices.len(), b.vertices.len());
        for (x, y) in a.vertices.iter().zip(&b.vertices) {
            // Positions in f16: 2^-11 relative.
            assert!((x.position - y.position).abs().max_element() <= 1e-3, "{x:?} {y:?}");
            assert!(angle(x.normal, y.normal) <= OCT_MAX_ANGLE && angle(x.wo, y.wo) <= OCT_MAX_ANGLE);
            assert!(color_close(x.beta, y.beta));
            assert_eq!(x.index, y.index);
        }
    }
    // Data without vertices refuses records that carry them.
    let path2 = tmp("no-vertices");
    let mut w = DatasetWriter::create(&path2, header(8)).unwrap();
    assert!(w.write(&recs.iter().find(|r| r.hit).unwrap().clone()).unwrap_err().to_string().contains("has no vertices"));
    let _ = std::fs::remove_dir_all(path.parent().unwrap());
    let _ = std::fs::remove_dir_all(path2.parent().unwrap());
}

/// A file whose checksums are right but whose records break the writer's
/// rules (forged, or written by a broken tool) is refused when read,
/// naming the chunk and the ray: a NaN vertex or an infinite vertex
/// throughput reached training, which "diverged" (and told the user to
/// lower --lr).
#[test]
fn records_are_checked_when_read_too() {
    let mut h = header(8);
    h.vertices = true;
    let mut rng = SampleRng::from_seed(12);
    let mut good = synthetic_record(&mut rng, 8, 1.0);
    good.vertices = good.exits.iter().map(|_| synthetic_vertex(&mut rng)).collect();
    // The first vertex of a chunk's vertex column: its position's x in f16
    // at byte 0, its throughput's x at byte 14 (after the position and the
    // two octahedral directions). The encoder clamps what it writes, so
    // the bad values go in as bytes, as a forger would put them.
    let forge = |name: &str, at: usize, f16_bits: u16| {
        let path = tmp(name);
        let mut w = DatasetWriter::create_with(&path, h.clone(), WriterOptions { chunk_rays: 32, compress: false, replace: true }).unwrap();
        w.cols.push(&good, w.header.max_internal_bounces, w.bounce_width);
        w.cols.vertices[at..at + 2].copy_from_slice(&f16_bits.to_le_bytes());
        w.rays += 1;
        w.hits += 1;
        w.finish().unwrap();
        let e = DatasetReader::open(&path).unwrap().read_all().unwrap_err().to_string();
        let _ = std::fs::remove_dir_all(path.parent().unwrap());
        e
    };
    let e = forge("read-nan-vertex", 0, 0x7E00);
    assert!(e.contains("ray 0 of the chunk: vertex 0: position"), "{e}");
    let e = forge("read-inf-beta", 14, 0x7C00);
    assert!(e.contains("ray 0 of the chunk: vertex 0: throughput"), "{e}");
    let e = forge("read-negative-beta", 14, 0xBC00);
    assert!(e.contains("ray 0 of the chunk: vertex 0: throughput"), "{e}");
}

/// Rewrites a file's version field (and the header checksum that covers it).
fn with_version(bytes: &[u8], version: u32) -> Vec<u8> {
    let mut b = bytes.to_vec();
    b[8..12].copy_from_slice(&version.to_le_bytes());
    let hlen = u32::from_le_bytes([b[12], b[13], b[14], b[15]]) as usize;
    let crc = crc32fast::hash(&b[8..16 + hlen]);
    b[16 + hlen..20 + hlen].copy_from_slice(&crc.to_le_bytes());
    b
}

#[test]
fn version_1_files_are_read_and_others_named() {
    let (path, bytes) = small_file(true);
    let now = DatasetReader::from_bytes(bytes.clone(), &path).unwrap().read_all().unwrap();
    // A version 1 file (no vertices) reads as it always did.
    let v1 = with_version(&bytes, 1);
    assert_eq!(DatasetReader::from_bytes(v1, &path).unwrap().read_all().unwrap(), now);
    let e = first_error_mem(&with_version(&bytes, 3), &path).unwrap();
    assert!(e.contains("version 3 not supported (this build reads 1 to 2; `nppp gen` rebuilds the data)"), "{e}");
    let _ = std::fs::remove_dir_all(path.parent().unwrap());
}
