//! Helpers shared by the binary's integration tests: running `nppp`, fresh
//! scratch folders, and the flags of a seconds-long training run.

// Each test binary uses its own subset.
#![allow(dead_code)]

use std::ffi::OsStr;
use std::process::{Command, Output};

/// A fresh, empty folder named after the test file (`prefix`) and the case,
/// removed when the test is done (kept when it fails).
pub fn scratch(prefix: &str, name: &str) -> Scratch {
    Scratch::new(&format!("nppp-{prefix}-{}-{name}", std::process::id()))
}

pub use nppp_files::ScratchDir as Scratch;

/// Runs the `nppp` binary with `env` set (and no backtraces on stderr).
pub fn nppp_env<I, S>(args: I, env: &[(&str, &str)]) -> Output
where
    I: IntoIterator<Item = S>,
    S: AsRef<OsStr>,
{
    let mut c = Command::new(env!("CARGO_BIN_EXE_nppp"));
    c.args(args).env("RUST_BACKTRACE", "0");
    for (k, v) in env {
        c.env(k, v);
    }
    c.output().expect("cannot run nppp")
}

pub fn nppp<I, S>(args: I) -> Output
where
    I: IntoIterator<Item = S>,
    S: AsRef<OsStr>,
{
    nppp_env(args, &[])
}

pub fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

pub fn stdout(o: &Output) -> String {
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// Exit status 0, else both outputs in the failure.
pub fn assert_ok(what: &str, o: &Output) {
    assert_eq!(
        o.status.code(),
        Some(0),
        "{what} failed:\n{}{}",
        stdout(o),
        stderr(o)
    );
}

/// Exit status `code`, no panic, every needle on stderr.
pub fn assert_refused(what: &str, o: &Output, code: i32, needles: &[&str]) {
    let err = stderr(o);
    assert!(!err.contains("panicked"), "{what}: panicked:\n{err}");
    assert_eq!(o.status.code(), Some(code), "{what}:\n{err}");
    for n in needles {
        assert!(err.contains(n), "{what}: stderr lacks {n:?}:\n{err}");
    }
}

/// `nppp train` flags of a seconds-long run: NdArray, tiny widths, 25-step
/// epochs, seed 3 (the data, output and length are the caller's).
pub const SMALL_TRAIN_FLAGS: &[&str] = &[
    "--backend",
    "ndarray",
    "--quiet",
    "--minutes",
    "0",
    "--batch",
    "16",
    "--k",
    "4",
    "--mask-batch",
    "64",
    "--encoder-width",
    "32",
    "--decoder-width",
    "32",
    "--mask-width",
    "32",
    "--latent-dim",
    "8",
    "--eval-rays",
    "16",
    "--holdout-every",
    "10",
    "--steps-per-epoch",
    "25",
    "--seed",
    "3",
];

/// CRC32 (IEEE), as the file formats and checkpoints use; bitwise, the
/// files the tests forge are small.
pub fn crc32(bytes: &[u8]) -> u32 {
    let mut c = !0u32;
    for &b in bytes {
        c ^= b as u32;
        for _ in 0..8 {
            c = if c & 1 != 0 {
                (c >> 1) ^ 0xEDB8_8320
            } else {
                c >> 1
            };
        }
    }
    !c
}
