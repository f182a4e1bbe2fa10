//! Render parts: one machine's share of a render (a range of every pixel's
//! samples) as exact per-pixel sums, and their merge into the whole film.
//!
//! A render split by sample range merges bit for bit into the render of the
//! whole range because every sample owns its random stream, keyed by (seed,
//! pixel, sample), and the film's sums are exact integers ([`crate::film`]).
//! A part records what it is a part of (renderer, scene content, image size,
//! spp, seed, M and the estimator settings, the estimator files' hashes), so
//! [`merge_parts`] can refuse parts of different renders, and which samples
//! it holds, so it can refuse a merge with a range missing or twice.
//!
//! File layout (little-endian; docs/shards.md):
//! magic `NPPPRPT\0`, u32 version, u32 header length, header JSON
//! ([`RenderPartHeader`]), u32 CRC-32 of version, length and JSON; then u64
//! payload length as stored, u64 raw length, the payload (deflate), u32
//! CRC-32 of the stored payload, `PEND`. The raw payload is columns over the
//! pixels in row-major order: for each channel r, g, b and each limb of
//! its [`crate::film::ExactSum`] (`EXACT_SUM_LIMBS`, 5) a u64 per pixel, then the valid counts (u32 per pixel),
//! then the dropped counts (u32 per pixel).

use crate::film::{EXACT_SUM_LIMBS, PixelSum};
use nppp_estimator::shard::{CoverError, check_cover};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::io::Read;
use std::path::{Path, PathBuf};
use thiserror::Error;

pub const RENDER_PART_MAGIC: [u8; 8] = *b"NPPPRPT\0";
/// 2: films of five limbs in units of 2^-149 (version 1: four, 2^-95).
pub const RENDER_PART_VERSION: u32 = 2;
const END_MAGIC: [u8; 4] = *b"PEND";
const MAX_HEADER_LEN: u32 = 1 << 20;
/// Raw bytes per pixel: 3 channels x 5 limbs x 8, valid and dropped counts.
pub const PART_BYTES_PER_PIXEL: u64 = 3 * EXACT_SUM_LIMBS as u64 * 8 + 4 + 4;
/// What merging parts holds at its peak, per pixel: the merged film, and
/// of the part being read its raw columns with either its compressed bytes
/// (at most 1/8 over raw) or its decoded film; then the image and its EXR
/// rows (f32 RGB, twice). Measured with four-limb films: 320 bytes a pixel at
/// 4096 x 4096 with two parts (this formula gave 349 then); the 220 once
/// counted let a merge pass the check and abort.
pub const MERGE_BYTES_PER_PIXEL: u64 = 3 * PART_BYTES_PER_PIXEL + PART_BYTES_PER_PIXEL / 8 + 2 * 12;

/// What a part belongs to and which samples it holds.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RenderPartHeader {
    /// The program that rendered it ([`renderer_id`]): parts of one image
    /// must come from one build of one version.
    pub renderer: String,
    /// The scene file as named on the rendering machine (for messages only:
    /// the same scene may sit under another path on another machine).
    pub scene: String,
    /// [`nppp_scene::scene_content_hash`] in hex.
    pub scene_hash: String,
    pub width: u32,
    pub height: u32,
    pub spp: u32,
    pub seed: u64,
    pub max_bounces: u32,
    /// First sample of every pixel in this part and one past its last, of `0..spp`.
    pub samples: [u32; 2],
    /// Everything else the image depends on, by name: estimator mode, P,
    /// entry options, decoder, each estimator file's hash, `auto`'s decision.
    pub settings: BTreeMap<String, String>,
    /// Time this part took (pilot included), for the merged report.
    pub seconds: f64,
}

/// The renderer a part came from: the version and the instruction-set
/// features the binary was compiled for (a `target-cpu=native` build on
/// another CPU is another build).
pub fn renderer_id() -> String {
    let features: Vec<&str> = [
        ("sse4.1", cfg!(target_feature = "sse4.1")),
        ("avx2", cfg!(target_feature = "avx2")),
        ("fma", cfg!(target_feature = "fma")),
        ("avx512f", cfg!(target_feature = "avx512f")),
        ("neon", cfg!(target_feature = "neon")),
    ]
    .into_iter()
    .filter_map(|(name, on)| on.then_some(name))
    .collect();
    format!(
        "nppp {} ({}{}{})",
        env!("CARGO_PKG_VERSION"),
        std::env::consts::ARCH,
        if features.is_empty() { "" } else { " " },
        features.join("+")
    )
}

#[derive(Debug, Error)]
pub enum RenderPartError {
    #[error("{}: {msg}", path.display())]
    File { path: PathBuf, msg: String },
    #[error("{0}")]
    Merge(String),
}

fn file_err(path: &Path, msg: impl Into<String>) -> RenderPartError {
    RenderPartError::File {
        path: path.into(),
        msg: msg.into(),
    }
}

/// Writes a part atomically (a temporary file renamed into place).
pub fn write_part(
    path: &Path,
    header: &RenderPartHeader,
    film: &[PixelSum],
) -> Result<(), RenderPartError> {
    if film.len() as u64 != header.width as u64 * header.height as u64 {
        return Err(file_err(
            path,
            format!(
                "internal: film of {} pixels for a {}x{} image",
                film.len(),
                header.width,
                header.height
            ),
        ));
    }
    let json = serde_json::to_vec(header).map_err(|e| file_err(path, e.to_string()))?;
    let mut raw = Vec::with_capacity(film.len() * PART_BYTES_PER_PIXEL as usize);
    for c in 0..3 {
        for l in 0..EXACT_SUM_LIMBS {
            for p in film {
                raw.extend_from_slice(&p.sum[c].0[l].to_le_bytes());
            }
        }
    }
    for p in film {
        raw.extend_from_slice(&p.valid.to_le_bytes());
    }
    for p in film {
        raw.extend_from_slice(&p.dropped.to_le_bytes());
    }
    let stored = miniz_oxide::deflate::compress_to_vec(&raw, 1);
    let mut out = Vec::with_capacity(stored.len() + json.len() + 64);
    out.extend_from_slice(&RENDER_PART_MAGIC);
    out.extend_from_slice(&RENDER_PART_VERSION.to_le_bytes());
    out.extend_from_slice(&(json.len() as u32).to_le_bytes());
    out.extend_from_slice(&json);
    let crc = crc32fast::hash(&out[8..]);
    out.extend_from_slice(&crc.to_le_bytes());
    out.extend_from_slice(&(stored.len() as u64).to_le_bytes());
    out.extend_from_slice(&(raw.len() as u64).to_le_bytes());
    out.extend_from_slice(&stored);
    out.extend_from_slice(&crc32fast::hash(&stored).to_le_bytes());
    out.extend_from_slice(&END_MAGIC);
    nppp_files::create_parent(path)
        .and_then(|_| nppp_files::write_atomic(path, &out))
        .map_err(|e| file_err(path, format!("cannot write: {e}")))
}

fn read_exact(
    f: &mut impl Read,
    n: usize,
    path: &Path,
    what: &str,
) -> Result<Vec<u8>, RenderPartError> {
    let mut buf = Vec::new();
    f.take(n as u64)
        .read_to_end(&mut buf)
        .map_err(|e| file_err(path, format!("cannot read: {e}")))?;
    if buf.len() != n {
        return Err(file_err(
            path,
            format!("ends inside its {what}: the file is truncated"),
        ));
    }
    Ok(buf)
}

fn u32_at(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]])
}

fn u64_at(b: &[u8], at: usize) -> u64 {
    let mut x = [0u8; 8];
    x.copy_from_slice(&b[at..at + 8]);
    u64::from_le_bytes(x)
}

fn read_header_from(f: &mut impl Read, path: &Path) -> Result<RenderPartHeader, RenderPartError> {
    let mut prefix = Vec::new();
    f.take(16)
        .read_to_end(&mut prefix)
        .map_err(|e| file_err(path, format!("cannot read: {e}")))?;
    if prefix.len() < 8 || prefix[..8] != RENDER_PART_MAGIC {
        return Err(file_err(
            path,
            "not an nppp render part (written by `nppp render --shard I/K --out PART.nppr`)",
        ));
    }
    if prefix.len() < 16 {
        return Err(file_err(
            path,
            "ends inside its header: the file is truncated",
        ));
    }
    let version = u32_at(&prefix, 8);
    if version != RENDER_PART_VERSION {
        return Err(file_err(
            path,
            format!(
                "render part version {version}; this build reads version {RENDER_PART_VERSION}: \
                 render the shard again with this build (`nppp render SCENE --shard I/K --out PART.nppr`)"
            ),
        ));
    }
    let len = u32_at(&prefix, 12);
    if len > MAX_HEADER_LEN {
        return Err(file_err(
            path,
            format!("header of {len} bytes: the file is damaged"),
        ));
    }
    let json = read_exact(f, len as usize, path, "header")?;
    let crc = read_exact(f, 4, path, "header")?;
    let mut h = crc32fast::Hasher::new();
    h.update(&prefix[8..16]);
    h.update(&json);
    if h.finalize() != u32_at(&crc, 0) {
        return Err(file_err(
            path,
            "header checksum mismatch: the file is damaged",
        ));
    }
    let header: RenderPartHeader =
        serde_json::from_slice(&json).map_err(|e| file_err(path, format!("header: {e}")))?;
    let [a, b] = header.samples;
    if !(a < b && b <= header.spp) || header.width == 0 || header.height == 0 {
        return Err(file_err(
            path,
            format!(
                "header: samples {a}..{b} of {} spp at {}x{} is not a part of a render",
                header.spp, header.width, header.height
            ),
        ));
    }
    Ok(header)
}

fn open(path: &Path) -> Result<std::io::BufReader<std::fs::File>, RenderPartError> {
    let f =
        nppp_files::open_regular(path).map_err(|e| file_err(path, format!("cannot open: {e}")))?;
    Ok(std::io::BufReader::new(f))
}

/// A part's header alone (cheap: the film is not read).
pub fn read_part_header(path: &Path) -> Result<RenderPartHeader, RenderPartError> {
    read_header_from(&mut open(path)?, path)
}

/// A part: its header and its film (every pixel's sums), checked.
pub fn read_part(path: &Path) -> Result<(RenderPartHeader, Vec<PixelSum>), RenderPartError> {
    let mut f = open(path)?;
    let header = read_header_from(&mut f, path)?;
    let n = header.width as u64 * header.height as u64;
    let want_raw = n * PART_BYTES_PER_PIXEL;
    let lens = read_exact(&mut f, 16, path, "film")?;
    let (stored_len, raw_len) = (u64_at(&lens, 0), u64_at(&lens, 8));
    if raw_len != want_raw || stored_len > raw_len + raw_len / 8 + 1024 {
        return Err(file_err(
            path,
            format!(
                "film of {raw_len} bytes ({stored_len} stored) for a {}x{} image (needs {want_raw}): the file is damaged",
                header.width, header.height
            ),
        ));
    }
    let stored = read_exact(&mut f, stored_len as usize, path, "film")?;
    let tail = read_exact(&mut f, 8, path, "film")?;
    if tail[4..] != END_MAGIC || crc32fast::hash(&stored) != u32_at(&tail, 0) {
        return Err(file_err(
            path,
            "film checksum mismatch: the file is damaged",
        ));
    }
    // Nothing after the end marker: an appended byte is damage too (an
    // estimator file with one is refused the same way).
    let mut extra = [0u8; 1];
    if std::io::Read::read(&mut f, &mut extra).map_err(|e| file_err(path, e.to_string()))? != 0 {
        return Err(file_err(
            path,
            "bytes after the end marker: the file is damaged",
        ));
    }
    let raw = miniz_oxide::inflate::decompress_to_vec_with_limit(&stored, raw_len as usize)
        .map_err(|e| {
            file_err(
                path,
                format!("film cannot be inflated ({e:?}): the file is damaged"),
            )
        })?;
    if raw.len() as u64 != raw_len {
        return Err(file_err(
            path,
            "film inflates to the wrong size: the file is damaged",
        ));
    }
    // The compressed bytes are done with: not held beside the film built
    // next (MERGE_BYTES_PER_PIXEL counts one or the other).
    drop(stored);
    let n = n as usize;
    let mut film = vec![PixelSum::default(); n];
    for c in 0..3 {
        for l in 0..EXACT_SUM_LIMBS {
            let col = (c * EXACT_SUM_LIMBS + l) * n * 8;
            for (i, p) in film.iter_mut().enumerate() {
                p.sum[c].0[l] = u64_at(&raw, col + 8 * i);
            }
        }
    }
    let counts = 3 * EXACT_SUM_LIMBS * 8 * n;
    let per_pixel = header.samples[1] - header.samples[0];
    let damaged = |i: usize, what: String| {
        file_err(
            path,
            format!(
                "pixel ({}, {}) {what}: the file is damaged",
                i as u32 % header.width,
                i as u32 / header.width
            ),
        )
    };
    for (i, p) in film.iter_mut().enumerate() {
        p.valid = u32_at(&raw, counts + 4 * i);
        p.dropped = u32_at(&raw, counts + 4 * n + 4 * i);
        let count = u64::from(p.valid) + u64::from(p.dropped);
        if count != u64::from(per_pixel) {
            let what = format!("counts {count} samples, the part holds {per_pixel} per pixel");
            return Err(damaged(i, what));
        }
        // Radiance samples are finite and non-negative: a sum below 0 or
        // beyond what its samples could add up to would make the merged
        // image negative or infinite.
        let most = f64::from(p.valid) * f64::from(f32::MAX);
        if let Some(c) = (0..3).find(|&c| !(0.0..=most).contains(&p.sum[c].to_f64())) {
            let what = format!(
                "channel {c} sums to {:e} over {} samples, which no render makes",
                p.sum[c].to_f64(),
                p.valid
            );
            return Err(damaged(i, what));
        }
    }
    Ok((header, film))
}

/// The whole render put together from its parts.
#[derive(Debug)]
pub struct MergedRender {
    /// The parts' common header, with `samples` the whole `0..spp` and
    /// `seconds` the parts' total.
    pub header: RenderPartHeader,
    pub film: Vec<PixelSum>,
}

impl MergedRender {
    /// The image: every pixel's mean, as [`crate::render()`] computes it.
    pub fn image(&self) -> crate::Image {
        crate::film::film_image(self.header.width, self.header.height, &self.film)
    }

    pub fn dropped_samples(&self) -> u64 {
        self.film.iter().map(|p| u64::from(p.dropped)).sum()
    }
}

/// The first way in which `b` belongs to another render than `a`, or None.
fn mismatch(a: &RenderPartHeader, b: &RenderPartHeader) -> Option<String> {
    let fields: [(&str, String, String); 6] = [
        ("renderer", a.renderer.clone(), b.renderer.clone()),
        // Before the scene's hash, which covers the image size too: parts
        // of another --width are told so.
        (
            "image size",
            format!("{}x{}", a.width, a.height),
            format!("{}x{}", b.width, b.height),
        ),
        (
            "scene content (hash)",
            a.scene_hash.clone(),
            b.scene_hash.clone(),
        ),
        ("spp", a.spp.to_string(), b.spp.to_string()),
        ("seed", a.seed.to_string(), b.seed.to_string()),
        (
            "M (max bounces)",
            a.max_bounces.to_string(),
            b.max_bounces.to_string(),
        ),
    ];
    for (name, x, y) in fields {
        if x != y {
            return Some(format!("{name} {y} where the first part has {x}"));
        }
    }
    let keys: std::collections::BTreeSet<&String> =
        a.settings.keys().chain(b.settings.keys()).collect();
    // `estimators` first: the other settings follow from it (`auto`'s
    // decision exists only in an auto render).
    let mut keys: Vec<&String> = keys.into_iter().collect();
    keys.sort_by_key(|k| k.as_str() != "estimators");
    for k in keys {
        let (x, y) = (a.settings.get(k), b.settings.get(k));
        if x != y {
            let show = |v: Option<&String>| v.map_or("(none)".to_string(), |s| s.clone());
            return Some(format!(
                "{k} = {} where the first part has {}",
                show(y),
                show(x)
            ));
        }
    }
    None
}

/// Checks that `paths` are parts of one render covering each of its samples
/// exactly once (in any order), then adds their films. Parts are read one at
/// a time: memory is two films.
pub fn merge_parts(paths: &[PathBuf]) -> Result<MergedRender, RenderPartError> {
    if paths.is_empty() {
        return Err(RenderPartError::Merge("no parts to merge".into()));
    }
    let headers = paths
        .iter()
        .map(|p| read_part_header(p))
        .collect::<Result<Vec<_>, _>>()?;
    let first = &headers[0];
    for (p, h) in paths.iter().zip(&headers).skip(1) {
        if let Some(m) = mismatch(first, h) {
            return Err(RenderPartError::Merge(format!(
                "{} is not a part of the render {} is a part of: {m}",
                p.display(),
                paths[0].display()
            )));
        }
    }
    let ranges: Vec<std::ops::Range<u64>> = headers
        .iter()
        .map(|h| u64::from(h.samples[0])..u64::from(h.samples[1]))
        .collect();
    match check_cover(&ranges, u64::from(first.spp)) {
        Ok(()) => {}
        Err(CoverError::Gap(g)) => {
            return Err(RenderPartError::Merge(format!(
                "samples {}..{} of the {} are in no part: render them with --shard or --samples \
                 (or name the missing part)",
                g.start, g.end, first.spp
            )));
        }
        Err(CoverError::Overlap { a, b, overlap }) => {
            return Err(RenderPartError::Merge(format!(
                "{} (samples {}..{}) and {} (samples {}..{}) overlap: samples {}..{} would count twice",
                paths[a].display(),
                ranges[a].start,
                ranges[a].end,
                paths[b].display(),
                ranges[b].start,
                ranges[b].end,
                overlap.start,
                overlap.end
            )));
        }
    }
    let film = add_films(paths, &headers)?;
    let mut header = first.clone();
    header.samples = [0, first.spp];
    header.seconds = headers.iter().map(|h| h.seconds).sum();
    Ok(MergedRender { header, film })
}

/// The sum of the films of `paths`, each of which must still hold the
/// header `headers` checked.
fn add_films(
    paths: &[PathBuf],
    headers: &[RenderPartHeader],
) -> Result<Vec<PixelSum>, RenderPartError> {
    let first = &headers[0];
    let mut film: Vec<PixelSum> = Vec::new();
    for (p, checked) in paths.iter().zip(headers) {
        let (h, f) = read_part(p)?;
        // The file read now must be the one checked above: a part replaced
        // in between (a shard job run again) was merged unchecked, and one
        // of a smaller image filled only the top rows.
        if &h != checked || f.len() != first.width as usize * first.height as usize {
            return Err(RenderPartError::Merge(format!(
                "{} changed while merge ran (another process wrote it); run merge again once \
                 the parts are final",
                p.display()
            )));
        }
        if film.is_empty() {
            film = f;
        } else {
            for (a, b) in film.iter_mut().zip(&f) {
                a.merge(b);
            }
        }
    }
    Ok(film)
}

/// The samples of shard `index` of `count` over `0..spp`: contiguous ranges
/// whose lengths differ by at most one, in order.
pub fn shard_samples(index: u32, count: u32, spp: u32) -> std::ops::Range<u32> {
    let at = |i: u32| (u64::from(i) * u64::from(spp) / u64::from(count)) as u32;
    at(index)..at(index + 1)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header() -> RenderPartHeader {
        RenderPartHeader {
            renderer: renderer_id(),
            scene: "s.json".into(),
            scene_hash: "0".into(),
            width: 2,
            height: 1,
            spp: 2,
            seed: 0,
            max_bounces: 5,
            samples: [0, 2],
            settings: BTreeMap::new(),
            seconds: 0.0,
        }
    }

    fn film_of(sums: [f32; 2]) -> Vec<PixelSum> {
        sums.map(|x| {
            let mut p = PixelSum::default();
            p.add(glam::Vec3::splat(x));
            p.add(glam::Vec3::ZERO);
            p
        })
        .to_vec()
    }

    /// A part whose sums no render could make (a forged or damaged file
    /// with valid checksums) is refused: merged, it made the image
    /// infinite or negative.
    #[test]
    fn sums_no_render_makes_are_refused() {
        let dir = std::env::temp_dir().join(format!("nppp-part-sums-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("p.nppr");
        write_part(&path, &header(), &film_of([1.5, 0.0])).unwrap();
        let (_, film) = read_part(&path).unwrap();
        assert_eq!(film[0].mean(), [0.75; 3]);

        let mut negative = film_of([1.0, 0.0]);
        negative[1].sum[2].add_f32(-3.0);
        let mut beyond = film_of([f32::MAX, f32::MAX]);
        beyond[0].sum[0].add_f32(f32::MAX);
        beyond[0].sum[0].add_f32(f32::MAX);
        for (film, needle) in [
            (negative, "pixel (1, 0) channel 2"),
            (beyond, "pixel (0, 0) channel 0"),
        ] {
            write_part(&path, &header(), &film).unwrap();
            let err = read_part(&path).unwrap_err().to_string();
            assert!(err.contains(needle) && err.contains("damaged"), "{err}");
        }
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A byte appended to a valid part merged without complaint (an
    /// estimator file with one is refused): both are damage.
    #[test]
    fn bytes_after_the_end_marker_are_refused() {
        let dir = std::env::temp_dir().join(format!("nppp-part-tail-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("p.nppr");
        write_part(&path, &header(), &film_of([1.5, 0.0])).unwrap();
        assert!(read_part(&path).is_ok());
        let mut bytes = std::fs::read(&path).unwrap();
        bytes.push(0);
        std::fs::write(&path, &bytes).unwrap();
        let err = read_part(&path).unwrap_err().to_string();
        assert!(err.contains("after the end marker"), "{err}");
        let _ = std::fs::remove_dir_all(&dir);
    }
    /// A part replaced between merge's check of the headers and its
    /// reading of the films (a shard job run again) is refused, not merged
    /// unchecked: a smaller image's part filled only the top rows.
    #[test]
    fn a_part_replaced_after_its_check_is_refused() {
        let dir = std::env::temp_dir().join(format!("nppp-part-swap-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let (a, b) = (dir.join("a.nppr"), dir.join("b.nppr"));
        // Two samples a pixel each, as `film_of` makes.
        let mut first = header();
        first.spp = 4;
        let mut second = first.clone();
        second.samples = [2, 4];
        write_part(&a, &first, &film_of([1.0, 0.0])).unwrap();
        write_part(&b, &second, &film_of([2.0, 0.0])).unwrap();
        let paths = [a.clone(), b.clone()];
        assert!(merge_parts(&paths).is_ok());
        let checked = [first.clone(), second.clone()];
        assert!(add_films(&paths, &checked).is_ok());
        // b rewritten after the check: another seed, or a smaller image.
        let mut reseeded = second.clone();
        reseeded.seed = 9;
        let mut small = second.clone();
        small.width = 1;
        for (h, film) in [
            (reseeded, film_of([2.0, 0.0])),
            (small, film_of([2.0, 0.0])[..1].to_vec()),
        ] {
            write_part(&b, &h, &film).unwrap();
            let err = add_films(&paths, &checked).unwrap_err().to_string();
            assert!(err.contains("b.nppr changed while merge ran"), "{err}");
        }
        let _ = std::fs::remove_dir_all(&dir);
    }
}
