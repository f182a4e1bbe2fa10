//! The training side never destroys a user's file (gen, train, bake and the
//! estimator side of render), through the real binary: outputs that name an
//! input are refused before any work; a model directory survives a kill at
//! every step of a checkpoint write (`NPPP_CRASH_AT`, nppp-files' crash
//! points: the process aborts there, as a kill would leave it) and an
//! interrupted `--overwrite`; damaged checkpoints are refused by checksum;
//! flags and data files that claim absurd memory get a message, not an
//! abort on allocation. docs/robustness.md ("Training side") lists the cases.

use nppp_estimator::{DatasetHeader, DatasetWriter, Exit, RayRecord, WriterOptions};
use nppp_geom::{BoundingSphere, SpherePair, Vec3};
use std::ffi::OsStr;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

mod common;
use common::{SMALL_TRAIN_FLAGS, nppp, nppp_env, stderr};

fn scratch(name: &str) -> common::Scratch {
    common::scratch("train-files", name)
}

/// `kill -SIGNAL` to a spawned `nppp` (INT or TERM), as a user's Ctrl-C or
/// a job scheduler would.
fn send_signal(signal: &str, child: &std::process::Child) {
    let killed = Command::new("kill")
        .args([format!("-{signal}"), child.id().to_string()])
        .status()
        .unwrap();
    assert!(killed.success(), "kill -{signal} failed");
}

fn assert_ok(what: &str, o: &Output) {
    assert!(o.status.success(), "{what} failed:\n{}", stderr(o));
}

/// Exit status 1, no panic, every needle on stderr.
fn assert_error(what: &str, o: &Output, needles: &[&str]) {
    let err = stderr(o);
    assert!(!err.contains("panicked"), "{what}: panicked:\n{err}");
    assert_eq!(
        o.status.code(),
        Some(1),
        "{what}: status {:?}:\n{err}",
        o.status
    );
    for n in needles {
        assert!(err.contains(n), "{what}: stderr lacks {n:?}:\n{err}");
    }
}

/// A small valid data file: `rays` rays of a unit sphere, half of them hits
/// with `k` exits each (the exits vary, so it compresses like real data).
fn write_data(path: &Path, rays: u32, k: u32) {
    let header = DatasetHeader {
        mesh_name: "ball".into(),
        mesh_hash: 1,
        material_name: "white".into(),
        material_hash: 2,
        material_json: r#"{"type": "diffuse", "albedo": [0.7, 0.7, 0.7]}"#.into(),
        sphere: BoundingSphere {
            center: Vec3::ZERO,
            radius: 1.0,
        },
        k,
        seed: 0,
        max_internal_bounces: 8,
        shard: None,
        vertices: false,
    };
    let mut wr = DatasetWriter::create_with(path, header, WriterOptions::default()).unwrap();
    for i in 0..rays {
        let f = (i as f32 + 0.5) / rays as f32;
        let hit = i % 2 == 0;
        let exits = if hit {
            (0..k)
                .map(|j| {
                    let a = f * 6.0 + j as f32 * 0.37;
                    Exit {
                        position: Vec3::new(a.cos(), a.sin(), 0.3).normalize(),
                        direction: Vec3::new(a.sin(), 0.2, a.cos()).normalize(),
                        throughput: Vec3::splat(0.2 + 0.5 * f),
                        radiance: Vec3::ZERO,
                        bounces: 1 + j % 3,
                    }
                })
                .collect()
        } else {
            vec![]
        };
        wr.write(&RayRecord {
            pair: SpherePair([f, (f * 7.0) % 1.0, 1.0 - f, (f * 3.0) % 1.0]),
            hit,
            exits,
            vertices: vec![],
        })
        .unwrap();
    }
    wr.finish().unwrap();
}

/// Flags of a seconds-long training run (NdArray, tiny widths, 25-step epochs).
fn small_train<'a>(data: &'a Path, out: &'a Path, epochs: &'a str) -> Vec<&'a OsStr> {
    let mut v: Vec<&OsStr> = vec!["train".as_ref(), "--data".as_ref(), data.as_os_str()];
    v.extend(SMALL_TRAIN_FLAGS.iter().map(OsStr::new));
    v.push("--epochs".as_ref());
    v.push(epochs.as_ref());
    v.push("--out".as_ref());
    v.push(out.as_os_str());
    v
}

/// Sets `flag` to `value` in `args` (clap refuses a repeated flag).
fn set_flag<'a>(args: &mut Vec<&'a OsStr>, flag: &'a str, value: &'a str) {
    match args.iter().position(|a| *a == OsStr::new(flag)) {
        Some(i) => args[i + 1] = OsStr::new(value),
        None => args.extend([OsStr::new(flag), OsStr::new(value)]),
    }
}

/// Data and a model trained for one epoch (one checkpoint) in `dir`.
fn trained(dir: &Path) -> (PathBuf, PathBuf) {
    let data = dir.join("data.nppd");
    write_data(&data, 400, 4);
    let model = dir.join("model");
    assert_ok("train", &nppp(small_train(&data, &model, "1")));
    (data, model)
}

fn bake_args<'a>(model: &'a Path, out: &'a Path, extra: &'a [&'a str]) -> Vec<&'a OsStr> {
    let mut v: Vec<&OsStr> = vec![
        "bake".as_ref(),
        "--model".as_ref(),
        model.as_os_str(),
        "--out".as_ref(),
        out.as_os_str(),
    ];
    v.extend(
        [
            "--latent-grid",
            "4",
            "--mask-grid",
            "4",
            "--backend",
            "ndarray",
            "--quiet",
            "--eval-rays",
            "16",
        ]
        .iter()
        .map(OsStr::new),
    );
    v.extend(extra.iter().map(OsStr::new));
    v
}

/// Every file under `dir` (relative name, bytes), sorted.
fn snapshot(dir: &Path) -> Vec<(String, Vec<u8>)> {
    fn walk(base: &Path, d: &Path, out: &mut Vec<(String, Vec<u8>)>) {
        for e in std::fs::read_dir(d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                walk(base, &p, out);
            } else {
                let rel = p.strip_prefix(base).unwrap().to_string_lossy().into_owned();
                out.push((rel, std::fs::read(&p).unwrap()));
            }
        }
    }
    let mut v = Vec::new();
    walk(dir, dir, &mut v);
    v.sort();
    v
}

fn state_step(model: &Path) -> u64 {
    let s = std::fs::read_to_string(model.join("checkpoint/state.json")).unwrap();
    let v: serde_json::Value = serde_json::from_str(&s).unwrap();
    v["step"].as_u64().unwrap()
}

// ---------------------------------------------------------------------------
// Outputs that name an input

#[test]
fn bake_never_writes_over_its_inputs_and_writes_last() {
    let dir = scratch("bake-inputs");
    let (data, model) = trained(&dir);
    let data_before = std::fs::read(&data).unwrap();
    let model_before = snapshot(&model);

    // The typo of .nppd for .nppp: refused by name, before any work.
    let o = nppp(bake_args(&model, &data, &[]));
    assert_error("bake --out DATA.nppd", &o, &["--out", "*.nppp"]);
    // A data file that happens to be named .nppp is still an input.
    let data_nppp = dir.join("data-copy.nppp");
    std::fs::copy(&data, &data_nppp).unwrap();
    let o = nppp(bake_args(
        &model,
        &data_nppp,
        &["--data", data_nppp.to_str().unwrap()],
    ));
    assert_error("bake --out = --data", &o, &["is the training data"]);
    assert_eq!(std::fs::read(&data_nppp).unwrap(), data_before);
    // Into the checkpoint, which training replaces wholesale.
    let inside = model.join("checkpoint/x.nppp");
    let o = nppp(bake_args(&model, &inside, &[]));
    assert_error("bake --out inside checkpoint", &o, &["checkpoint/"]);
    assert_eq!(std::fs::read(&data).unwrap(), data_before);
    assert_eq!(
        snapshot(&model),
        model_before,
        "the model directory changed"
    );

    // An existing estimator survives a bake that fails after the grids
    // (its held-out data is missing): bake evaluates first, writes last.
    let est = dir.join("est.nppp");
    std::fs::write(&est, b"the user's previous estimator").unwrap();
    let missing = dir.join("moved-away.nppd");
    let o = nppp(bake_args(
        &model,
        &est,
        &["--data", missing.to_str().unwrap()],
    ));
    assert_error(
        "bake with missing data",
        &o,
        &["moved-away.nppd", "--no-eval"],
    );
    assert_eq!(
        std::fs::read(&est).unwrap(),
        b"the user's previous estimator"
    );

    // And a good bake replaces it.
    assert_ok("bake", &nppp(bake_args(&model, &est, &[])));
    assert!(std::fs::read(&est).unwrap().starts_with(b"NPPPEST"));
    let names: Vec<_> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".tmp"))
        .collect();
    assert!(names.is_empty(), "temporary files left: {names:?}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn gen_never_writes_over_its_scene_or_mesh() {
    let dir = scratch("gen-inputs");
    let obj = dir.join("ball.obj");
    let obj_text = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n";
    std::fs::write(&obj, obj_text).unwrap();
    let scene = dir.join("scene.json");
    let scene_text = r#"{"camera": {"position": [0, 0, 5], "look_at": [0, 0, 0], "up": [0, 1, 0],
        "fov_y_deg": 40, "width": 8, "height": 8},
      "materials": {"m": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}},
      "meshes": {"ball": {"obj": "ball.obj"}},
      "instances": [{"mesh": "ball", "material": "m"}]}"#;
    std::fs::write(&scene, scene_text).unwrap();
    let run = |out: &Path, source: &[&str]| {
        let mut a: Vec<&OsStr> = vec!["gen".as_ref()];
        a.extend(source.iter().map(OsStr::new));
        a.extend(
            ["--rays", "100", "--k", "2", "--out"]
                .iter()
                .map(OsStr::new),
        );
        a.push(out.as_os_str());
        nppp(a)
    };
    let sc = scene.to_str().unwrap();
    let ob = obj.to_str().unwrap();
    let o = run(&scene, &["--scene", sc, "--instance", "0"]);
    assert_error("gen --out SCENE", &o, &["--out", "*.nppd"]);
    let o = run(&obj, &["--mesh", ob, "--material", "white"]);
    assert_error("gen --out MESH", &o, &["--out", "*.nppd"]);
    // An OBJ that happens to be named .nppd is still the scene's mesh.
    let odd = dir.join("odd.nppd");
    std::fs::write(&odd, obj_text).unwrap();
    std::fs::write(&scene, scene_text.replace("ball.obj", "odd.nppd")).unwrap();
    let o = run(&odd, &["--scene", sc, "--instance", "0"]);
    assert_error("gen --out = the scene's mesh", &o, &["a mesh of the scene"]);
    let o = run(
        &odd,
        &["--mesh", odd.to_str().unwrap(), "--material", "white"],
    );
    assert_error("gen --out = --mesh", &o, &["--mesh OBJ"]);
    assert_eq!(std::fs::read_to_string(&obj).unwrap(), obj_text);
    assert_eq!(std::fs::read_to_string(&odd).unwrap(), obj_text);
    assert!(
        std::fs::read_to_string(&scene)
            .unwrap()
            .contains("odd.nppd")
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// `nppp gen` and `nppp merge` keep an existing data file unless told
/// `--overwrite` (an adversarial pass replaced a 383 kB data set by a 3 kB
/// one with a slip of `--out`), and refuse a plan no disk holds.
#[test]
fn gen_and_merge_keep_existing_data_unless_told_to_overwrite() {
    let dir = scratch("gen-overwrite");
    let data = dir.join("d.nppd");
    let gen_into = |out: &Path, rays: &str, extra: &[&str]| {
        let mut a: Vec<&OsStr> = [
            "gen",
            "--mesh",
            "builtin",
            "--material",
            "white",
            "--k",
            "2",
        ]
        .iter()
        .map(OsStr::new)
        .collect();
        a.extend(
            ["--quiet", "--rays", rays, "--out"]
                .into_iter()
                .map(OsStr::new),
        );
        a.push(out.as_os_str());
        a.extend(extra.iter().map(OsStr::new));
        nppp(a)
    };
    assert_ok("gen", &gen_into(&data, "64", &[]));
    let before = std::fs::read(&data).unwrap();
    let o = gen_into(&data, "32", &[]);
    assert_error(
        "gen over existing data",
        &o,
        &["--out", "exists", "--overwrite"],
    );
    assert_eq!(std::fs::read(&data).unwrap(), before);
    assert_ok("gen --overwrite", &gen_into(&data, "32", &["--overwrite"]));
    assert_ne!(std::fs::read(&data).unwrap(), before);
    // merge into an existing .nppd likewise.
    let shard = dir.join("s0.nppd");
    assert_ok("gen --shard", &gen_into(&shard, "32", &["--shard", "0/1"]));
    let merged = std::fs::read(&data).unwrap();
    let merge = |extra: &[&str]| {
        let mut a: Vec<&OsStr> = vec!["merge".as_ref(), shard.as_os_str(), "--out".as_ref()];
        a.push(data.as_os_str());
        a.extend(extra.iter().map(OsStr::new));
        nppp(a)
    };
    assert_error(
        "merge over existing data",
        &merge(&[]),
        &["--out", "exists", "--overwrite"],
    );
    assert_eq!(std::fs::read(&data).unwrap(), merged);
    assert_ok("merge --overwrite", &merge(&["--overwrite"]));
    // A plan no disk holds is refused before any tracing.
    let huge = dir.join("huge.nppd");
    let o = gen_into(&huge, "18446744073709551615", &[]);
    assert_error("gen --rays u64::MAX", &o, &["--rays", "--k", "exits"]);
    assert!(!huge.exists());
    let _ = std::fs::remove_dir_all(&dir);
}

/// Ctrl-C or SIGTERM during `nppp gen`: the half-written data's temporary
/// file is removed (it was left behind, one per run, hidden) and no data
/// file appears. So too for the signals a batch system or a user sends to
/// end a job (a soft CPU limit's SIGXCPU, SIGUSR1: they killed it at once).
#[test]
fn an_interrupted_gen_leaves_no_temporary_file() {
    use std::process::Stdio;
    let dir = scratch("gen-interrupt");
    // In folders gen makes: they go with the temporary file (they were
    // left behind, empty).
    let made = dir.join("new/deeper");
    let out = made.join("x.nppd");
    for signal in ["INT", "TERM", "XCPU", "USR1"] {
        let child = Command::new(env!("CARGO_BIN_EXE_nppp"))
            .args(["gen", "--mesh", "builtin", "--material", "white", "--quiet"])
            .args(["--rays", "100000000", "--out"])
            .arg(&out)
            .stderr(Stdio::piped())
            .stdout(Stdio::null())
            .spawn()
            .unwrap();
        // Wait until the temporary file exists: tracing is under way.
        let listing = |d: &Path| -> Vec<String> {
            std::fs::read_dir(d)
                .into_iter()
                .flatten()
                .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
                .collect()
        };
        let t0 = std::time::Instant::now();
        while !listing(&made).iter().any(|n| n.ends_with(".tmp")) {
            assert!(t0.elapsed().as_secs() < 120, "no temporary file appeared");
            std::thread::sleep(std::time::Duration::from_millis(50));
        }
        send_signal(signal, &child);
        let o = child.wait_with_output().unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(
            o.status.code(),
            Some(130),
            "SIG{signal}: {:?}\n{err}",
            o.status
        );
        assert!(err.contains("interrupted"), "SIG{signal}:\n{err}");
        assert!(
            listing(&dir).is_empty(),
            "SIG{signal} left {:?}",
            listing(&dir)
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// A file-size limit (`ulimit -f`): its SIGXFSZ killed every command at
/// the write past it, with no message of nppp's and the temporary file
/// left behind. The write fails instead, and the error names the file.
#[cfg(unix)]
#[test]
fn a_file_size_limit_is_an_error_naming_the_file() {
    let dir = scratch("file-size-limit");
    let scene =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../data/scenes/cornell-materials.json");
    let out = dir.join("o.exr");
    let o = Command::new("sh")
        .arg("-c")
        .arg("ulimit -f 4 && exec \"$@\"")
        .arg("sh")
        .arg(env!("CARGO_BIN_EXE_nppp"))
        .args(["render", "--spp", "1", "--max-bounces", "1", "--quiet"])
        .args(["--width", "320", "--height", "240", "--out"])
        .arg(&out)
        .arg(&scene)
        .output()
        .unwrap();
    assert_error("ulimit -f 4", &o, &["o.exr", "File too large"]);
    let left: Vec<_> = std::fs::read_dir(&dir).unwrap().collect();
    assert!(left.is_empty(), "left {left:?}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn render_never_writes_over_its_reference() {
    let dir = scratch("render-ref");
    let scene =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../data/scenes/cornell-materials.json");
    let reference = dir.join("ref.exr");
    let small = ["--spp", "1", "--max-bounces", "1", "--quiet"];
    let mut a: Vec<&OsStr> = vec![
        "render".as_ref(),
        scene.as_os_str(),
        "--out".as_ref(),
        reference.as_os_str(),
    ];
    a.extend(small.iter().map(OsStr::new));
    assert_ok("render ref", &nppp(&a));
    let before = std::fs::read(&reference).unwrap();
    let spelled = dir.join("sub/../ref.exr");
    std::fs::create_dir_all(dir.join("sub")).unwrap();
    a.extend(["--reference".as_ref(), spelled.as_os_str()]);
    let o = nppp(&a);
    assert_error(
        "render --out X --reference X",
        &o,
        &["--out", "the --reference image"],
    );
    assert_eq!(std::fs::read(&reference).unwrap(), before);
    let _ = std::fs::remove_dir_all(&dir);
}

// ---------------------------------------------------------------------------
// Model directories: kills, --overwrite, checksums

/// A kill at each step of a checkpoint write (here: the resumed run's first
/// checkpoint) leaves a model that both `bake` and `--resume` use.
#[test]
fn a_kill_at_any_step_of_a_checkpoint_leaves_a_usable_model() {
    let dir = scratch("kill");
    let (data, model) = trained(&dir);
    let points = [
        "checkpoint:weights-written",
        "before-rename:checkpoint.tmp/train_config.json",
        "before-rename:checkpoint.tmp/state.json",
        "checkpoint:complete",
        "checkpoint:between-renames",
        "checkpoint:swapped",
        "before-rename:model/meta.json",
        "before-rename:model/train_config.json",
        "before-rename:model/log.csv",
    ];
    for point in points {
        let case = dir.join(point.replace([':', '/', '.'], "_"));
        let m = case.join("model");
        std::fs::create_dir_all(&case).unwrap();
        for (rel, bytes) in snapshot(&model) {
            let p = m.join(rel);
            std::fs::create_dir_all(p.parent().unwrap()).unwrap();
            std::fs::write(p, bytes).unwrap();
        }
        let mut args = small_train(&data, &m, "2");
        args.push("--resume".as_ref());
        let o = nppp_env(&args, &[("NPPP_CRASH_AT", point)]);
        assert!(
            !o.status.success(),
            "{point}: the run was not killed:\n{}",
            stderr(&o)
        );
        assert!(
            stderr(&o).contains(point),
            "{point}: never reached:\n{}",
            stderr(&o)
        );
        // The model is usable as it is: bake it, then resume it to the end.
        let est = case.join("e.nppp");
        assert_ok(
            &format!("bake after a kill at {point}"),
            &nppp(bake_args(&m, &est, &["--no-eval"])),
        );
        let o = nppp(&args);
        assert_ok(&format!("--resume after a kill at {point}"), &o);
        assert_eq!(state_step(&m), 50, "{point}");
        let log = std::fs::read_to_string(m.join("log.csv")).unwrap();
        assert_eq!(log.lines().count(), 3, "{point}: log\n{log}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// What a kill during the old in-place rewrite of train_config.json left:
/// an empty file beside a complete checkpoint. The checkpoint's own copy is
/// what resume and bake read.
#[test]
fn an_emptied_config_beside_the_checkpoint_does_not_matter() {
    let dir = scratch("empty-config");
    let (data, model) = trained(&dir);
    for f in [
        "train_config.json",
        "model_config.json",
        "meta.json",
        "log.csv",
    ] {
        std::fs::write(model.join(f), b"").unwrap();
    }
    assert_ok("bake", &nppp(bake_args(&model, &dir.join("e.nppp"), &[])));
    let mut args = small_train(&data, &model, "2");
    args.push("--resume".as_ref());
    assert_ok("--resume", &nppp(&args));
    assert_eq!(state_step(&model), 50);
    // The copies are refreshed by the next checkpoint.
    assert!(
        std::fs::read_to_string(model.join("train_config.json"))
            .unwrap()
            .contains("\"batch\"")
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// `--overwrite` keeps the old model until the new run has saved a
/// checkpoint: a kill before that loses nothing.
#[test]
fn an_interrupted_overwrite_keeps_the_old_model() {
    let dir = scratch("overwrite");
    let (data, model) = trained(&dir);
    let before = snapshot(&model);
    for point in [
        "checkpoint:weights-written",
        "checkpoint:complete",
        "before-rename:checkpoint.tmp/state.json",
    ] {
        let mut args = small_train(&data, &model, "3");
        args.push("--overwrite".as_ref());
        set_flag(&mut args, "--seed", "9");
        let o = nppp_env(&args, &[("NPPP_CRASH_AT", point)]);
        assert!(!o.status.success(), "{point}: not killed");
        let mut after = snapshot(&model);
        // Debris of the interrupted write may remain in checkpoint.tmp/; it is never read.
        after.retain(|(n, _)| !n.starts_with("checkpoint.tmp"));
        assert_eq!(after, before, "{point}: the old model changed");
        assert_ok(
            "bake the old model",
            &nppp(bake_args(&model, &dir.join("e.nppp"), &["--no-eval"])),
        );
    }
    // A completed overwrite replaces it.
    let mut args = small_train(&data, &model, "1");
    args.push("--overwrite".as_ref());
    set_flag(&mut args, "--seed", "9");
    assert_ok("--overwrite", &nppp(&args));
    assert_ne!(snapshot(&model), before);
    assert!(!model.join("checkpoint.tmp").exists());
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn damaged_checkpoints_are_refused_by_checksum() {
    let dir = scratch("checksum");
    let (data, model) = trained(&dir);
    let w = model.join("checkpoint/model.bpk");
    let good = std::fs::read(&w).unwrap();
    let n = good.len();
    for at in [0, n / 3, n / 2, n - 1] {
        let mut bad = good.clone();
        bad[at] ^= 0x10;
        std::fs::write(&w, &bad).unwrap();
        let o = nppp(bake_args(&model, &dir.join("e.nppp"), &["--no-eval"]));
        assert_error(
            &format!("bake, byte {at} flipped"),
            &o,
            &["model.bpk", "corrupt"],
        );
        let mut args = small_train(&data, &model, "2");
        args.push("--resume".as_ref());
        let o = nppp(&args);
        assert_error(
            &format!("resume, byte {at} flipped"),
            &o,
            &["model.bpk", "corrupt"],
        );
    }
    std::fs::write(&w, &good).unwrap();
    // An old (version 1) checkpoint is named as such, with the command that rebuilds it.
    let sp = model.join("checkpoint/state.json");
    let state = std::fs::read_to_string(&sp).unwrap();
    std::fs::write(&sp, state.replace("\"version\": 2", "\"version\": 1")).unwrap();
    let o = nppp(bake_args(&model, &dir.join("e.nppp"), &["--no-eval"]));
    assert_error(
        "v1 checkpoint",
        &o,
        &["version 1", "nppp train", "--overwrite"],
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// A checkpoint's `meta.json` edited to a sphere of radius 0 or k = 0 (its
/// checksum fixed up) reached the estimator's assembly and was refused
/// there with a Rust debug dump and no file named; it is refused on
/// loading, naming the file and how to rebuild the model.
#[test]
fn a_forged_meta_json_is_refused_naming_the_file() {
    let dir = scratch("forged-meta");
    let (data, model) = trained(&dir);
    let mp = model.join("checkpoint/meta.json");
    let sp = model.join("checkpoint/state.json");
    let (meta, state) = (
        std::fs::read_to_string(&mp).unwrap(),
        std::fs::read_to_string(&sp).unwrap(),
    );
    for (what, edit, needle) in [
        (
            "radius 0",
            &(|m: &mut serde_json::Value| m["dataset"]["sphere"]["radius"] = 0.0.into())
                as &dyn Fn(&mut serde_json::Value),
            "radius 0) is not finite with a positive radius",
        ),
        (
            "k 0",
            &|m: &mut serde_json::Value| m["dataset"]["k"] = 0.into(),
            "k = 0",
        ),
        // The exit transform: bake refused it at the estimator's assembly,
        // naming no file, and `train --resume` trained on.
        (
            "std 0",
            &|m: &mut serde_json::Value| m["transform"]["std"][0] = 0.0.into(),
            "transform.std[0] = 0",
        ),
        (
            "version 0",
            &|m: &mut serde_json::Value| m["version"] = 0.into(),
            "model format version 0",
        ),
    ] {
        let mut m: serde_json::Value = serde_json::from_str(&meta).unwrap();
        edit(&mut m);
        forge_checkpoint_file(&model, "meta.json", &m);
        let out = dir.join("e.nppp");
        let o = nppp(bake_args(&model, &out, &["--no-eval"]));
        assert_error(what, &o, &["checkpoint/meta.json", needle, "nppp train"]);
        assert!(!out.exists());
    }
    std::fs::write(&mp, &meta).unwrap();
    std::fs::write(&sp, &state).unwrap();
    // A newer build's model: not the advice to retrain it over.
    let mut m: serde_json::Value = serde_json::from_str(&meta).unwrap();
    m["version"] = 2.into();
    forge_checkpoint_file(&model, "meta.json", &m);
    let out = dir.join("e.nppp");
    let o = nppp(bake_args(&model, &out, &["--no-eval"]));
    assert_error("version 2", &o, &["checkpoint/meta.json", "newer nppp"]);
    assert!(!stderr(&o).contains("--overwrite`"), "{}", stderr(&o));
    std::fs::write(&mp, &meta).unwrap();
    std::fs::write(&sp, &state).unwrap();
    // The checkpoint's training configuration, by its key, for bake and
    // for a resumed run (they said "learning rate -1 must be positive").
    let tp = model.join("checkpoint/train_config.json");
    let config = std::fs::read_to_string(&tp).unwrap();
    for (key, value, needle) in [
        ("lr", serde_json::json!(-1.0), "lr (--lr) = -1"),
        ("k", serde_json::json!(0), "k (--k) = 0"),
        ("holdout_every", serde_json::json!(0), "holdout_every"),
    ] {
        let mut c: serde_json::Value = serde_json::from_str(&config).unwrap();
        c[key] = value;
        forge_checkpoint_file(&model, "train_config.json", &c);
        let o = nppp(bake_args(&model, &out, &["--no-eval"]));
        assert_error(key, &o, &["checkpoint/train_config.json", needle]);
        let mut args = small_train(&data, &model, "2");
        args.push("--resume".as_ref());
        let o = nppp(&args);
        assert_error(key, &o, &["checkpoint/train_config.json", needle]);
        std::fs::write(&sp, &state).unwrap();
    }
    std::fs::write(&tp, &config).unwrap();
    // A key nothing reads: serde skipped it, so a misspelt setting in a
    // hand-edited file trained or baked with its default, silently.
    let misspelt = |file: &str, text: &str, path: &[&str], needle: &str| {
        let mut v: serde_json::Value = serde_json::from_str(text).unwrap();
        let (last, parents) = path.split_last().unwrap();
        let mut at = &mut v;
        for p in parents {
            at = &mut at[*p];
        }
        at[*last] = serde_json::json!(0.5);
        if file == "state.json" {
            std::fs::write(&sp, serde_json::to_string_pretty(&v).unwrap()).unwrap();
        } else {
            forge_checkpoint_file(&model, file, &v);
        }
        let o = nppp(bake_args(&model, &out, &["--no-eval"]));
        let named = format!("checkpoint/{file}");
        assert_error(needle, &o, &[&named, needle, "unknown key"]);
        assert!(!out.exists());
        let mut args = small_train(&data, &model, "2");
        args.push("--resume".as_ref());
        assert_error(needle, &nppp(&args), &[&named, needle]);
    };
    misspelt(
        "train_config.json",
        &config,
        &["lerning_rate"],
        "\"lerning_rate\"",
    );
    misspelt(
        "train_config.json",
        &config,
        &["model", "hiden"],
        "\"model.hiden\"",
    );
    std::fs::write(&tp, &config).unwrap();
    std::fs::write(&sp, &state).unwrap();
    misspelt(
        "meta.json",
        &meta,
        &["dataset", "radus"],
        "\"dataset.radus\"",
    );
    std::fs::write(&mp, &meta).unwrap();
    std::fs::write(&sp, &state).unwrap();
    misspelt("state.json", &state, &["stepz"], "\"stepz\"");
    std::fs::write(&sp, &state).unwrap();
    // state.json has no checksum of its own: values no run writes went
    // into the log (a 309-digit time, a 300-digit loss).
    for (key, value, needle) in [
        ("elapsed_s", serde_json::json!(1e308), "elapsed_s = "),
        ("elapsed_s", serde_json::json!(-4.0), "elapsed_s = -4"),
        (
            "epoch_sums",
            serde_json::json!([1e308, 0, 0, 0]),
            "epoch_sums[0] = 1e308",
        ),
    ] {
        let mut v: serde_json::Value = serde_json::from_str(&state).unwrap();
        v[key] = value;
        std::fs::write(&sp, serde_json::to_string_pretty(&v).unwrap()).unwrap();
        let o = nppp(bake_args(&model, &out, &["--no-eval"]));
        assert_error(needle, &o, &["checkpoint/state.json", needle, "damaged"]);
    }
    std::fs::write(&sp, &state).unwrap();
    // The model is intact again: bake takes it.
    let o = nppp(bake_args(&model, &out, &["--no-eval"]));
    assert!(o.status.success(), "{}", stderr(&o));
    let _ = std::fs::remove_dir_all(&dir);
}

/// The weights file copied over `optim.bpk`, its checksum forged to
/// match: Burn read it as an optimizer record holding no state, and the
/// run resumed with a fresh Adam state without a word.
#[test]
fn another_record_in_place_of_the_adam_state_is_refused() {
    let dir = scratch("forged-optim");
    let (data, model) = trained(&dir);
    let ckpt = model.join("checkpoint");
    let weights = std::fs::read(ckpt.join("model.bpk")).unwrap();
    std::fs::write(ckpt.join("optim.bpk"), &weights).unwrap();
    let sp = ckpt.join("state.json");
    let mut st: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&sp).unwrap()).unwrap();
    for f in st["files"].as_array_mut().unwrap() {
        if f["name"] == "optim.bpk" {
            f["bytes"] = weights.len().into();
            f["crc32"] = common::crc32(&weights).into();
        }
    }
    std::fs::write(&sp, serde_json::to_string_pretty(&st).unwrap()).unwrap();
    let mut args = small_train(&data, &model, "2");
    args.push("--resume".as_ref());
    assert_error(
        "weights as Adam state",
        &nppp(&args),
        &["optim.bpk", "not this model's Adam state"],
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// Training data under a path that is not UTF-8: the model records the
/// path in JSON, which cannot hold it; the run failed at its first
/// checkpoint with "path contains invalid UTF-8 characters", naming no
/// file. Refused up front, by name.
#[cfg(unix)]
#[test]
fn training_data_under_a_path_that_is_not_utf8_is_refused_by_name() {
    use std::os::unix::ffi::OsStrExt;
    let dir = scratch("non-utf8");
    let odd = dir.join(OsStr::from_bytes(b"d\xfe"));
    std::fs::create_dir_all(&odd).unwrap();
    let data = odd.join("k.nppd");
    write_data(&data, 400, 4);
    let out = dir.join("m");
    let o = nppp(small_train(&data, &out, "1"));
    assert_error(
        "non-UTF-8 --data",
        &o,
        &["--data", "k.nppd", "not valid UTF-8"],
    );
    assert!(!out.exists());
    let _ = std::fs::remove_dir_all(&dir);
}

/// Files of the user's inside a checkpoint folder: each checkpoint swap
/// deleted the folder it replaced with all it held, so `train --resume
/// --data m/checkpoint/data.nppd` exited 0 and deleted its own training
/// data. Refused before any work, for resumed and fresh runs, the files
/// kept.
#[test]
fn files_put_in_a_checkpoint_folder_are_never_deleted() {
    let dir = scratch("foreign-in-checkpoint");
    let (data, model) = trained(&dir);
    let inside = model.join("checkpoint/data.nppd");
    std::fs::copy(&data, &inside).unwrap();
    let mut args = small_train(&inside, &model, "2");
    args.push("--resume".as_ref());
    let o = nppp(&args);
    assert_error(
        "--resume --data inside",
        &o,
        &[
            "checkpoint",
            "\"data.nppd\"",
            "did not write",
            "move it out",
        ],
    );
    assert!(inside.is_file());
    let mut args = small_train(&data, &model, "1");
    args.push("--overwrite".as_ref());
    assert_error(
        "--overwrite",
        &nppp(&args),
        &["\"data.nppd\"", "move it out"],
    );
    assert!(inside.is_file());
    // In `checkpoint.old` too (a kill between a swap's renames leaves one).
    std::fs::remove_file(&inside).unwrap();
    std::fs::create_dir_all(model.join("checkpoint.old")).unwrap();
    std::fs::write(model.join("checkpoint.old/notes.txt"), b"mine").unwrap();
    let mut args = small_train(&data, &model, "2");
    args.push("--resume".as_ref());
    assert_error(
        "checkpoint.old",
        &nppp(&args),
        &["checkpoint.old", "\"notes.txt\""],
    );
    assert_eq!(
        std::fs::read(model.join("checkpoint.old/notes.txt")).unwrap(),
        b"mine"
    );
    // Without it the run resumes, and the debris of train's own goes.
    std::fs::remove_file(model.join("checkpoint.old/notes.txt")).unwrap();
    assert_ok("--resume", &nppp(&args));
    assert!(!model.join("checkpoint.old").exists());
    let _ = std::fs::remove_dir_all(&dir);
}

/// Writes `value` as the checkpoint's file `name` and fixes its size and
/// checksum up in `state.json` (a forgery that the checksums pass).
fn forge_checkpoint_file(model: &Path, name: &str, value: &serde_json::Value) {
    let forged = serde_json::to_string_pretty(value).unwrap();
    std::fs::write(model.join("checkpoint").join(name), &forged).unwrap();
    let sp = model.join("checkpoint/state.json");
    let mut st: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&sp).unwrap()).unwrap();
    for f in st["files"].as_array_mut().unwrap() {
        if f["name"] == name {
            f["bytes"] = forged.len().into();
            f["crc32"] = common::crc32(forged.as_bytes()).into();
        }
    }
    std::fs::write(&sp, serde_json::to_string_pretty(&st).unwrap()).unwrap();
}

/// A fresh run that diverges before its first checkpoint left the folder it
/// created behind, holding only its lock file; the folder is removed, and a
/// folder that existed before the run is kept.
#[test]
fn a_fresh_run_that_fails_leaves_no_folder_behind() {
    let dir = scratch("diverged");
    let data = dir.join("data.nppd");
    write_data(&data, 400, 4);
    let out = dir.join("model");
    let mut args = small_train(&data, &out, "1");
    set_flag(&mut args, "--lr", "1e30");
    let o = nppp(&args);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(
        !out.exists(),
        "left {:?}",
        std::fs::read_dir(&out).map(|d| d.count())
    );
    std::fs::create_dir_all(&out).unwrap();
    let o = nppp(&args);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(out.is_dir());
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn train_refuses_a_folder_that_is_not_a_model() {
    let dir = scratch("not-a-model");
    let data = dir.join("data.nppd");
    write_data(&data, 400, 4);
    let mine = dir.join("mine");
    std::fs::create_dir_all(mine.join("checkpoint")).unwrap();
    std::fs::write(mine.join("notes.txt"), b"my notes").unwrap();
    std::fs::write(mine.join("checkpoint/mine.bin"), b"my file").unwrap();
    let before = snapshot(&mine);
    let mut args = small_train(&data, &mine, "1");
    args.push("--overwrite".as_ref());
    let o = nppp(&args);
    assert_error(
        "train --out USER-FOLDER",
        &o,
        &["notes.txt", "not a model directory"],
    );
    assert_eq!(snapshot(&mine), before);
    // --out naming the data file.
    let o = nppp(small_train(&data, &data, "1"));
    assert_error("train --out DATA", &o, &["is a file"]);
    // --data naming a folder.
    let o = nppp(small_train(&dir, &dir.join("m"), "1"));
    assert_error("train --data FOLDER", &o, &["is a directory"]);
    let _ = std::fs::remove_dir_all(&dir);
}

// ---------------------------------------------------------------------------
// Memory: flags and files that claim too much

#[test]
fn absurd_batches_are_refused_with_a_message() {
    let dir = scratch("batches");
    let data = dir.join("data.nppd");
    write_data(&data, 400, 4);
    for (flag, value, needle) in [
        (
            "--batch",
            "18446744073709551615",
            "--batch 18446744073709551615",
        ),
        ("--batch", "100000000", "--batch 100000000"),
        ("--mask-batch", "1000000000", "--mask-batch 1000000000"),
    ] {
        let out = dir.join("m");
        let mut args = small_train(&data, &out, "1");
        set_flag(&mut args, flag, value);
        let o = nppp(&args);
        assert_error(&format!("{flag} {value}"), &o, &[needle, "memory"]);
        assert!(!out.exists(), "{flag} {value}: wrote {}", out.display());
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// A small file whose chunks inflate to gigabytes (k = 2^20 identical
/// exits per hit): refused from its header and index, before reading.
#[test]
fn a_data_file_that_claims_too_much_is_refused() {
    let dir = scratch("claims");
    let data = dir.join("bomb.nppd");
    let k = 1u32 << 20;
    let header = DatasetHeader {
        mesh_name: "ball".into(),
        mesh_hash: 1,
        material_name: "white".into(),
        material_hash: 2,
        material_json: "{}".into(),
        sphere: BoundingSphere {
            center: Vec3::ZERO,
            radius: 1.0,
        },
        k,
        seed: 0,
        max_internal_bounces: 8,
        shard: None,
        vertices: false,
    };
    let mut wr = DatasetWriter::create_with(&data, header, WriterOptions::default()).unwrap();
    let exit = Exit {
        position: Vec3::Z,
        direction: Vec3::Z,
        throughput: Vec3::ZERO,
        radiance: Vec3::ZERO,
        bounces: 1,
    };
    for i in 0..4u32 {
        let f = i as f32 / 4.0;
        wr.write(&RayRecord {
            pair: SpherePair([f, 0.5, 0.5, 0.5]),
            hit: true,
            exits: vec![exit; k as usize],
            vertices: vec![],
        })
        .unwrap();
    }
    wr.finish().unwrap();
    let size = std::fs::metadata(&data).unwrap().len();
    assert!(size < 2 << 20, "the forged file is {size} bytes");
    let out = dir.join("m");
    let o = nppp(small_train(&data, &out, "1"));
    assert_error("train on a bomb", &o, &["bomb.nppd", "damaged or forged"]);
    assert!(!out.exists());
    let _ = std::fs::remove_dir_all(&dir);
}

// ---------------------------------------------------------------------------
// Interrupting a real run

/// Ctrl-C (SIGINT) and SIGTERM in the middle of a long run: a checkpoint of
/// the step reached is saved, the message says how to resume, the status is
/// 1, and `--resume` continues from there.
#[test]
fn an_interrupted_run_saves_a_checkpoint_and_says_how_to_resume() {
    use std::io::{BufRead, BufReader};
    use std::process::Stdio;
    let dir = scratch("interrupt");
    let data = dir.join("data.nppd");
    write_data(&data, 400, 4);
    for signal in ["INT", "TERM"] {
        let model = dir.join(format!("model-{signal}"));
        let mut args = small_train(&data, &model, "100000");
        args.retain(|a| *a != OsStr::new("--quiet"));
        let mut child = Command::new(env!("CARGO_BIN_EXE_nppp"))
            .args(&args)
            .stderr(Stdio::piped())
            .stdout(Stdio::null())
            .spawn()
            .unwrap();
        // Wait for the first epoch line: the loop is running.
        let mut lines = BufReader::new(child.stderr.take().unwrap()).lines();
        let mut seen = String::new();
        for line in lines.by_ref() {
            let line = line.unwrap();
            seen.push_str(&line);
            seen.push('\n');
            if line.starts_with("epoch") {
                break;
            }
        }
        // A second run into the same folder is refused while this one writes it.
        let mut second = small_train(&data, &model, "100000");
        second.push("--resume".as_ref());
        let o = nppp(&second);
        assert_error(
            "a second train into a busy folder",
            &o,
            &["another `nppp train`"],
        );
        send_signal(signal, &child);
        for line in lines {
            seen.push_str(&line.unwrap());
            seen.push('\n');
        }
        let status = child.wait().unwrap();
        assert_eq!(status.code(), Some(1), "SIG{signal}: {status:?}\n{seen}");
        assert!(
            seen.contains("interrupted: a checkpoint of step"),
            "SIG{signal}:\n{seen}"
        );
        assert!(seen.contains("--resume"), "SIG{signal}:\n{seen}");
        let step = state_step(&model);
        assert!(step >= 25, "SIG{signal}: saved step {step}");
        assert!(
            seen.contains(&format!("step {step} ")),
            "SIG{signal}: step {step} not named:\n{seen}"
        );
        // It resumes from there.
        let stop = (step + 5).to_string();
        let mut args = small_train(&data, &model, "100000");
        let extra = ["--resume", "--stop-after", stop.as_str()];
        args.extend(extra.iter().map(OsStr::new));
        assert_ok("--resume after an interrupt", &nppp(&args));
        assert_eq!(state_step(&model), step + 5);
    }
    let _ = std::fs::remove_dir_all(&dir);
}
