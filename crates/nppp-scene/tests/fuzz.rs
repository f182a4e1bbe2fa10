//! Whatever the input, loading returns an error and never panics.

mod common;

use common::{FILE, base, parse};
use nppp_scene::parse_scene;
use proptest::prelude::*;
use serde_json::{Value, json};
use std::path::Path;

fn any_json() -> impl Strategy<Value = Value> {
    let leaf = prop_oneof![
        Just(Value::Null),
        any::<bool>().prop_map(Value::Bool),
        any::<i64>().prop_map(|i| json!(i)),
        any::<u64>().prop_map(|u| json!(u)),
        prop::num::f64::NORMAL.prop_map(|f| json!(f)),
        prop_oneof![
            Just(0.0),
            Just(-0.0),
            Just(1e-45),
            Just(3.5e38),
            Just(1e300),
            Just(180.0),
            Just(8.0),
            Just(9.0)
        ]
        .prop_map(|f| json!(f)),
        "[a-z_\\.]{0,8}".prop_map(Value::String),
        Just(json!("meshes/missing.obj")),
    ];
    leaf.prop_recursive(4, 32, 6, |inner| {
        prop_oneof![
            prop::collection::vec(inner.clone(), 0..6).prop_map(Value::Array),
            prop::collection::vec(("[a-z_]{1,6}", inner), 0..6)
                .prop_map(|kv| Value::Object(kv.into_iter().collect())),
        ]
    })
}

/// Every path into the base scene, so that structure-aware mutations hit
/// every validator, not just the top-level type check.
fn paths(v: &Value, prefix: Vec<String>, out: &mut Vec<Vec<String>>) {
    out.push(prefix.clone());
    match v {
        Value::Object(m) => {
            for (k, c) in m {
                let mut p = prefix.clone();
                p.push(k.clone());
                paths(c, p, out);
            }
        }
        Value::Array(a) => {
            for (i, c) in a.iter().enumerate() {
                let mut p = prefix.clone();
                p.push(i.to_string());
                paths(c, p, out);
            }
        }
        _ => {}
    }
}

fn slot<'a>(v: &'a mut Value, path: &[String]) -> &'a mut Value {
    let mut cur = v;
    for k in path {
        cur = match (k.parse::<usize>(), cur.is_array()) {
            (Ok(i), true) => &mut cur[i],
            _ => &mut cur[k.as_str()],
        };
    }
    cur
}

#[test]
fn every_truncation_is_an_error_not_a_panic() {
    let text = serde_json::to_string_pretty(&base()).expect("serialize");
    for end in 0..text.len() {
        if text.is_char_boundary(end) {
            assert!(
                parse_scene(&text[..end], Path::new(FILE)).is_err(),
                "prefix of {end} bytes loaded"
            );
        }
    }
    parse_scene(&text, Path::new(FILE)).expect("the whole text loads");
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 512, ..ProptestConfig::default() })]

    #[test]
    fn garbage_text_never_panics(text in ".{0,200}") {
        let _ = parse_scene(&text, Path::new(FILE));
    }

    #[test]
    fn json_like_garbage_never_panics(text in "[\\[\\]{}\":,0-9a-z. eE+-]{0,200}") {
        let _ = parse_scene(&text, Path::new(FILE));
    }

    #[test]
    fn byte_edits_never_panic(edits in prop::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 1..6)) {
        let mut bytes = base().to_string().into_bytes();
        for (at, b) in edits {
            let i = at.index(bytes.len());
            bytes[i] = b;
        }
        let text = String::from_utf8_lossy(&bytes);
        let _ = parse_scene(&text, Path::new(FILE));
    }

    #[test]
    fn any_value_anywhere_never_panics(which in any::<prop::sample::Index>(), value in any_json()) {
        let mut v = base();
        let mut all = Vec::new();
        paths(&v, Vec::new(), &mut all);
        let path = &all[which.index(all.len())];
        *slot(&mut v, path) = value;
        if let Err(e) = parse(&v) {
            // Errors always say where.
            prop_assert!(e.to_string().contains(FILE), "{}", e);
        }
    }
}
