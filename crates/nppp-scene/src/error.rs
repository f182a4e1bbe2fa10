//! The one error type of scene loading. Every variant carries the scene file
//! and, where the problem sits inside it, the key path (`instances[3].material`),
//! because docs/scene-format.md promises errors that point at the offending key or
//! file: a user with a 300-line scene must not have to guess.

use std::path::PathBuf;

/// Why a scene could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    /// The scene file itself could not be read. The I/O error is part of
    /// the message and deliberately not a `source()`: error reporters that
    /// print the chain (`anyhow`'s `{:#}`) would say it twice.
    #[error("{}: cannot read the scene file: {error}", file.display())]
    Read {
        file: PathBuf,
        error: std::io::Error,
    },
    /// The file is not JSON (syntax error, trailing characters, a number
    /// outside the f64 range such as `1e400`, a duplicated key). `key` is
    /// the path of the value being read when the parser gave up; empty when
    /// the error is at the top level.
    #[error(
        "{}:{line}:{column}: invalid JSON{}: {message}",
        file.display(),
        at_key(key)
    )]
    Json {
        file: PathBuf,
        line: usize,
        column: usize,
        key: String,
        message: String,
    },
    /// Well-formed JSON that breaks the contract (unknown or missing key,
    /// wrong type, value out of range, unknown name, degenerate geometry).
    #[error("{}: {key}: {message}", file.display())]
    Invalid {
        file: PathBuf,
        key: String,
        message: String,
    },
    /// An OBJ file named by `meshes.<name>.obj` is unreadable or malformed.
    /// `line` is the 1-based line of the OBJ file, when one is to blame.
    #[error(
        "{}: {key}: {}{}: {message}",
        file.display(),
        obj.display(),
        line.map(|l| format!(":{l}")).unwrap_or_default()
    )]
    Obj {
        file: PathBuf,
        key: String,
        obj: PathBuf,
        line: Option<usize>,
        message: String,
    },
}

fn at_key(key: &str) -> String {
    if key.is_empty() {
        String::new()
    } else {
        format!(" at {key}")
    }
}

impl SceneError {
    /// The key path the error is about (`camera.fov_y_deg`), if any; lets
    /// callers and tests check *where* without parsing the message.
    pub fn key_path(&self) -> Option<&str> {
        match self {
            SceneError::Read { .. } => None,
            SceneError::Json { key, .. } if key.is_empty() => None,
            SceneError::Json { key, .. }
            | SceneError::Invalid { key, .. }
            | SceneError::Obj { key, .. } => Some(key),
        }
    }

    /// The scene file the error is about.
    pub fn file(&self) -> &std::path::Path {
        match self {
            SceneError::Read { file, .. }
            | SceneError::Json { file, .. }
            | SceneError::Invalid { file, .. }
            | SceneError::Obj { file, .. } => file,
        }
    }
}
