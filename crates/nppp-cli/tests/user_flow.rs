//! What a new user meets first (issue 21), through the real binary: the
//! summaries `train` and `bake` print, the training log and its curves, PNG
//! previews with exposure and a tonemap that leave the EXR alone, image-size
//! overrides, and warnings where a number means the result is probably not
//! what was asked for. Each test takes seconds on the tiny scenes of
//! tests/bad_input.

use std::ffi::OsStr;
use std::path::{Path, PathBuf};

mod common;
use common::{SMALL_TRAIN_FLAGS, assert_ok, assert_refused, nppp, stderr, stdout};

fn file(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../tests/bad_input")
        .join(name)
}

fn scratch(name: &str) -> common::Scratch {
    common::scratch("user-flow", name)
}

/// `nppp render SCENE --quiet --out EXR [--png PNG] EXTRA...`.
fn render_args<'a>(
    scene: &'a Path,
    exr: &'a Path,
    png: Option<&'a Path>,
    extra: &[&'a str],
) -> Vec<&'a OsStr> {
    let mut args: Vec<&OsStr> = vec![
        "render".as_ref(),
        scene.as_os_str(),
        "--quiet".as_ref(),
        "--out".as_ref(),
        exr.as_os_str(),
    ];
    if let Some(p) = png {
        args.extend([OsStr::new("--png"), p.as_os_str()]);
    }
    args.extend(extra.iter().map(|s| OsStr::new(*s)));
    args
}

/// Renders `scene` to `dir/NAME.exr` and `.png` with `extra` flags; returns
/// the two files' bytes.
fn render(scene: &Path, dir: &Path, name: &str, extra: &[&str]) -> (Vec<u8>, Vec<u8>) {
    let exr = dir.join(format!("{name}.exr"));
    let png = dir.join(format!("{name}.png"));
    let o = nppp(render_args(scene, &exr, Some(&png), extra));
    assert_ok(&format!("render {extra:?}"), &o);
    (std::fs::read(&exr).unwrap(), std::fs::read(&png).unwrap())
}

/// Width, height and 8-bit RGB samples of a PNG.
fn decode_png(bytes: &[u8]) -> (u32, u32, Vec<u8>) {
    let dec = png::Decoder::new(std::io::Cursor::new(bytes));
    let mut r = dec.read_info().unwrap();
    let mut buf = vec![0; r.output_buffer_size().unwrap()];
    let info = r.next_frame(&mut buf).unwrap();
    buf.truncate(info.buffer_size());
    (info.width, info.height, buf)
}

fn mean(bytes: &[u8]) -> f64 {
    bytes.iter().map(|&b| b as f64).sum::<f64>() / bytes.len() as f64
}

// ---------------------------------------------------------------------------
// gen -> train -> bake: summaries, the log, the curves

/// Flags of a seconds-long training run (NdArray, tiny widths, 25-step
/// epochs, 50 steps): a log row every 10 steps, held-out metrics every 20
/// steps and at each epoch's end.
fn small_train<'a>(data: &'a Path, out: &'a Path) -> Vec<&'a OsStr> {
    let mut v: Vec<&OsStr> = vec![
        "train".as_ref(),
        "--data".as_ref(),
        data.as_os_str(),
        "--out".as_ref(),
        out.as_os_str(),
    ];
    v.extend(SMALL_TRAIN_FLAGS.iter().map(OsStr::new));
    v.extend(
        ["--steps", "50", "--log-every", "10", "--eval-every", "20"]
            .iter()
            .map(OsStr::new),
    );
    v
}

/// The summaries of train and bake are a few labelled lines, never a Rust
/// debug dump; the log has a row every `--log-every` steps with the
/// learning rate and the time per step, held-out metrics every
/// `--eval-every` steps and at each epoch's end; `nppp plot-log DIR` draws
/// log.svg and log.png beside it.
#[test]
fn train_and_bake_print_summaries_and_the_log_is_plotted() {
    let dir = scratch("train");
    // The data from the real `gen`: the tiny scene's glass ball.
    let data = dir.join("data.nppd");
    let scene = file("ok_tiny.json");
    let o = nppp([
        "gen".as_ref(),
        "--scene".as_ref(),
        scene.as_os_str(),
        "--instance".as_ref(),
        "3".as_ref(),
        "--rays".as_ref(),
        "400".as_ref(),
        "--k".as_ref(),
        "4".as_ref(),
        "--quiet".as_ref(),
        "--out".as_ref(),
        data.as_os_str(),
    ]);
    assert_ok("gen", &o);
    assert!(!stderr(&o).contains("warning"), "{}", stderr(&o));
    // gen's summary, the model for the others: rates in one format (issue
    // 21 point 8), no `inf` from a run shorter than the CPU clock's tick.
    let out = stdout(&o);
    for needle in [
        "  rays        400 ",
        " exits/s, ",
        " rays/s, ",
        " BVH queries/s in the walks",
        // 400 rays project nothing (a one-ray shard projected 11,459 min).
        "  projection  none: 400 rays are too few",
    ] {
        assert!(out.contains(needle), "gen summary lacks {needle:?}:\n{out}");
    }
    assert!(!out.contains("inf ") && !out.contains("NaN"), "{out}");

    let model = dir.join("model");
    let o = nppp(small_train(&data, &model));
    assert_ok("train", &o);
    let out = stdout(&o);
    for needle in [
        "  steps       50 of 50 (50 in this run, 2.00 epochs)",
        "  time        ",
        " ms per step",
        "  held-out    ",
        "mask accuracy",
        "  throughput  mean error per ray ",
        "  files       ",
        "log.csv",
        "  next        `nppp bake --model ",
    ] {
        assert!(
            out.contains(needle),
            "train summary lacks {needle:?}:\n{out}"
        );
    }
    for dump in ["TrainReport", "HeldoutMetrics", "{", "}", "Some("] {
        assert!(
            !out.contains(dump),
            "train printed a debug dump ({dump:?}):\n{out}"
        );
    }

    // log.csv: the header names its columns; rows at every 10th step and at
    // the evaluations (20, 40, every epoch's end: 25 and 50), held-out
    // columns filled exactly at the evaluations.
    let log = std::fs::read_to_string(model.join("log.csv")).unwrap();
    let mut lines = log.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = |name: &str| {
        header
            .iter()
            .position(|c| *c == name)
            .unwrap_or_else(|| panic!("log.csv has no column {name:?}: {header:?}"))
    };
    let (step, lr, loss, held, sps) = (
        col("step"),
        col("lr"),
        col("train_loss"),
        col("heldout_chamfer"),
        col("seconds_per_step"),
    );
    for name in [
        "train_chamfer",
        "train_energy",
        "train_bce",
        "mask_accuracy",
        "throughput_rms_error",
    ] {
        col(name);
    }
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    let steps: Vec<u64> = rows.iter().map(|r| r[step].parse().unwrap()).collect();
    assert_eq!(steps, [10, 20, 25, 30, 40, 50], "log rows:\n{log}");
    for r in &rows {
        assert_eq!(r.len(), header.len(), "{log}");
        for c in [lr, loss, sps] {
            let v: f64 = r[c].parse().unwrap_or_else(|_| panic!("{log}"));
            assert!(v.is_finite() && v > 0.0, "{log}");
        }
        let evaluated = [20, 25, 40, 50].contains(&r[step].parse::<u64>().unwrap());
        assert_eq!(!r[held].is_empty(), evaluated, "held-out cells:\n{log}");
    }

    // The curves: `train` drew them already where a font is found; plot-log
    // redraws both files beside the log.
    let fonts = !stderr(&o).contains("no TrueType font");
    assert_eq!(
        out.contains("  curves      "),
        fonts,
        "{out}\n{}",
        stderr(&o)
    );
    for f in ["log.svg", "log.png"] {
        let _ = std::fs::remove_file(model.join(f));
    }
    let o = nppp(["plot-log".as_ref(), model.as_os_str()]);
    if fonts {
        assert_ok("plot-log", &o);
        let svg = std::fs::read_to_string(model.join("log.svg")).unwrap();
        assert!(svg.contains("<svg") && svg.contains("held-out"), "{svg}");
        let (w, h, px) = decode_png(&std::fs::read(model.join("log.png")).unwrap());
        assert!(w >= 400 && h >= 400, "{w}x{h}");
        assert!(
            px.iter().any(|&b| b < 128),
            "log.png is blank: nothing drawn"
        );
        assert!(stdout(&o).contains("log.png"), "{}", stdout(&o));
    } else {
        assert_refused("plot-log without a font", &o, 1, &["font"]);
    }

    // bake: the same kind of summary.
    let est = dir.join("m.nppp");
    let o = nppp([
        "bake".as_ref(),
        "--model".as_ref(),
        model.as_os_str(),
        "--out".as_ref(),
        est.as_os_str(),
        "--latent-grid".as_ref(),
        "4".as_ref(),
        "--mask-grid".as_ref(),
        "4".as_ref(),
        "--backend".as_ref(),
        "ndarray".as_ref(),
        "--quiet".as_ref(),
        "--eval-rays".as_ref(),
        "16".as_ref(),
    ]);
    assert_ok("bake", &o);
    let out = stdout(&o);
    for needle in [
        "  grids       latent 4^4 at ",
        " with the decoder",
        "  time        ",
        "  held-out    ",
        "unbaked",
        "baked",
        "mask accuracy",
        "throughput RMS error per ray",
    ] {
        assert!(
            out.contains(needle),
            "bake summary lacks {needle:?}:\n{out}"
        );
    }
    for dump in ["BakeReport", "HeldoutMetrics", "{", "}", "Some("] {
        assert!(
            !out.contains(dump),
            "bake printed a debug dump ({dump:?}):\n{out}"
        );
    }
    assert!(est.exists());
    let _ = std::fs::remove_dir_all(&dir);
}

// ---------------------------------------------------------------------------
// The PNG preview and the image size

#[test]
fn exposure_and_tonemap_change_the_png_and_never_the_exr() {
    let dir = scratch("exposure");
    let scene = file("ok_tiny.json");
    let (exr0, png0) = render(&scene, &dir, "plain", &[]);
    let (exr1, png1) = render(&scene, &dir, "bright", &["--exposure", "2"]);
    let (exr2, png2) = render(&scene, &dir, "dark", &["--exposure", "-2"]);
    let (exr3, png3) = render(&scene, &dir, "filmic", &["--tonemap", "filmic"]);
    let (exr4, png4) = render(&scene, &dir, "clamp", &["--tonemap", "clamp"]);
    for (e, what) in [
        (&exr1, "--exposure 2"),
        (&exr2, "--exposure -2"),
        (&exr3, "--tonemap filmic"),
        (&exr4, "--tonemap clamp"),
    ] {
        assert!(*e == exr0, "{what} changed the EXR");
    }
    assert_eq!(png0, png4, "clamp is the default tone curve");
    assert_ne!(png0, png3, "--tonemap filmic left the PNG as it was");
    let m = |p: &[u8]| mean(&decode_png(p).2);
    let (m0, m1, m2) = (m(&png0), m(&png1), m(&png2));
    assert!(
        m2 < m0 && m0 < m1,
        "PNG means at -2, 0, +2 EV: {m2} {m0} {m1}"
    );

    // Values nppp refuses (status 1, naming the flag), and what the parser
    // refuses (status 2): an unknown curve, preview flags without --png.
    let exr = dir.join("x.exr");
    let png = dir.join("x.png");
    for bad in ["nan", "inf", "1000", "-100"] {
        let o = nppp(render_args(&scene, &exr, Some(&png), &["--exposure", bad]));
        assert_refused(&format!("--exposure {bad}"), &o, 1, &["--exposure"]);
    }
    let o = nppp(render_args(
        &scene,
        &exr,
        Some(&png),
        &["--tonemap", "reinhard"],
    ));
    assert_refused("--tonemap reinhard", &o, 2, &["--tonemap", "filmic"]);
    for flags in [["--exposure", "1"], ["--tonemap", "filmic"]] {
        let o = nppp(render_args(&scene, &exr, None, &flags));
        assert_refused(&format!("{flags:?} without --png"), &o, 2, &["--png"]);
    }
    assert!(!exr.exists() && !png.exists(), "a refused render wrote");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn image_size_flags_override_the_camera() {
    let dir = scratch("size");
    // A 16x8 camera, to see the aspect ratio kept.
    let text = std::fs::read_to_string(file("ok_tiny.json"))
        .unwrap()
        .replace(
            "\"width\": 8, \"height\": 8",
            "\"width\": 16, \"height\": 8",
        );
    assert!(text.contains("\"width\": 16"));
    let scene = dir.join("wide.json");
    std::fs::write(&scene, text).unwrap();
    let size = |extra: &[&str]| {
        let (_, png) = render(&scene, &dir, "s", extra);
        let img = nppp_render::image_io::read_exr(&dir.join("s.exr")).unwrap();
        let (pw, ph, _) = decode_png(&png);
        assert_eq!(
            (pw, ph),
            (img.width, img.height),
            "{extra:?}: PNG and EXR differ"
        );
        (img.width, img.height)
    };
    assert_eq!(size(&[]), (16, 8));
    assert_eq!(size(&["--scale", "2"]), (32, 16));
    assert_eq!(size(&["--scale", "0.25"]), (4, 2));
    assert_eq!(size(&["--width", "24"]), (24, 12), "height follows");
    assert_eq!(size(&["--height", "2"]), (4, 2), "width follows");
    assert_eq!(size(&["--width", "5", "--height", "3"]), (5, 3));

    let out = dir.join("t.exr");
    for (flags, needle) in [
        (&["--scale", "0"][..], "--scale"),
        (&["--scale", "nan"][..], "--scale"),
        (
            &["--scale", "1e6"][..],
            "--scale 1000000: the image would be",
        ),
        // A huge factor in e-notation, not 300 digits.
        (&["--scale", "1e300"][..], "1.600e301 pixels wide"),
        (
            &["--height", "16384"][..],
            "--height 16384: the image would be 32768 pixels wide (16x8",
        ),
    ] {
        let o = nppp(render_args(&scene, &out, None, flags));
        assert_refused(&format!("{flags:?}"), &o, 1, &[needle]);
    }
    // A count of 0 is the parser's usage error (status 2), naming the flag.
    for (flags, needle) in [
        (&["--width", "0"][..], "--width"),
        (&["--height", "0"][..], "--height"),
    ] {
        let o = nppp(render_args(&scene, &out, None, flags));
        assert_refused(
            &format!("{flags:?}"),
            &o,
            2,
            &[needle, "must be at least 1"],
        );
    }
    // --scale with --width or --height is a usage error (the parser's: 2).
    for flags in [
        ["--scale", "2", "--width", "4"],
        ["--scale", "2", "--height", "4"],
    ] {
        let o = nppp(render_args(&scene, &out, None, &flags));
        assert_refused(&format!("{flags:?}"), &o, 2, &["--scale"]);
    }
    assert!(!out.exists(), "a refused render wrote");
    let _ = std::fs::remove_dir_all(&dir);
}

// ---------------------------------------------------------------------------
// Warnings

/// With P >= M no path reaches an estimator: the render says so (it is
/// plain path tracing, bit for bit) and says what to do; with P < M it does
/// not.
#[test]
fn a_p_that_no_path_reaches_is_warned_about() {
    let dir = scratch("p-over-m");
    let scene = file("ok_estimator.json");
    let run = |name: &str, p: &str, estimators: &str| {
        let out = dir.join(format!("{name}.exr"));
        let o = nppp(render_args(
            &scene,
            &out,
            None,
            &[
                "--estimators",
                estimators,
                "--min-bounces",
                p,
                "--max-bounces",
                "3",
            ],
        ));
        assert_ok(name, &o);
        (stderr(&o), std::fs::read(&out).unwrap())
    };
    for p in ["3", "9"] {
        let (err, exr) = run(&format!("p{p}"), p, "neural");
        assert!(
            err.contains(&format!("warning: P = {p} >= M = 3"))
                && err.contains("plain path tracing")
                && err.contains("lower --min-bounces"),
            "P = {p}:\n{err}"
        );
        let (_, pt) = run("pt", p, "off");
        assert!(exr == pt, "P = {p} >= M: not plain path tracing");
    }
    let (err, _) = run("p1", "1", "neural");
    assert!(!err.contains(">= M"), "P = 1 < M = 3 warned:\n{err}");
    let (err, _) = run("off", "9", "off");
    assert!(!err.contains(">= M"), "--estimators off warned:\n{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// `gen` on an emitter is refused (a lamp ends every path that reaches it:
/// nothing to learn, and the renderer leaves an estimator on a lamp
/// unused); it wrote only zero-throughput exits with a warning before. A
/// reflecting object gets no warning.
#[test]
fn gen_on_an_emitter_is_refused() {
    let dir = scratch("gen-emitter");
    let scene = file("ok_tiny.json");
    let args = |instance: &str, out: &Path| -> Vec<std::ffi::OsString> {
        vec![
            "gen".into(),
            "--scene".into(),
            scene.clone().into(),
            "--instance".into(),
            instance.into(),
            "--rays".into(),
            "200".into(),
            "--k".into(),
            "2".into(),
            "--quiet".into(),
            "--out".into(),
            out.into(),
        ]
    };
    let generate = |instance: &str| {
        let out = dir.join(format!("i{instance}.nppd"));
        let o = nppp(args(instance, &out));
        assert_ok(&format!("gen --instance {instance}"), &o);
        assert!(out.exists());
        stderr(&o)
    };
    // Instance 1 is the lamp.
    let lamp = dir.join("i1.nppd");
    let o = nppp(args("1", &lamp));
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("material \"lamp\" is an emitter")
            && stderr(&o).contains("nothing for an estimator to learn"),
        "{}",
        stderr(&o)
    );
    assert!(!lamp.exists());
    // Instance 3, the glass ball, and 0, the diffuse floor: no warning.
    for i in ["3", "0"] {
        let err = generate(i);
        assert!(!err.contains("warning"), "instance {i}:\n{err}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// `--estimators neural` at P = 0 on an object that is not translucent (the
/// corpus' glass ball) says that the camera sees it through the network;
/// from P = 1, or with the oracle, nothing is said.
#[test]
fn neural_p0_on_a_surface_warns() {
    let dir = scratch("p0-warning");
    let scene = file("ok_estimator.json");
    let out = dir.join("o.exr");
    let warned = |flags: &[&'static str]| {
        let o = nppp(render_args(&scene, &out, None, flags));
        assert_ok("render", &o);
        stderr(&o)
            .lines()
            .any(|l| l.starts_with("warning: P = 0: camera rays enter the estimators"))
    };
    assert!(warned(&["--estimators", "neural"]), "the scene's P is 0");
    assert!(!warned(&["--estimators", "neural", "--min-bounces", "1"]));
    assert!(!warned(&["--estimators", "oracle"]));
    let _ = std::fs::remove_dir_all(&dir);
}

/// An estimator whose exits are nonsense (the corpus' random decoder) has
/// most of its exits clamped: the render warns and says what to do.
#[test]
fn an_estimator_that_clamps_most_exits_is_warned_about() {
    let dir = scratch("clamped");
    let scene = file("ok_estimator.json");
    let out = dir.join("o.exr");
    let o = nppp(render_args(&scene, &out, None, &["--estimators", "neural"]));
    assert_ok("render", &o);
    let err = stderr(&o);
    let line = err
        .lines()
        .find(|l| l.starts_with("warning:") && l.contains("clamped"))
        .unwrap_or_else(|| panic!("no clamped-exits warning:\n{err}"));
    assert!(
        line.contains("estimator exits (") && line.contains("Train longer"),
        "{line}"
    );
    // Plain path tracing has no estimator to warn about.
    let o = nppp(render_args(&scene, &out, None, &["--estimators", "off"]));
    assert_ok("render off", &o);
    assert!(!stderr(&o).contains("warning"), "{}", stderr(&o));
    let _ = std::fs::remove_dir_all(&dir);
}
