//! Baking: grid nodes hold the encoder's output within the quantization
//! step, the file carries the model's identity, and the held-out comparison
//! of baked and unbaked estimators runs.

use std::fs;
use std::path::{Path, PathBuf};

use nppp_estimator::grid::node_coords;
use nppp_estimator::{BakedEstimator, DatasetWriter};
use nppp_geom::SpherePair;
use nppp_nn::eval::BurnEstimator;
use nppp_nn::synthetic::SyntheticObject;
use nppp_nn::{
    BackendKind, BakeOptions, TrainOptions, bake, load_model_dir, synthetic_header, train,
};

fn tmp(name: &str) -> PathBuf {
    let d = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(format!("nppp-nn-{name}"));
    let _ = fs::remove_dir_all(&d);
    fs::create_dir_all(&d).unwrap();
    d
}

/// A tiny trained model directory, trained from a real data file.
fn trained(dir: &Path) -> PathBuf {
    let data = dir.join("mirror.npppdata");
    let mut header = synthetic_header("mirror-ball", 8);
    header.mesh_hash = 0xDEAD_BEEF;
    header.material_hash = 42;
    header.max_internal_bounces = 16;
    let mut w = DatasetWriter::create(&data, header).unwrap();
    for r in (SyntheticObject::Mirror { radius: 0.6 }).rays(400, 8, 3) {
        w.write(&r).unwrap();
    }
    w.finish().unwrap();
    let model = dir.join("model");
    let mut o = TrainOptions::new(&data, &model);
    o.backend = BackendKind::Ndarray;
    o.quiet = true;
    o.batch = Some(16);
    o.k = Some(8);
    o.encoder_width = Some(32);
    o.decoder_width = Some(16);
    o.steps_per_epoch = Some(10);
    o.epochs = Some(1);
    o.minutes = 0.0;
    train(&o).unwrap();
    model
}

#[test]
fn baked_nodes_equal_the_encoder_within_the_quantization_step() {
    let dir = tmp("bake");
    let model = trained(&dir);
    let device = BackendKind::Ndarray.device().unwrap();
    let loaded = load_model_dir(&model, &device).unwrap();
    let est = BurnEstimator::new(
        &loaded.model,
        loaded.meta.transform.clone(),
        &loaded.meta.dataset,
        16,
    )
    .unwrap();
    let res = 4u32;
    let nodes: Vec<SpherePair> = (0..res.pow(4) as usize)
        .map(|i| SpherePair(node_coords(res, i)))
        .collect();
    let z = est.latents(&nodes).unwrap();
    for bits in [8u8, 4, 2] {
        let out = dir.join(format!("m{bits}.nppp"));
        let mut o = BakeOptions::new(&model, &out);
        o.backend = BackendKind::Ndarray;
        o.latent_grid = res;
        o.mask_grid = 3;
        o.bits = bits;
        o.quiet = true;
        o.eval_rays = 16;
        let rep = bake(&o).unwrap();
        assert!(rep.max_node_error_steps <= 0.5 + 1e-3, "{rep:?}");
        let b = BakedEstimator::load(&out).unwrap();
        assert_eq!(b.meta.mesh_name, "mirror-ball");
        assert_eq!(b.meta.mesh_hash, 0xDEAD_BEEF);
        assert_eq!(b.meta.material_hash, 42);
        assert_eq!(b.meta.max_internal_bounces, 16);
        assert_eq!(b.latent.bits, bits);
        assert_eq!(b.mask.res, 3);
        let c = b.latent.channels as usize;
        for (k, &x) in z.iter().enumerate() {
            let step = b.latent.scale[k % c];
            let got = b.latent.node_value(k / c, k % c);
            assert!(
                (got - x).abs() <= 0.5 * step + 1e-5 * x.abs().max(1.0),
                "node {} ch {}: {got} vs {x} (step {step})",
                k / c,
                k % c
            );
        }
        // The decoder in the file is the trained one, exactly.
        assert_eq!(b.decoder, loaded.model.export_decoder().unwrap());
        let (u, m) = (rep.unbaked.unwrap(), rep.baked.unwrap());
        assert!(u.hit_rays > 0 && m.hit_rays == u.hit_rays);
        assert!(m.chamfer.is_finite() && m.mask_accuracy > 0.0);
    }
}

#[test]
fn bake_errors_are_clear() {
    let dir = tmp("bake-errors");
    let mut o = BakeOptions::new(dir.join("missing"), dir.join("x.nppp"));
    o.backend = BackendKind::Ndarray;
    o.quiet = true;
    let err = bake(&o).unwrap_err();
    assert!(err.to_string().contains("does not exist"), "{err}");
    let model = trained(&dir);
    let mut o = BakeOptions::new(&model, dir.join("x.nppp"));
    o.backend = BackendKind::Ndarray;
    o.quiet = true;
    o.latent_grid = 1;
    let err = bake(&o).unwrap_err();
    assert!(err.to_string().contains("resolution"), "{err}");
    o.latent_grid = 200;
    let err = bake(&o).unwrap_err();
    assert!(err.to_string().contains("GiB"), "{err}");

    // Scoring data whose held-out rays are not the model's: the same
    // object with another k (it failed later naming no file), other rays,
    // or a shard of the training data (whose rays are numbered from its
    // own first: bake scored the model on rays it had trained on).
    o.latent_grid = 8;
    let write = |name: &str, k: usize, n: usize, shard: bool| {
        let path = dir.join(name);
        let mut header = synthetic_header("mirror-ball", k);
        header.mesh_hash = 0xDEAD_BEEF;
        header.material_hash = 42;
        header.max_internal_bounces = 16;
        if shard {
            header.shard = Some(nppp_estimator::shard::DatasetShard {
                first_ray: 0,
                end_ray: n as u64,
                rays: 2 * n as u64,
                chunk_rays: nppp_estimator::WriterOptions::default().chunk_rays,
                compress: true,
            });
        }
        let mut w = DatasetWriter::create(&path, header).unwrap();
        for r in (SyntheticObject::Mirror { radius: 0.6 }).rays(n, k, 3) {
            w.write(&r).unwrap();
        }
        w.finish().unwrap();
        path
    };
    for (data, needle) in [
        (
            write("k4.nppd", 4, 400, false),
            "k = 4; the model was trained on",
        ),
        (write("more.nppd", 8, 500, false), "holds 500 rays"),
        (
            write("shard.nppd", 8, 200, true),
            "is a shard (rays 0..200 of 400)",
        ),
    ] {
        o.data = Some(data.clone());
        let err = format!("{:#}", bake(&o).unwrap_err());
        assert!(
            err.contains(needle) && err.contains(&data.display().to_string()),
            "{err}"
        );
    }
    assert!(!dir.join("x.nppp").exists());
}

/// The vertex head (issue 18): it trains when the data has picked vertices,
/// is scored on the held-out rays, learns (on a convex ball the picked
/// vertex is the first hit, a function of the ray), and is baked into the
/// file with scores close to the model's.
#[test]
fn the_vertex_head_learns_the_first_hit_and_is_baked() {
    use nppp_nn::synthetic::first_hit_vertex;
    let dir = tmp("vertex-head");
    let (radius, k) = (0.6, 8);
    let data = dir.join("ball.nppd");
    let mut header = synthetic_header("ball", k);
    header.vertices = true;
    let mut w = DatasetWriter::create(&data, header).unwrap();
    for mut r in (SyntheticObject::AbsorbingDiffuse { radius }).rays(1500, k, 3) {
        if r.hit {
            r.vertices = vec![first_hit_vertex(&r.pair, radius).unwrap(); k];
        }
        w.write(&r).unwrap();
    }
    w.finish().unwrap();
    let train_for = |epochs: usize, name: &str| -> (PathBuf, nppp_nn::eval::VertexMetrics) {
        let model = dir.join(name);
        let mut o = TrainOptions::new(&data, &model);
        o.backend = BackendKind::Ndarray;
        o.quiet = true;
        o.batch = Some(16);
        o.k = Some(8);
        o.encoder_width = Some(64);
        o.decoder_width = Some(32);
        o.eval_rays = Some(64);
        o.steps_per_epoch = Some(25);
        o.epochs = Some(epochs);
        o.minutes = 0.0;
        let rep = train(&o).unwrap();
        (
            model,
            rep.metrics
                .unwrap()
                .vertex
                .expect("the vertex head is scored"),
        )
    };
    let (m1, first) = train_for(1, "m1");
    // Resuming that run on data without vertices is refused, naming why.
    let plain = dir.join("plain.nppd");
    let mut w = DatasetWriter::create(&plain, synthetic_header("ball", k)).unwrap();
    for r in (SyntheticObject::AbsorbingDiffuse { radius }).rays(1500, k, 3) {
        w.write(&r).unwrap();
    }
    w.finish().unwrap();
    let mut o = TrainOptions::new(&plain, &m1);
    o.backend = BackendKind::Ndarray;
    o.quiet = true;
    o.resume = true;
    o.epochs = Some(2);
    o.minutes = 0.0;
    let e = format!("{:#}", train(&o).unwrap_err());
    assert!(
        e.contains("trained with a vertex head") && e.contains("has no picked vertices"),
        "{e}"
    );
    let (model, last) = train_for(12, "m12");
    assert!(
        last.chamfer < first.chamfer / 3.0,
        "vertex chamfer {first:?} -> {last:?}"
    );
    assert!(
        last.position_error < first.position_error,
        "{first:?} -> {last:?}"
    );
    let config = fs::read_to_string(model.join("checkpoint/train_config.json")).unwrap();
    assert!(config.contains("\"vertex_head\": true"), "{config}");
    let out = dir.join("ball.nppp");
    let mut o = BakeOptions::new(&model, &out);
    o.backend = BackendKind::Ndarray;
    o.latent_grid = 8;
    o.mask_grid = 4;
    o.quiet = true;
    o.eval_rays = 64;
    let rep = bake(&o).unwrap();
    let (u, b) = (
        rep.unbaked.unwrap().vertex.unwrap(),
        rep.baked.unwrap().vertex.unwrap(),
    );
    assert!(
        b.chamfer < 1.5 * u.chamfer + 0.2,
        "baked vertex head {b:?}, unbaked {u:?}"
    );
    let est = BakedEstimator::load(&out).unwrap();
    let head = est.vertex.expect("the file has the vertex head");
    assert_eq!(
        head.decoder,
        load_model_dir(&model, &BackendKind::Ndarray.device().unwrap())
            .unwrap()
            .model
            .export_vertex_decoder()
            .unwrap()
            .unwrap()
    );
}
