//! A JSON value tree built by our own serde visitor instead of
//! `serde_json::Value`, for three reasons:
//! - objects keep the file's key order, so material and mesh indices follow
//!   the file rather than alphabetical order;
//! - a duplicated key is an error (serde_json silently keeps the last one,
//!   which would render something other than what one of the two lines says);
//! - when the parser fails (for example on `1e400`, which does not fit an
//!   f64), we still know the key path of the value it was reading.

use serde::de::{self, DeserializeSeed, MapAccess, SeqAccess, Visitor};
use std::cell::RefCell;
use std::collections::HashSet;
use std::fmt;

/// A JSON number as the parser saw it: integers stay exact (seeds are u64).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum Num {
    U(u64),
    I(i64),
    F(f64),
}

impl Num {
    pub(crate) fn as_f64(self) -> f64 {
        match self {
            Num::U(u) => u as f64,
            Num::I(i) => i as f64,
            Num::F(f) => f,
        }
    }
}

impl fmt::Display for Num {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Num::U(u) => write!(f, "{u}"),
            Num::I(i) => write!(f, "{i}"),
            // Scientific notation for the very large or small, so `1e39`
            // is not echoed back as forty digits.
            Num::F(x) if x.abs() >= 1e16 || (x.abs() < 1e-6 && *x != 0.0) => write!(f, "{x:e}"),
            Num::F(x) => write!(f, "{x}"),
        }
    }
}

#[derive(Clone, Debug, PartialEq)]
pub(crate) enum Json {
    Null,
    Bool(bool),
    Num(Num),
    Str(String),
    Arr(Vec<Json>),
    /// Keys in file order, no duplicates.
    Obj(Vec<(String, Json)>),
}

impl Json {
    /// "a string", "an array", ... for "expected X, found Y" messages.
    pub(crate) fn kind(&self) -> &'static str {
        match self {
            Json::Null => "null",
            Json::Bool(_) => "a boolean",
            Json::Num(_) => "a number",
            Json::Str(_) => "a string",
            Json::Arr(_) => "an array",
            Json::Obj(_) => "an object",
        }
    }
}

/// One step of a key path.
#[derive(Clone, Debug)]
enum Seg {
    Key(String),
    Index(usize),
}

/// Appends `.key` (or `["key"]` when the key is not a plain identifier, so a
/// material named `a.b` cannot be confused with a nested key).
pub(crate) fn join_key(base: &str, key: &str) -> String {
    let plain = !key.is_empty()
        && key
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-');
    if plain {
        if base.is_empty() {
            key.to_string()
        } else {
            format!("{base}.{key}")
        }
    } else {
        // serde_json's string escaping is exactly JSON's; it cannot fail for a String.
        let quoted = serde_json::to_string(key).unwrap_or_else(|_| format!("\"{key}\""));
        format!("{base}[{quoted}]")
    }
}

pub(crate) fn join_index(base: &str, i: usize) -> String {
    format!("{base}[{i}]")
}

fn render_path(segs: &[Seg]) -> String {
    let mut out = String::new();
    for s in segs {
        out = match s {
            Seg::Key(k) => join_key(&out, k),
            Seg::Index(i) => join_index(&out, *i),
        };
    }
    out
}

/// A parse failure with the position serde_json reports and the key path
/// of the value being read at that moment.
pub(crate) struct ParseFailure {
    pub line: usize,
    pub column: usize,
    pub key: String,
    pub message: String,
}

/// Parses a whole document (trailing non-whitespace is an error).
pub(crate) fn parse(text: &str) -> Result<Json, ParseFailure> {
    let path = RefCell::new(Vec::new());
    let mut de = serde_json::Deserializer::from_str(text);
    let result = ValueSeed { path: &path }
        .deserialize(&mut de)
        .and_then(|v| de.end().map(|()| v));
    result.map_err(|e| {
        let full = e.to_string();
        // serde_json appends " at line L column C"; we print those ourselves.
        let suffix = format!(" at line {} column {}", e.line(), e.column());
        let message = full.strip_suffix(&suffix).unwrap_or(&full).to_string();
        ParseFailure {
            line: e.line(),
            column: e.column(),
            key: render_path(&path.borrow()),
            message,
        }
    })
}

/// Carries the current key path down the recursion. Segments are popped only
/// on success, so after a failure the stack names where it happened.
struct ValueSeed<'p> {
    path: &'p RefCell<Vec<Seg>>,
}

impl<'de> DeserializeSeed<'de> for ValueSeed<'_> {
    type Value = Json;
    fn deserialize<D: de::Deserializer<'de>>(self, d: D) -> Result<Json, D::Error> {
        d.deserialize_any(self)
    }
}

impl<'de> Visitor<'de> for ValueSeed<'_> {
    type Value = Json;

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("any JSON value")
    }
    fn visit_unit<E>(self) -> Result<Json, E> {
        Ok(Json::Null)
    }
    fn visit_bool<E>(self, v: bool) -> Result<Json, E> {
        Ok(Json::Bool(v))
    }
    fn visit_u64<E>(self, v: u64) -> Result<Json, E> {
        Ok(Json::Num(Num::U(v)))
    }
    fn visit_i64<E>(self, v: i64) -> Result<Json, E> {
        Ok(Json::Num(if v >= 0 { Num::U(v as u64) } else { Num::I(v) }))
    }
    fn visit_f64<E>(self, v: f64) -> Result<Json, E> {
        Ok(Json::Num(Num::F(v)))
    }
    fn visit_str<E>(self, v: &str) -> Result<Json, E> {
        Ok(Json::Str(v.to_string()))
    }
    fn visit_string<E>(self, v: String) -> Result<Json, E> {
        Ok(Json::Str(v))
    }

    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Json, A::Error> {
        let mut out = Vec::new();
        loop {
            self.path.borrow_mut().push(Seg::Index(out.len()));
            match seq.next_element_seed(ValueSeed { path: self.path })? {
                Some(v) => out.push(v),
                None => {
                    self.path.borrow_mut().pop();
                    return Ok(Json::Arr(out));
                }
            }
            self.path.borrow_mut().pop();
        }
    }

    fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<Json, A::Error> {
        let mut out: Vec<(String, Json)> = Vec::new();
        // A set, not a scan of `out`: a scene may hold thousands of meshes.
        let mut seen = HashSet::new();
        while let Some(key) = map.next_key::<String>()? {
            self.path.borrow_mut().push(Seg::Key(key.clone()));
            if !seen.insert(key.clone()) {
                return Err(de::Error::custom(format!("duplicate key \"{key}\"")));
            }
            let v = map.next_value_seed(ValueSeed { path: self.path })?;
            self.path.borrow_mut().pop();
            out.push((key, v));
        }
        Ok(Json::Obj(out))
    }
}
