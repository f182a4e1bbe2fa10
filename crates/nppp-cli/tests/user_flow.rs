//! What a new user meets first (issue 21), through the real binary: PNG
//! previews with exposure and a tonemap that leave the EXR alone, image-size
//! overrides, and warnings where a number means the result is probably not
//! what was asked for.

use std::ffi::OsStr;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn file(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../tests/bad_input")
        .join(name)
}

fn scratch(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("nppp-user-flow-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn nppp<I, S>(args: I) -> Output
where
    I: IntoIterator<Item = S>,
    S: AsRef<OsStr>,
{
    Command::new(env!("CARGO_BIN_EXE_nppp"))
        .args(args)
        .env("RUST_BACKTRACE", "0")
        .output()
        .expect("cannot run nppp")
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// Renders `scene` to `dir/NAME.exr` and `.png` with `extra` flags; returns
/// the two files' bytes.
fn render(scene: &Path, dir: &Path, name: &str, extra: &[&str]) -> (Vec<u8>, Vec<u8>) {
    let exr = dir.join(format!("{name}.exr"));
    let png = dir.join(format!("{name}.png"));
    let mut args: Vec<&OsStr> = vec![
        "render".as_ref(),
        scene.as_os_str(),
        "--quiet".as_ref(),
        "--out".as_ref(),
        exr.as_os_str(),
        "--png".as_ref(),
        png.as_os_str(),
    ];
    args.extend(extra.iter().map(OsStr::new));
    let o = nppp(&args);
    assert_eq!(o.status.code(), Some(0), "{extra:?}: {}", stderr(&o));
    (std::fs::read(&exr).unwrap(), std::fs::read(&png).unwrap())
}

#[test]
fn exposure_and_tonemap_change_the_png_and_never_the_exr() {
    let dir = scratch("exposure");
    let scene = file("ok_tiny.json");
    let (exr0, png0) = render(&scene, &dir, "plain", &[]);
    let (exr1, png1) = render(&scene, &dir, "bright", &["--exposure", "2"]);
    let (exr2, png2) = render(&scene, &dir, "filmic", &["--tonemap", "filmic"]);
    assert_eq!(exr0, exr1, "--exposure changed the EXR");
    assert_eq!(exr0, exr2, "--tonemap changed the EXR");
    assert_ne!(png0, png1, "--exposure 2 left the PNG as it was");
    assert_ne!(png0, png2, "--tonemap filmic left the PNG as it was");
    for bad in ["nan", "1000"] {
        let out = dir.join("x.exr");
        let png = dir.join("x.png");
        let o = nppp([
            "render".as_ref(),
            scene.as_os_str(),
            "--exposure".as_ref(),
            bad.as_ref(),
            "--out".as_ref(),
            out.as_os_str(),
            "--png".as_ref(),
            png.as_os_str(),
        ]);
        assert_eq!(o.status.code(), Some(1), "--exposure {bad}: {}", stderr(&o));
        assert!(stderr(&o).contains("--exposure"), "{}", stderr(&o));
        assert!(!out.exists() && !png.exists());
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn image_size_flags_override_the_camera() {
    let dir = scratch("size");
    let scene = file("ok_tiny.json");
    let size = |extra: &[&str]| {
        render(&scene, &dir, "s", extra);
        let img = nppp_render::image_io::read_exr(&dir.join("s.exr")).unwrap();
        (img.width, img.height)
    };
    let (w, h) = size(&[]);
    assert_eq!(size(&["--scale", "2"]), (2 * w, 2 * h));
    assert_eq!(size(&["--width", &(3 * w).to_string()]), (3 * w, 3 * h));
    assert_eq!(size(&["--height", &(2 * h).to_string()]), (2 * w, 2 * h));
    assert_eq!(size(&["--width", "5", "--height", "3"]), (5, 3));
    // --scale with --width is a usage error (clap: status 2).
    let o = nppp([
        "render".as_ref(),
        scene.as_os_str(),
        "--scale".as_ref(),
        "2".as_ref(),
        "--width".as_ref(),
        "4".as_ref(),
        "--out".as_ref(),
        dir.join("t.exr").as_os_str(),
    ]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_p_that_no_path_reaches_is_warned_about() {
    let dir = scratch("p-over-m");
    let (exr, _) = {
        let scene = file("ok_estimator.json");
        let out = dir.join("o.exr");
        let o = nppp([
            "render".as_ref(),
            scene.as_os_str(),
            "--quiet".as_ref(),
            "--estimators".as_ref(),
            "neural".as_ref(),
            "--min-bounces".as_ref(),
            "9".as_ref(),
            "--max-bounces".as_ref(),
            "5".as_ref(),
            "--out".as_ref(),
            out.as_os_str(),
        ]);
        assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
        assert!(
            stderr(&o).contains("warning: P = 9 >= M = 5"),
            "{}",
            stderr(&o)
        );
        (std::fs::read(&out).unwrap(), ())
    };
    assert!(!exr.is_empty());
    let _ = std::fs::remove_dir_all(&dir);
}
