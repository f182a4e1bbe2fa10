//! Shards (issue 22), through the real binary: `nppp render --shard I/K`
//! and `nppp gen --shard I/K` parts, merged by `nppp merge` in any order,
//! give the single run's file byte for byte; parts that do not make one
//! render or one data set are refused with a message naming the part and
//! what is wrong, and nothing is written.

use std::ffi::OsString;
use std::path::{Path, PathBuf};
use std::process::Output;

mod common;
use common::{assert_ok, assert_refused, nppp};

fn repo(rel: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../..")
        .join(rel)
}

fn scratch(name: &str) -> common::Scratch {
    common::scratch("shards", name)
}

const SPP: u32 = 6;

/// `nppp render SCENE --width 24 --spp 6 --quiet FLAGS... --out OUT [--shard I/K]`.
fn render(scene: &Path, flags: &[&str], out: &Path, shard: Option<(u32, u32)>) -> Output {
    let mut args: Vec<OsString> = vec!["render".into(), scene.into()];
    for a in ["--width", "24", "--spp", &SPP.to_string(), "--quiet"] {
        args.push(a.into());
    }
    args.extend(flags.iter().map(OsString::from));
    args.push("--out".into());
    args.push(out.into());
    if let Some((i, k)) = shard {
        args.push("--shard".into());
        args.push(format!("{i}/{k}").into());
    }
    nppp(args)
}

fn merge(parts: &[PathBuf], out: &Path) -> Output {
    let mut args: Vec<OsString> = vec!["merge".into()];
    args.extend(parts.iter().map(OsString::from));
    args.push("--out".into());
    args.push(out.into());
    nppp(args)
}

/// The K parts of a render, rendered, in a rotated order (the merge must
/// not care).
fn render_parts(dir: &Path, scene: &Path, flags: &[&str], k: u32, tag: &str) -> Vec<PathBuf> {
    let mut parts: Vec<PathBuf> = (0..k)
        .map(|i| {
            let p = dir.join(format!("{tag}-{i}-of-{k}.nppr"));
            assert_ok(
                &format!("shard {i}/{k}"),
                &render(scene, flags, &p, Some((i, k))),
            );
            p
        })
        .collect();
    parts.rotate_left(k as usize / 2);
    parts
}

#[test]
fn render_shards_merge_into_the_same_bytes() {
    let dir = scratch("render");
    let cases: [(&str, &[&str]); 3] = [
        // The network at P = 1: decoder batches of every size.
        (
            "data/scenes/cornell-box.json",
            &["--estimators", "neural", "--min-bounces", "1"],
        ),
        // auto's pilot runs in every shard and decides the same.
        ("data/scenes/cornell-jade.json", &[]),
        ("data/scenes/cornell-glass.json", &["--estimators", "off"]),
    ];
    for (c, (scene, flags)) in cases.iter().enumerate() {
        let scene = repo(scene);
        let whole = dir.join(format!("whole-{c}.exr"));
        assert_ok("whole render", &render(&scene, flags, &whole, None));
        let want = std::fs::read(&whole).unwrap();
        for k in [1, 4, SPP] {
            let parts = render_parts(&dir, &scene, flags, k, &format!("c{c}"));
            let merged = dir.join(format!("merged-{c}-{k}.exr"));
            assert_ok("merge", &merge(&parts, &merged));
            assert!(
                std::fs::read(&merged).unwrap() == want,
                "{}: {k} shards merged differ from the single render",
                scene.display()
            );
        }
    }
}

#[test]
fn merge_writes_the_same_preview() {
    let dir = scratch("preview");
    let scene = repo("data/scenes/cornell-glass.json");
    let (exr, png) = (dir.join("whole.exr"), dir.join("whole.png"));
    let mut flags = vec!["--estimators", "off", "--png"];
    let png_s = png.to_string_lossy().into_owned();
    flags.push(&png_s);
    assert_ok("whole", &render(&scene, &flags, &exr, None));
    let parts = render_parts(&dir, &scene, &["--estimators", "off"], 2, "p");
    let (mexr, mpng) = (dir.join("merged.exr"), dir.join("merged.png"));
    let mut args: Vec<OsString> = vec!["merge".into()];
    args.extend(parts.iter().map(OsString::from));
    args.extend([
        "--out".into(),
        mexr.clone().into(),
        "--png".into(),
        mpng.clone().into(),
    ]);
    assert_ok("merge --png", &nppp(args));
    assert!(std::fs::read(&mexr).unwrap() == std::fs::read(&exr).unwrap());
    assert!(std::fs::read(&mpng).unwrap() == std::fs::read(&png).unwrap());
}

/// `--samples` ranges of one's choice (unequal machines), mixed with a
/// `--shard` part, merge into the single render too.
#[test]
fn explicit_sample_ranges_merge_into_the_same_bytes() {
    let dir = scratch("samples");
    let scene = repo("data/scenes/cornell-glass.json");
    let off = ["--estimators", "off"];
    let whole = dir.join("whole.exr");
    assert_ok("whole", &render(&scene, &off, &whole, None));
    let a = dir.join("a.nppr");
    assert_ok("shard 0/2", &render(&scene, &off, &a, Some((0, 2))));
    let mut parts = vec![a];
    for (name, range) in [("b.nppr", "3..4"), ("c.nppr", "4..6")] {
        let p = dir.join(name);
        let mut flags = off.to_vec();
        flags.extend(["--samples", range]);
        assert_ok(range, &render(&scene, &flags, &p, None));
        parts.push(p);
    }
    parts.reverse();
    let merged = dir.join("merged.exr");
    assert_ok("merge", &merge(&parts, &merged));
    assert!(std::fs::read(&merged).unwrap() == std::fs::read(&whole).unwrap());
}

#[test]
fn merge_refuses_parts_of_other_renders_and_gaps() {
    let dir = scratch("refuse");
    let scene = repo("data/scenes/cornell-glass.json");
    let off = ["--estimators", "off"];
    let part = |name: &str, flags: &[&str], shard: (u32, u32)| {
        let p = dir.join(name);
        assert_ok(name, &render(&scene, flags, &p, Some(shard)));
        p
    };
    let p0 = part("p0.nppr", &off, (0, 3));
    let p1 = part("p1.nppr", &off, (1, 3));
    let p2 = part("p2.nppr", &off, (2, 3));
    let half0 = part("half0.nppr", &off, (0, 2));
    let seed9 = part(
        "seed9.nppr",
        &["--estimators", "off", "--seed", "9"],
        (1, 3),
    );
    let m4 = part(
        "m4.nppr",
        &["--estimators", "off", "--max-bounces", "4"],
        (1, 3),
    );
    // auto with and without its confirmation pass (which renders the
    // first samples its own way): parts of two different renders.
    let auto0 = part("auto0.nppr", &["--estimators", "auto"], (0, 2));
    let confirmed1 = part(
        "confirmed1.nppr",
        &["--estimators", "auto", "--auto-confirm"],
        (1, 2),
    );
    let other_scene = dir.join("other.nppr");
    assert_ok(
        "other scene",
        &render(
            &repo("data/scenes/cornell-box.json"),
            &off,
            &other_scene,
            Some((1, 3)),
        ),
    );
    let out = dir.join("out.exr");
    let cases: Vec<(&str, Vec<PathBuf>, Vec<&str>)> = vec![
        (
            "a missing part",
            vec![p0.clone(), p2.clone()],
            vec!["samples 2..4", "in no part"],
        ),
        (
            "no last part",
            vec![p0.clone(), p1.clone()],
            vec!["samples 4..6", "in no part"],
        ),
        (
            "overlapping parts",
            vec![p0.clone(), half0.clone(), p1.clone(), p2.clone()],
            vec!["overlap", "half0.nppr"],
        ),
        (
            "another seed",
            vec![p0.clone(), seed9.clone(), p2.clone()],
            vec!["seed9.nppr", "seed 9"],
        ),
        (
            "another M",
            vec![p0.clone(), m4.clone(), p2.clone()],
            vec!["m4.nppr", "M (max bounces) 4"],
        ),
        (
            "another scene",
            vec![p0.clone(), other_scene.clone(), p2.clone()],
            vec!["other.nppr", "scene content"],
        ),
        (
            "a part twice",
            vec![p0.clone(), p1.clone(), p1.clone(), p2.clone()],
            vec!["named twice"],
        ),
        (
            "with and without --auto-confirm",
            vec![auto0, confirmed1],
            vec!["confirmed1.nppr", "auto_confirm = true"],
        ),
    ];
    for (what, parts, needles) in cases {
        assert_refused(what, &merge(&parts, &out), 1, &needles);
        assert!(!out.exists(), "{what}: an image was written");
    }
    // Damaged files, each named.
    let bytes = std::fs::read(&p1).unwrap();
    let damaged: [(&str, Vec<u8>, &str); 5] = [
        (
            "truncated.nppr",
            bytes[..bytes.len() - 100].to_vec(),
            "truncated",
        ),
        ("header-only.nppr", bytes[..40].to_vec(), "truncated"),
        (
            "flipped.nppr",
            {
                let mut b = bytes.clone();
                let n = b.len();
                b[n - 50] ^= 0x40;
                b
            },
            "checksum",
        ),
        (
            // A part of the format before this one (four-limb films).
            "version1.nppr",
            {
                let mut b = bytes.clone();
                b[8] = 1;
                b
            },
            "render part version 1; this build reads version 2",
        ),
        // An OpenEXR file's magic number, then anything.
        (
            "image.nppr",
            b"\x76\x2f\x31\x01 not a part".to_vec(),
            "not an nppp render part",
        ),
    ];
    for (name, b, needle) in damaged {
        let p = dir.join(name);
        std::fs::write(&p, b).unwrap();
        let o = merge(&[p0.clone(), p.clone(), p2.clone()], &out);
        assert_refused(name, &o, 1, &[name, needle]);
        assert!(!out.exists(), "{name}: an image was written");
    }
    // A part cannot be the output, and the output must be an image or data.
    assert_refused(
        "out is a part",
        &merge(&[p0.clone(), p1.clone(), p2.clone()], &p1),
        1,
        &["is one of the parts"],
    );
    assert_refused(
        "out .png",
        &merge(&[p0, p1, p2], &dir.join("x.png")),
        1,
        &["*.exr", "*.nppd"],
    );
}

#[test]
fn shard_flags_are_checked_before_rendering() {
    let dir = scratch("flags");
    let scene = repo("data/scenes/cornell-glass.json");
    let part = dir.join("p.nppr");
    // (what, flags, --out, exit status, needles)
    type Case<'a> = (&'a str, Vec<&'a str>, PathBuf, i32, Vec<&'a str>);
    let cases: [Case; 10] = [
        (
            "I = K",
            vec!["--shard", "6/6"],
            part.clone(),
            2,
            vec!["0 to 5"],
        ),
        (
            "K > spp",
            vec!["--shard", "0/7"],
            part.clone(),
            1,
            vec!["at most 6 shards"],
        ),
        (
            "not I/K",
            vec!["--shard", "two"],
            part.clone(),
            2,
            vec!["I/K"],
        ),
        (
            "an EXR name",
            vec!["--shard", "0/2"],
            dir.join("p.exr"),
            1,
            vec!["*.nppr"],
        ),
        (
            "samples past spp",
            vec!["--samples", "2..9"],
            part.clone(),
            1,
            vec!["6 samples per pixel"],
        ),
        (
            "empty samples",
            vec!["--samples", "3..3"],
            part.clone(),
            2,
            vec!["START must be below END"],
        ),
        (
            "samples past 32 bits",
            vec!["--samples", "0..4294967296"],
            part.clone(),
            2,
            vec!["4294967296 is too large"],
        ),
        (
            "with --png",
            vec!["--shard", "0/2", "--png", "x.png"],
            part.clone(),
            2,
            vec!["--png"],
        ),
        // The preview's flags without a preview were accepted and did
        // nothing (clap's `requires` does not hold beside --shard).
        (
            "with --exposure",
            vec!["--shard", "0/2", "--exposure", "3"],
            part.clone(),
            1,
            vec!["--exposure", "does not write"],
        ),
        (
            "with --tonemap",
            vec!["--samples", "0..2", "--tonemap", "filmic"],
            part.clone(),
            1,
            vec!["--tonemap", "does not write"],
        ),
    ];
    for (what, flags, out, code, needles) in cases {
        let mut args: Vec<OsString> = vec![
            "render".into(),
            scene.clone().into(),
            "--spp".into(),
            "6".into(),
        ];
        args.extend(flags.iter().map(OsString::from));
        args.extend(["--out".into(), out.clone().into()]);
        assert_refused(what, &nppp(args), code, &needles);
        assert!(!out.exists(), "{what}: a file was written");
    }
}

/// `nppp gen --mesh builtin --material white --rays 9000 --k 2 --seed 5 --out OUT [--shard I/K]`.
fn gen_data(out: &Path, seed: &str, shard: Option<&str>) -> Output {
    let mut args: Vec<OsString> = [
        "gen",
        "--mesh",
        "builtin",
        "--material",
        "white",
        "--rays",
        "9000",
        "--k",
        "2",
        "--quiet",
        "--seed",
        seed,
    ]
    .iter()
    .map(OsString::from)
    .collect();
    args.extend(["--out".into(), out.into()]);
    if let Some(s) = shard {
        args.extend(["--shard".into(), s.into()]);
    }
    nppp(args)
}

#[test]
fn data_shards_merge_into_the_same_bytes() {
    let dir = scratch("gen");
    let whole = dir.join("whole.nppd");
    assert_ok("gen", &gen_data(&whole, "5", None));
    // 9000 rays are 3 chunks of 4096: at most 3 shards.
    let parts: Vec<PathBuf> = ["2/3", "0/3", "1/3"]
        .iter()
        .enumerate()
        .map(|(i, s)| {
            let p = dir.join(format!("part{i}.nppd"));
            assert_ok(s, &gen_data(&p, "5", Some(s)));
            p
        })
        .collect();
    let merged = dir.join("merged.nppd");
    assert_ok("merge", &merge(&parts, &merged));
    assert!(
        std::fs::read(&merged).unwrap() == std::fs::read(&whole).unwrap(),
        "merged data differ"
    );
    let halves: Vec<PathBuf> = ["0/2", "1/2"]
        .iter()
        .enumerate()
        .map(|(i, s)| {
            let p = dir.join(format!("half{i}.nppd"));
            assert_ok(s, &gen_data(&p, "5", Some(s)));
            p
        })
        .collect();
    let merged2 = dir.join("merged2.nppd");
    assert_ok("merge halves", &merge(&halves, &merged2));
    assert!(std::fs::read(&merged2).unwrap() == std::fs::read(&whole).unwrap());

    let out = dir.join("out.nppd");
    let seed6 = dir.join("seed6.nppd");
    assert_ok("seed 6", &gen_data(&seed6, "6", Some("1/3")));
    let cases: Vec<(&str, Vec<PathBuf>, Vec<&str>)> = vec![
        (
            "a missing shard",
            vec![parts[0].clone(), parts[1].clone()],
            vec!["rays 4096..8192", "in no part"],
        ),
        (
            "another seed",
            vec![parts[0].clone(), parts[1].clone(), seed6],
            vec!["seed6.nppd", "seed 6"],
        ),
        (
            "overlap",
            vec![
                parts[0].clone(),
                parts[1].clone(),
                parts[2].clone(),
                halves[1].clone(),
            ],
            vec!["overlap"],
        ),
        (
            "a whole data set",
            vec![whole.clone(), parts[0].clone()],
            vec!["whole.nppd", "not a shard"],
        ),
    ];
    for (what, parts, needles) in cases {
        assert_refused(what, &merge(&parts, &out), 1, &needles);
        assert!(!out.exists(), "{what}: data were written");
    }
    assert_refused(
        "4 shards of 3 chunks",
        &gen_data(&out, "5", Some("0/4")),
        1,
        &["at most 3 shards"],
    );
    assert!(!out.exists());
}
