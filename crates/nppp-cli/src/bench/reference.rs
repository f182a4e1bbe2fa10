//! The reference each scene is measured against: plain path tracing at M
//! with many samples, rendered once as two independent halves (their
//! difference is the reference's own noise floor) and cached in
//! `<out>/<scene>/` with the settings it was made with (`ReferenceMeta`),
//! re-rendered only when those or the scene's content (`scene_hash`)
//! change (or with `--fresh-reference`). Also the scene-path helpers the
//! cache and the report name scenes by.

use super::harness::render_with;
use crate::bench_cmd::BenchArgs;
use anyhow::{Context, Result, ensure};
use nppp_render::metrics;
use nppp_render::{Image, RenderScene, image_io};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

#[derive(Serialize, Deserialize, Debug, Clone, PartialEq)]
pub(super) struct ReferenceMeta {
    pub(super) format: u32,
    pub(super) scene: String,
    pub(super) scene_hash: String,
    pub(super) width: u32,
    pub(super) height: u32,
    pub(super) spp: u32,
    pub(super) max_bounces: u32,
    pub(super) seeds: [u64; 2],
    pub(super) renderer: String,
    /// Not part of the match: how long it took and how noisy it is.
    pub(super) seconds: f64,
    pub(super) noise_floor_rel_mse: f64,
}

impl ReferenceMeta {
    fn same_settings(&self, o: &ReferenceMeta) -> bool {
        self.format == o.format
            && self.scene_hash == o.scene_hash
            && self.width == o.width
            && self.height == o.height
            && self.spp == o.spp
            && self.max_bounces == o.max_bounces
            && self.seeds == o.seeds
            && self.renderer == o.renderer
    }
}

pub(super) fn resolve_scene(dir: &Path, name: &str) -> Result<PathBuf> {
    ensure!(
        !name.trim().is_empty(),
        "--scenes: an empty scene name (give names or paths separated by commas, e.g. \
         cornell-box,room)"
    );
    let p = if name.ends_with(".json") || name.contains('/') {
        PathBuf::from(name)
    } else {
        dir.join(format!("{name}.json"))
    };
    ensure!(
        p.exists(),
        "{}: scene not found (run nppp bench from the repository root, or pass --scenes-dir or a path in --scenes)",
        p.display()
    );
    // There, but a folder or a device: said as render says it.
    nppp_files::check_regular(&p).with_context(|| format!("{}: the scene file", p.display()))?;
    Ok(p)
}

/// `data/scenes/../../models/x` -> `models/x`, lexically (for messages and
/// the report; the file system is not consulted).
pub(super) fn tidy_path(p: &Path) -> PathBuf {
    use std::path::Component;
    let mut out: Vec<Component> = Vec::new();
    for c in p.components() {
        match c {
            Component::CurDir => {}
            Component::ParentDir if matches!(out.last(), Some(Component::Normal(_))) => {
                out.pop();
            }
            c => out.push(c),
        }
    }
    if out.is_empty() {
        PathBuf::from(".")
    } else {
        out.iter().collect()
    }
}

pub(super) fn scene_name(path: &Path) -> String {
    path.file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "scene".into())
}

/// Hash of everything a plain path-traced reference depends on in the scene:
/// the file itself and the content of every mesh (OBJ files included).
pub(super) fn scene_hash(path: &Path, scene: &nppp_scene::Scene) -> Result<String> {
    let bytes =
        nppp_files::read_regular(path).with_context(|| format!("reading {}", path.display()))?;
    let mut h = nppp_scene::hash::Fnv1a::new();
    h.bytes(&bytes);
    for m in &scene.meshes {
        h.u64(nppp_scene::mesh_content_hash(m));
    }
    for m in &scene.materials {
        h.u64(nppp_scene::material_content_hash(m));
    }
    Ok(format!("{:016x}", h.finish()))
}

pub(super) fn load_or_render_reference(
    a: &BenchArgs,
    rs: &RenderScene,
    dir: &Path,
    name: &str,
    want: &ReferenceMeta,
) -> Result<(Image, ReferenceMeta, bool)> {
    let exr = dir.join("reference.exr");
    let json = dir.join("reference.json");
    if !a.fresh_reference && exr.is_file() && json.is_file() {
        let text = nppp_files::read_regular_to_string(&json)
            .with_context(|| format!("reading {}", json.display()))?;
        // A cache that cannot be used as it is (other settings, a damaged
        // or edited file) is rendered again, saying why: it is ours to
        // remake, and one bad file must not end a run of many scenes.
        let why = match serde_json::from_str::<ReferenceMeta>(&text) {
            Ok(have) if !have.same_settings(want) => {
                format!("{} was made with other settings", json.display())
            }
            Ok(have)
                if !(have.noise_floor_rel_mse.is_finite()
                    && have.noise_floor_rel_mse >= 0.0
                    && have.seconds.is_finite()
                    && have.seconds >= 0.0) =>
            {
                format!(
                    "{} records an impossible noise floor or time",
                    json.display()
                )
            }
            Ok(have) => match image_io::read_exr(&exr) {
                Err(e) => format!("the cached {} is unreadable ({e})", exr.display()),
                Ok(img) if img.width != want.width || img.height != want.height => {
                    format!("{} has the wrong size", exr.display())
                }
                Ok(img) if img.pixels.iter().flatten().any(|v| !v.is_finite()) => {
                    format!("{} holds NaN or infinite pixels", exr.display())
                }
                Ok(img) => {
                    nppp_files::note!(
                        "[{name}] reference: cached {} ({} spp, settings match)",
                        exr.display(),
                        have.spp
                    );
                    return Ok((img, have, true));
                }
            },
            Err(e) => format!("{} is unreadable ({e})", json.display()),
        };
        nppp_files::note!("[{name}] reference: {why}; re-rendering");
    }
    // Two independent halves: their difference estimates the reference's own noise.
    let rs_ref = rs;
    let half = want.spp / 2;
    nppp_files::note!(
        "[{name}] reference: rendering PT M={} at {} spp (two halves of {half})...",
        want.max_bounces,
        want.spp
    );
    let (ia, sa) = render_with(rs_ref, half, want.max_bounces, want.seeds[0]);
    let (ib, sb) = render_with(rs_ref, want.spp - half, want.max_bounces, want.seeds[1]);
    let wa = half as f64 / want.spp as f64;
    let mut img = Image::new(ia.width, ia.height);
    let mut floor = 0.0f64;
    for ((o, pa), pb) in img.pixels.iter_mut().zip(&ia.pixels).zip(&ib.pixels) {
        for c in 0..3 {
            let (x, y) = (pa[c] as f64, pb[c] as f64);
            let r = wa * x + (1.0 - wa) * y;
            o[c] = r as f32;
            // Var(mean of two halves) ~= (x - y)^2 / 4 for equal halves.
            floor += (x - y) * (x - y) / 4.0 / (r * r + metrics::REL_EPS);
        }
    }
    floor /= (3 * img.pixels.len().max(1)) as f64;
    let mut meta = want.clone();
    meta.seconds = sa.seconds + sb.seconds;
    meta.noise_floor_rel_mse = floor;
    // The settings file says which image the EXR is, so it goes first and
    // comes back last: a run that failed (or was killed) after writing the
    // EXR left the old settings beside the new image, and the next run
    // measured against an M = 1 reference "cached, settings match".
    match std::fs::remove_file(&json) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
            return Err(e).with_context(|| format!("removing the stale {}", json.display()));
        }
        _ => {}
    }
    image_io::write_exr(&img, &exr).with_context(|| format!("writing {}", exr.display()))?;
    let text = serde_json::to_string_pretty(&meta).context("serializing the reference settings")?;
    image_io::write_text(&json, &(text + "\n"))
        .with_context(|| format!("writing {}", json.display()))?;
    let png = dir.join("reference.png");
    image_io::write_png(&img, &png).with_context(|| format!("writing {}", png.display()))?;
    nppp_files::note!(
        "[{name}] reference: {:.1} s, noise floor relMSE {:.3e}",
        meta.seconds,
        floor
    );
    Ok((img, meta, false))
}
