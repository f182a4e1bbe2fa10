//! The baked estimator and its `.nppp` file (layout: `FORMAT.md`).
//!
//! A baked estimator is everything the renderer needs for one
//! (mesh, material): the quantized latent and mask grids, the decoder and the
//! output transform, plus what it was trained for so that attaching it to the
//! wrong object can be detected, and optionally the vertex head that
//! returns a skipped vertex for next-event estimation. Loading checks every size against the file
//! length before allocating anything, so a damaged or hostile file gives a
//! clear error, never a panic or a huge allocation.

use crate::exit::{EXIT_FEATURES, ExitTransform};
use crate::grid::{self, GridError, MIN_RES, QuantizedGrid};
use crate::mlp::{Dense, Mlp};
use crate::quant;
use crate::vertex::{VERTEX_FEATURES, VertexTransform};
use nppp_geom::{BoundingSphere, Vec3};
use serde::{Deserialize, Serialize};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use thiserror::Error;

pub const ESTIMATOR_MAGIC: [u8; 8] = *b"NPPPEST\0";
/// Version 2 added the optional vertex head (`vertex_decoder` in the
/// header, its transform and layers after the decoder's); version 1 files
/// (no vertex head) are still read.
pub const ESTIMATOR_VERSION: u32 = 2;
/// The oldest version this build reads.
pub const ESTIMATOR_VERSION_MIN: u32 = 1;
/// Magic, version, checksum: the part of the file the CRC does not cover.
const PREFIX_LEN: usize = 16;
/// A header is a few hundred bytes of JSON; anything near this is not ours.
const MAX_HEADER_LEN: usize = 1 << 20;
const MAX_DECODER_LAYERS: usize = 64;
const MAX_LAYER_WIDTH: usize = 1 << 16;
/// Mask logits are clamped before quantization: only their sign and the
/// neighbourhood of 0 matter, and a few saturated nodes at +-30 would
/// otherwise waste most of the 256 levels and blur the hit boundary.
pub const MASK_LOGIT_CLAMP: f32 = 8.0;
/// Bit depth of the mask grid built by [`BakedEstimator::from_f32_grids`].
pub const DEFAULT_MASK_BITS: u8 = 8;

#[derive(Debug, Error)]
pub enum EstimatorFileError {
    // `err`, not `source`: the reason is part of this message, and an error
    // chain printer (anyhow's `{:#}`) would print it a second time.
    #[error("{}: {err}", path.display())]
    Io { path: PathBuf, err: std::io::Error },
    #[error("{}: not an nppp estimator file (wrong magic; expected \"NPPPEST\\0\")", path.display())]
    Magic { path: PathBuf },
    #[error("{}: version {found} not supported (this build reads {ESTIMATOR_VERSION_MIN} to {ESTIMATOR_VERSION}; `make bake` or `nppp bake` rebuilds it)", path.display())]
    Version { path: PathBuf, found: u32 },
    #[error("{}: checksum mismatch (file corrupted)", path.display())]
    Checksum { path: PathBuf },
    #[error("{}: truncated: {what}", path.display())]
    Truncated { path: PathBuf, what: String },
    #[error("{}: invalid header: {what}", path.display())]
    Header { path: PathBuf, what: String },
    #[error("{}: {what}", path.display())]
    Invalid { path: PathBuf, what: String },
    /// Building an estimator in memory (bake) from inconsistent parts.
    #[error("cannot build estimator: {0}")]
    Build(String),
}

/// What an estimator was trained for and how it is to be run.
#[derive(Clone, Debug, PartialEq)]
pub struct EstimatorMeta {
    pub mesh_name: String,
    /// Content hash of the mesh file: an estimator silently attached to an
    /// edited mesh would give plausible but wrong images.
    pub mesh_hash: u64,
    pub material_name: String,
    pub material_hash: u64,
    /// Maps mesh space to the unit sphere all estimator data lives in.
    pub sphere: BoundingSphere,
    pub latent_dim: u32,
    pub noise_dim: u32,
    /// Largest bounce count the decoder may report (the data generator's cap).
    pub max_internal_bounces: u32,
    pub notes: String,
}

#[derive(Clone, Debug, PartialEq)]
pub struct BakedEstimator {
    pub meta: EstimatorMeta,
    pub latent: QuantizedGrid,
    /// One channel: the mask network's logit (hit if the interpolated value > 0).
    pub mask: QuantizedGrid,
    pub decoder: Mlp,
    pub transform: ExitTransform,
    /// The vertex head, when the model was trained on data with picked
    /// vertices (an opaque object with a non-delta surface).
    pub vertex: Option<VertexHead>,
}

/// The second decoder: `[z, r']` -> an encoded [`crate::PickedVertex`].
#[derive(Clone, Debug, PartialEq)]
pub struct VertexHead {
    pub decoder: Mlp,
    pub transform: VertexTransform,
}

/// Shape of one grid as written in the header.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq, Eq)]
struct GridShape {
    res: u32,
    channels: u32,
    bits: u8,
}

/// The JSON header: every size the binary sections have, and the strings.
/// Floats live in the binary sections so they round-trip bit-exactly.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct FileHeader {
    mesh_name: String,
    mesh_hash: u64,
    material_name: String,
    material_hash: u64,
    latent_dim: u32,
    noise_dim: u32,
    max_internal_bounces: u32,
    notes: String,
    latent: GridShape,
    mask: GridShape,
    /// `[inputs, outputs]` of each decoder layer.
    decoder: Vec<[u32; 2]>,
    /// The same for the vertex head, if any (version 2 on).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    vertex_decoder: Option<Vec<[u32; 2]>>,
}

fn shape(g: &QuantizedGrid) -> GridShape {
    GridShape { res: g.res, channels: g.channels, bits: g.bits }
}

/// Section sizes in file order, each `(name, bytes)`.
fn section_sizes(h: &FileHeader) -> Result<Vec<(String, usize)>, String> {
    let mut v = vec![("sphere".to_string(), 16usize), ("output transform".to_string(), 8 * EXIT_FEATURES)];
    for (name, g) in [("latent", &h.latent), ("mask", &h.mask)] {
        if quant::check_bits(g.bits).is_err() {
            return Err(format!("{name} grid: {} bits not supported (8, 4 or 2)", g.bits));
        }
        if g.channels == 0 || g.channels as usize > MAX_LAYER_WIDTH {
            return Err(format!("{name} grid: {} channels is absurd", g.channels));
        }
        if g.res < MIN_RES {
            return Err(format!("{name} grid: resolution {} is below {MIN_RES}", g.res));
        }
        let bytes = grid::data_bytes(g.res, g.channels, g.bits)
            .ok_or_else(|| format!("{name} grid: resolution {} with {} channels is absurd (size overflows)", g.res, g.channels))?;
        v.push((format!("{name} quantization"), 8 * g.channels as usize));
        v.push((name.to_string(), bytes));
    }
    layer_sections("decoder", &h.decoder, &mut v)?;
    if let Some(vd) = &h.vertex_decoder {
        v.push(("vertex transform".to_string(), 8 * VERTEX_FEATURES));
        layer_sections("vertex decoder", vd, &mut v)?;
    }
    Ok(v)
}

/// The sections of an MLP's layers (`name layer i`), sizes checked.
fn layer_sections(name: &str, layers: &[[u32; 2]], v: &mut Vec<(String, usize)>) -> Result<(), String> {
    if layers.is_empty() || layers.len() > MAX_DECODER_LAYERS {
        return Err(format!("{name} has {} layers (1 to {MAX_DECODER_LAYERS} allowed)", layers.len()));
    }
    for (i, &[ni, no]) in layers.iter().enumerate() {
        let (ni, no) = (ni as usize, no as usize);
        if ni == 0 || no == 0 || ni > MAX_LAYER_WIDTH || no > MAX_LAYER_WIDTH {
            return Err(format!("{name} layer {i} is {no}x{ni} (each side 1 to {MAX_LAYER_WIDTH})"));
        }
        v.push((format!("{name} layer {i}"), 4 * (ni * no + no)));
    }
    Ok(())
}

/// A parsed header, its section sizes, and where the sections start.
type Layout = (FileHeader, Vec<(String, usize)>, usize);

/// Reads little-endian values from a byte slice; running out is an error
/// (the sizes were checked, but a bug here must not become a panic).
struct Cursor<'a> {
    bytes: &'a [u8],
    pos: usize,
}

impl<'a> Cursor<'a> {
    fn take(&mut self, n: usize) -> Option<&'a [u8]> {
        let end = self.pos.checked_add(n)?;
        let s = self.bytes.get(self.pos..end)?;
        self.pos = end;
        Some(s)
    }

    fn f32s(&mut self, n: usize) -> Option<Vec<f32>> {
        let s = self.take(n.checked_mul(4)?)?;
        Some(s.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect())
    }
}

fn put_f32s(out: &mut Vec<u8>, xs: &[f32]) {
    for x in xs {
        out.extend_from_slice(&x.to_le_bytes());
    }
}

fn read_u32(b: &[u8], at: usize) -> Option<u32> {
    b.get(at..at + 4).map(|s| u32::from_le_bytes([s[0], s[1], s[2], s[3]]))
}

fn fmt_bytes(b: usize) -> String {
    nppp_files::format_bytes(b as u64)
}

impl BakedEstimator {
    /// Quantizes f32 grids from bake into an estimator; the latent grid at
    /// `bits`, the mask (logits, clamped to +-[`MASK_LOGIT_CLAMP`]) at
    /// [`DEFAULT_MASK_BITS`].
    #[allow(clippy::too_many_arguments)]
    pub fn from_f32_grids(
        meta: EstimatorMeta,
        latent_res: u32,
        latent: &[f32],
        mask_res: u32,
        mask_logits: &[f32],
        bits: u8,
        decoder: Mlp,
        transform: ExitTransform,
    ) -> Result<Self, EstimatorFileError> {
        Self::from_f32_grids_with_mask_bits(meta, latent_res, latent, mask_res, mask_logits, bits, DEFAULT_MASK_BITS, decoder, transform)
    }

    #[allow(clippy::too_many_arguments)]
    pub fn from_f32_grids_with_mask_bits(
        meta: EstimatorMeta,
        latent_res: u32,
        latent: &[f32],
        mask_res: u32,
        mask_logits: &[f32],
        bits: u8,
        mask_bits: u8,
        decoder: Mlp,
        transform: ExitTransform,
    ) -> Result<Self, EstimatorFileError> {
        let b = |what: &str, e: GridError| EstimatorFileError::Build(format!("{what} grid: {e}"));
        let latent = QuantizedGrid::from_f32(latent_res, meta.latent_dim, latent, bits).map_err(|e| b("latent", e))?;
        let clamped: Vec<f32> =
            mask_logits.iter().map(|&x| if x.is_nan() { x } else { x.clamp(-MASK_LOGIT_CLAMP, MASK_LOGIT_CLAMP) }).collect();
        let mask = QuantizedGrid::from_f32(mask_res, 1, &clamped, mask_bits).map_err(|e| b("mask", e))?;
        let est = Self { meta, latent, mask, decoder, transform, vertex: None };
        est.check().map_err(EstimatorFileError::Build)?;
        Ok(est)
    }

    /// Attaches a vertex head (checked against the estimator's latent and
    /// noise sizes).
    pub fn with_vertex_head(mut self, head: VertexHead) -> Result<Self, EstimatorFileError> {
        self.vertex = Some(head);
        self.check().map_err(EstimatorFileError::Build)?;
        Ok(self)
    }

    /// Everything that must hold for the sampler to run: sizes agree between
    /// grids, decoder and metadata, and every float is usable.
    pub fn check(&self) -> Result<(), String> {
        let m = &self.meta;
        if !(m.sphere.center.is_finite() && m.sphere.radius.is_finite() && m.sphere.radius > 0.0) {
            let (c, r) = (m.sphere.center, m.sphere.radius);
            return Err(format!("bounding sphere (centre [{} {} {}], radius {r}) is not finite with a positive radius", c.x, c.y, c.z));
        }
        self.latent.validate().map_err(|e| format!("latent grid: {e}"))?;
        self.mask.validate().map_err(|e| format!("mask grid: {e}"))?;
        if self.latent.channels != m.latent_dim {
            return Err(format!("latent grid has {} channels but latent_dim is {}", self.latent.channels, m.latent_dim));
        }
        if self.mask.channels != 1 {
            return Err(format!("mask grid has {} channels, 1 expected", self.mask.channels));
        }
        self.decoder.validate().map_err(|e| format!("decoder: {e}"))?;
        let want_in = m.latent_dim as usize + m.noise_dim as usize;
        if self.decoder.inputs() != want_in {
            return Err(format!(
                "decoder takes {} inputs, latent_dim + noise_dim = {} + {} = {want_in}",
                self.decoder.inputs(),
                m.latent_dim,
                m.noise_dim
            ));
        }
        if self.decoder.outputs() != EXIT_FEATURES {
            return Err(format!("decoder gives {} outputs, an exit has {EXIT_FEATURES} features", self.decoder.outputs()));
        }
        if let Some(what) = crate::exit::transform_problem(&self.transform.mean, &self.transform.std) {
            return Err(format!("output transform: {what}"));
        }
        if let Some(v) = &self.vertex {
            v.decoder.validate().map_err(|e| format!("vertex decoder: {e}"))?;
            if v.decoder.inputs() != want_in {
                return Err(format!("vertex decoder takes {} inputs, latent_dim + noise_dim = {want_in}", v.decoder.inputs()));
            }
            if v.decoder.outputs() != VERTEX_FEATURES {
                return Err(format!("vertex decoder gives {} outputs, a vertex has {VERTEX_FEATURES} features", v.decoder.outputs()));
            }
            if let Some(what) = crate::exit::transform_problem(&v.transform.mean, &v.transform.std) {
                return Err(format!("vertex transform: {what}"));
            }
        }
        Ok(())
    }

    /// Bytes the runtime holds: grids and decoder (what the thesis counts,
    /// plus the small per-channel and transform parameters).
    pub fn memory_bytes(&self) -> usize {
        let mlp = |m: &Mlp| -> usize { m.layers.iter().map(|l| 4 * (l.weight.len() + l.bias.len())).sum() };
        let vertex = self.vertex.as_ref().map_or(0, |v| mlp(&v.decoder) + 8 * VERTEX_FEATURES);
        self.latent.memory_bytes() + self.mask.memory_bytes() + mlp(&self.decoder) + 8 * EXIT_FEATURES + vertex
    }

    /// The serialized file, checksum included.
    pub fn to_bytes(&self) -> Vec<u8> {
        let m = &self.meta;
        let header = FileHeader {
            mesh_name: m.mesh_name.clone(),
            mesh_hash: m.mesh_hash,
            material_name: m.material_name.clone(),
            material_hash: m.material_hash,
            latent_dim: m.latent_dim,
            noise_dim: m.noise_dim,
            max_internal_bounces: m.max_internal_bounces,
            notes: m.notes.clone(),
            latent: shape(&self.latent),
            mask: shape(&self.mask),
            decoder: self.decoder.layers.iter().map(|l| [l.inputs as u32, l.outputs as u32]).collect(),
            vertex_decoder: self.vertex.as_ref().map(|v| v.decoder.layers.iter().map(|l| [l.inputs as u32, l.outputs as u32]).collect()),
        };
        // Serializing plain strings and integers cannot fail.
        let json = serde_json::to_vec(&header).unwrap_or_default();
        let mut out = Vec::with_capacity(PREFIX_LEN + 4 + json.len() + self.memory_bytes() + 64);
        out.extend_from_slice(&ESTIMATOR_MAGIC);
        out.extend_from_slice(&ESTIMATOR_VERSION.to_le_bytes());
        out.extend_from_slice(&[0; 4]);
        out.extend_from_slice(&(json.len() as u32).to_le_bytes());
        out.extend_from_slice(&json);
        let s = &m.sphere;
        put_f32s(&mut out, &[s.center.x, s.center.y, s.center.z, s.radius]);
        put_f32s(&mut out, &self.transform.mean);
        put_f32s(&mut out, &self.transform.std);
        for g in [&self.latent, &self.mask] {
            put_f32s(&mut out, &g.scale);
            put_f32s(&mut out, &g.offset);
            out.extend_from_slice(&g.data);
        }
        for l in &self.decoder.layers {
            put_f32s(&mut out, &l.weight);
            put_f32s(&mut out, &l.bias);
        }
        if let Some(v) = &self.vertex {
            put_f32s(&mut out, &v.transform.mean);
            put_f32s(&mut out, &v.transform.std);
            for l in &v.decoder.layers {
                put_f32s(&mut out, &l.weight);
                put_f32s(&mut out, &l.bias);
            }
        }
        let crc = crc32fast::hash(&out[PREFIX_LEN..]);
        out[12..16].copy_from_slice(&crc.to_le_bytes());
        out
    }

    pub fn save(&self, path: &Path) -> Result<(), EstimatorFileError> {
        self.check().map_err(|what| EstimatorFileError::Invalid { path: path.into(), what: format!("refusing to save: {what}") })?;
        nppp_files::write_atomic(path, &self.to_bytes()).map_err(|err| EstimatorFileError::Io { path: path.into(), err })
    }

    pub fn load(path: &Path) -> Result<Self, EstimatorFileError> {
        // The only allocation before validation is the file itself.
        let bytes = nppp_files::read_regular(path).map_err(|err| EstimatorFileError::Io { path: path.into(), err })?;
        Self::from_bytes(&bytes, path)
    }

    /// Parses a file's bytes; `path` only names the file in errors.
    pub fn from_bytes(bytes: &[u8], path: &Path) -> Result<Self, EstimatorFileError> {
        let p = || path.to_path_buf();
        let n = bytes.len();
        if bytes[..n.min(8)] != ESTIMATOR_MAGIC[..n.min(8)] {
            return Err(EstimatorFileError::Magic { path: p() });
        }
        if n < PREFIX_LEN + 4 {
            return Err(EstimatorFileError::Truncated {
                path: p(),
                what: format!("file is {n} bytes, the fixed prefix alone is {}", PREFIX_LEN + 4),
            });
        }
        let version = read_u32(bytes, 8).unwrap_or(0);
        if !(ESTIMATOR_VERSION_MIN..=ESTIMATOR_VERSION).contains(&version) {
            return Err(EstimatorFileError::Version { path: p(), found: version });
        }
        let stored_crc = read_u32(bytes, 12).unwrap_or(0);
        let crc_ok = crc32fast::hash(&bytes[PREFIX_LEN..]) == stored_crc;
        let layout = Self::layout(bytes, path);
        if !crc_ok {
            // A short file fails the checksum too; say "truncated" when the
            // header explains the damage, "corrupted" otherwise.
            return Err(match layout {
                Err(e @ EstimatorFileError::Truncated { .. }) => e,
                Ok((_, sections, start)) => {
                    Self::truncation(&sections, start, n, path).unwrap_or(EstimatorFileError::Checksum { path: p() })
                }
                Err(_) => EstimatorFileError::Checksum { path: p() },
            });
        }
        let (header, sections, start) = layout?;
        if header.vertex_decoder.is_some() && version < 2 {
            return Err(EstimatorFileError::Header {
                path: p(),
                what: format!("a vertex decoder in a version {version} file (vertex heads came with version 2)"),
            });
        }
        if let Some(e) = Self::truncation(&sections, start, n, path) {
            return Err(e);
        }
        let total = start + sections.iter().map(|s| s.1).sum::<usize>();
        if total != n {
            return Err(EstimatorFileError::Invalid { path: p(), what: format!("{} bytes after the last section", n - total) });
        }
        let est = Self::decode(bytes, start, header)
            .ok_or_else(|| EstimatorFileError::Truncated { path: p(), what: "sections end early".into() })?;
        est.check().map_err(|what| EstimatorFileError::Invalid { path: p(), what })?;
        Ok(est)
    }

    /// Parses the header and derives the section sizes without allocating
    /// anything proportional to them.
    fn layout(bytes: &[u8], path: &Path) -> Result<Layout, EstimatorFileError> {
        let n = bytes.len();
        let hlen = read_u32(bytes, PREFIX_LEN).unwrap_or(0) as usize;
        if hlen > MAX_HEADER_LEN {
            return Err(EstimatorFileError::Header { path: path.into(), what: format!("header length {hlen} is absurd") });
        }
        let start = PREFIX_LEN + 4 + hlen;
        if start > n {
            return Err(EstimatorFileError::Truncated {
                path: path.into(),
                what: format!("header says {hlen} header bytes, {} present", n - PREFIX_LEN - 4),
            });
        }
        let header: FileHeader = serde_json::from_slice(&bytes[PREFIX_LEN + 4..start])
            .map_err(|e| EstimatorFileError::Header { path: path.into(), what: e.to_string() })?;
        let sections = section_sizes(&header).map_err(|what| EstimatorFileError::Invalid { path: path.into(), what })?;
        Ok((header, sections, start))
    }

    /// The first section that does not fit in `n` bytes, as an error.
    fn truncation(sections: &[(String, usize)], start: usize, n: usize, path: &Path) -> Option<EstimatorFileError> {
        let mut at = start;
        for (name, len) in sections {
            let end = at.checked_add(*len);
            if end.is_none_or(|e| e > n) {
                let present = n.saturating_sub(at);
                return Some(EstimatorFileError::Truncated {
                    path: path.into(),
                    what: format!("header says {len} {name} bytes, {present} present"),
                });
            }
            at = end.unwrap_or(usize::MAX);
        }
        None
    }

    fn decode(bytes: &[u8], start: usize, h: FileHeader) -> Option<Self> {
        let mut c = Cursor { bytes, pos: start };
        let s = c.f32s(4)?;
        let sphere = BoundingSphere { center: Vec3::new(s[0], s[1], s[2]), radius: s[3] };
        let mut transform = ExitTransform::default();
        transform.mean.copy_from_slice(&c.f32s(EXIT_FEATURES)?);
        transform.std.copy_from_slice(&c.f32s(EXIT_FEATURES)?);
        let mut grid = |g: GridShape| -> Option<QuantizedGrid> {
            let scale = c.f32s(g.channels as usize)?;
            let offset = c.f32s(g.channels as usize)?;
            let data = c.take(grid::data_bytes(g.res, g.channels, g.bits)?)?.to_vec();
            Some(QuantizedGrid { res: g.res, channels: g.channels, bits: g.bits, scale, offset, data })
        };
        let latent = grid(h.latent)?;
        let mask = grid(h.mask)?;
        let mlp = |c: &mut Cursor, shape: &[[u32; 2]]| -> Option<Mlp> {
            let mut layers = Vec::with_capacity(shape.len());
            for &[ni, no] in shape {
                let (ni, no) = (ni as usize, no as usize);
                let weight = c.f32s(ni * no)?;
                let bias = c.f32s(no)?;
                layers.push(Dense { inputs: ni, outputs: no, weight, bias });
            }
            Some(Mlp { layers })
        };
        let decoder = mlp(&mut c, &h.decoder)?;
        let vertex = match &h.vertex_decoder {
            None => None,
            Some(shape) => {
                let mut transform = VertexTransform::default();
                transform.mean.copy_from_slice(&c.f32s(VERTEX_FEATURES)?);
                transform.std.copy_from_slice(&c.f32s(VERTEX_FEATURES)?);
                Some(VertexHead { decoder: mlp(&mut c, shape)?, transform })
            }
        };
        let meta = EstimatorMeta {
            mesh_name: h.mesh_name,
            mesh_hash: h.mesh_hash,
            material_name: h.material_name,
            material_hash: h.material_hash,
            sphere,
            latent_dim: h.latent_dim,
            noise_dim: h.noise_dim,
            max_internal_bounces: h.max_internal_bounces,
            notes: h.notes,
        };
        Some(Self { meta, latent, mask, decoder, transform, vertex })
    }

    /// `nppp info`: the file's summary ([`Self::describe`]) with the
    /// format version it was written in (an older one than this build
    /// writes still loads).
    pub fn describe_file(path: &Path) -> Result<String, EstimatorFileError> {
        let bytes = nppp_files::read_regular(path).map_err(|err| EstimatorFileError::Io { path: path.into(), err })?;
        let est = Self::from_bytes(&bytes, path)?;
        Ok(est.describe_as(read_u32(&bytes, 8).unwrap_or(ESTIMATOR_VERSION)))
    }

    /// Human-readable summary, with the format version it is saved in.
    pub fn describe(&self) -> String {
        self.describe_as(ESTIMATOR_VERSION)
    }

    fn describe_as(&self, version: u32) -> String {
        let m = &self.meta;
        let mut s = String::new();
        let _ = writeln!(s, "nppp estimator (format version {version})");
        let _ = writeln!(s, "  mesh:      {} (content hash {:016x})", m.mesh_name, m.mesh_hash);
        let _ = writeln!(s, "  material:  {} (content hash {:016x})", m.material_name, m.material_hash);
        let c = m.sphere.center;
        let _ = writeln!(s, "  sphere:    centre ({}, {}, {}), radius {}", c.x, c.y, c.z, m.sphere.radius);
        let _ =
            writeln!(s, "  latent:    {} dims, noise {} dims, internal bounces <= {}", m.latent_dim, m.noise_dim, m.max_internal_bounces);
        for (name, g, what) in [("latent grid", &self.latent, "latents"), ("mask grid", &self.mask, "logits, hit if > 0")] {
            let _ = writeln!(
                s,
                "  {name}: {}^4 nodes x {} ch x {} bit = {} ({what}; + {} scale/offset)",
                g.res,
                g.channels,
                g.bits,
                fmt_bytes(g.data.len()),
                fmt_bytes(4 * (g.scale.len() + g.offset.len()))
            );
        }
        let widths: Vec<String> =
            std::iter::once(self.decoder.inputs()).chain(self.decoder.layers.iter().map(|l| l.outputs)).map(|w| w.to_string()).collect();
        let params: usize = self.decoder.layers.iter().map(|l| l.weight.len() + l.bias.len()).sum();
        let macs = self.decoder.multiply_adds();
        let _ = writeln!(
            s,
            "  decoder:   {} (ReLU), {params} parameters = {}, {macs} multiply-adds per sample",
            widths.join(" -> "),
            fmt_bytes(4 * params)
        );
        let fmt_arr = |a: &[f32]| a.iter().map(|x| format!("{x:.4}")).collect::<Vec<_>>().join(", ");
        let _ = writeln!(s, "  transform: mean [{}]", fmt_arr(&self.transform.mean));
        let _ = writeln!(s, "             std  [{}]", fmt_arr(&self.transform.std));
        let (l, k) = (&self.latent, &self.mask);
        let formula = grid::data_bytes(l.res, l.channels, l.bits).unwrap_or(0) + grid::data_bytes(k.res, k.channels, k.bits).unwrap_or(0);
        let _ = writeln!(
            s,
            "  memory:    {} in total; thesis formula S_z^4 x d_z x b/8 + S_m^4 x b_m/8 = {}^4 x {} x {}/8 + {}^4 x {}/8 = {}",
            fmt_bytes(self.memory_bytes()),
            l.res,
            l.channels,
            l.bits,
            k.res,
            k.bits,
            fmt_bytes(formula)
        );
        match &self.vertex {
            Some(v) => {
                let macs = v.decoder.multiply_adds();
                let _ = writeln!(
                    s,
                    "  vertex head: a skipped vertex for next-event estimation (`--entry-nee picked`), {macs} multiply-adds per sample"
                );
            }
            None => {
                let _ = writeln!(s, "  vertex head: none (`--entry-nee picked` needs the oracle or a model trained on data with vertices)");
            }
        }
        if !m.notes.is_empty() {
            let _ = writeln!(s, "  notes:     {}", m.notes);
        }
        s
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    pub(crate) fn tiny_estimator(latent_dim: u32, noise_dim: u32, bits: u8) -> BakedEstimator {
        let res = 3u32;
        let n = grid::node_count(res);
        let latent: Vec<f32> = (0..n * latent_dim as usize).map(|k| ((k * 37 % 101) as f32 / 50.0 - 1.0) * (1 + k % 3) as f32).collect();
        let mask: Vec<f32> = (0..n).map(|k| (k as f32 * 0.7).sin() * 12.0).collect();
        let width = 8;
        let mut seed = 1u32;
        let mut rnd = move || {
            seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (seed >> 8) as f32 / (1 << 24) as f32 - 0.5
        };
        let mut dense = |i: usize, o: usize| Dense {
            inputs: i,
            outputs: o,
            weight: (0..i * o).map(|_| rnd()).collect(),
            bias: (0..o).map(|_| rnd()).collect(),
        };
        let inputs = (latent_dim + noise_dim) as usize;
        let decoder = Mlp { layers: vec![dense(inputs, width), dense(width, width), dense(width, EXIT_FEATURES)] };
        let meta = EstimatorMeta {
            mesh_name: "dragon.obj".into(),
            mesh_hash: 0xdead_beef_0123_4567,
            material_name: "glass \"ior 1.5\"".into(),
            material_hash: u64::MAX,
            sphere: BoundingSphere { center: Vec3::new(0.1, -2.0, 3.5), radius: 1.75 },
            latent_dim,
            noise_dim,
            max_internal_bounces: 64,
            notes: "test estimator ✓".into(),
        };
        let mut transform = ExitTransform::default();
        for i in 0..EXIT_FEATURES {
            transform.mean[i] = 0.01 * i as f32 - 0.05;
            transform.std[i] = 0.5 + 0.1 * i as f32;
        }
        BakedEstimator::from_f32_grids(meta, res, &latent, 2, &mask[..16], bits, decoder, transform).unwrap()
    }

    /// A vertex head for [`tiny_estimator`]'s sizes.
    pub(crate) fn tiny_vertex_head(latent_dim: u32, noise_dim: u32) -> VertexHead {
        let inputs = (latent_dim + noise_dim) as usize;
        let dense = |i: usize, o: usize, salt: usize| Dense {
            inputs: i,
            outputs: o,
            weight: (0..i * o).map(|k| (((k + salt) * 29 % 53) as f32 / 53.0 - 0.5) * 0.6).collect(),
            bias: (0..o).map(|k| ((k + salt) % 7) as f32 * 0.05 - 0.15).collect(),
        };
        let mut transform = VertexTransform::default();
        for i in 0..VERTEX_FEATURES {
            transform.mean[i] = 0.02 * i as f32 - 0.1;
            transform.std[i] = 0.3 + 0.05 * i as f32;
        }
        VertexHead { decoder: Mlp { layers: vec![dense(inputs, 6, 1), dense(6, VERTEX_FEATURES, 2)] }, transform }
    }

    /// Version 2: an estimator with a vertex head round-trips bit for bit;
    /// a version 1 file (no vertex head) still loads; a version 1 file that
    /// claims a vertex head, or a head of the wrong shape, is refused.
    #[test]
    fn vertex_head_round_trips_and_version_1_still_loads() {
        let est = tiny_estimator(4, 3, 8).with_vertex_head(tiny_vertex_head(4, 3)).unwrap();
        let bytes = est.to_bytes();
        let back = BakedEstimator::from_bytes(&bytes, Path::new("v.nppp")).unwrap();
        assert_eq!(back, est);
        assert!(est.describe().contains("vertex head: a skipped vertex"));
        let mut v1 = bytes.clone();
        v1[8..12].copy_from_slice(&1u32.to_le_bytes());
        let e = BakedEstimator::from_bytes(&v1, Path::new("v.nppp")).unwrap_err().to_string();
        assert!(e.contains("a vertex decoder in a version 1 file"), "{e}");
        let plain = tiny_estimator(4, 3, 8);
        let mut v1 = plain.to_bytes();
        v1[8..12].copy_from_slice(&1u32.to_le_bytes());
        assert_eq!(BakedEstimator::from_bytes(&v1, Path::new("old.nppp")).unwrap(), plain);
        assert!(plain.describe().contains("vertex head: none"));
        // `nppp info` says which version the file is, not this build's.
        let d = tmpdir("describe-v1");
        std::fs::write(d.join("old.nppp"), &v1).unwrap();
        let info = BakedEstimator::describe_file(&d.join("old.nppp")).unwrap();
        assert!(info.starts_with("nppp estimator (format version 1)"), "{info}");
        assert!(plain.describe().starts_with(&format!("nppp estimator (format version {ESTIMATOR_VERSION})")));
        let _ = std::fs::remove_dir_all(&d);
        // A head with another latent size cannot be attached.
        let e = tiny_estimator(4, 3, 8).with_vertex_head(tiny_vertex_head(5, 3)).unwrap_err().to_string();
        assert!(e.contains("vertex decoder takes 8 inputs"), "{e}");
        // Truncated in the vertex head's sections: named.
        let e = BakedEstimator::from_bytes(&bytes[..bytes.len() - 10], Path::new("v.nppp")).unwrap_err().to_string();
        assert!(e.contains("truncated") && e.contains("vertex decoder layer 1"), "{e}");
    }

    fn tmpdir(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("nppp-est-{name}-{}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    #[test]
    fn file_round_trip_is_bit_exact() {
        let dir = tmpdir("roundtrip");
        for bits in [8u8, 4, 2] {
            let est = tiny_estimator(5, 3, bits);
            let path = dir.join(format!("e{bits}.nppp"));
            est.save(&path).unwrap();
            let bytes = std::fs::read(&path).unwrap();
            let back = BakedEstimator::load(&path).unwrap();
            assert_eq!(back, est);
            assert_eq!(back.to_bytes(), bytes);
            // No temp file left behind.
            assert_eq!(
                std::fs::read_dir(&dir).unwrap().filter(|e| e.as_ref().unwrap().file_name().to_string_lossy().ends_with(".tmp")).count(),
                0
            );
        }
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn describe_mentions_everything() {
        let est = tiny_estimator(4, 2, 8);
        let d = est.describe();
        for needle in [
            "dragon.obj",
            "deadbeef01234567",
            "glass",
            "radius 1.75",
            "3^4 nodes x 4 ch x 8 bit",
            "2^4 nodes x 1 ch",
            "6 -> 8 -> 8 -> 13",
            "thesis formula",
            "test estimator",
        ] {
            assert!(d.contains(needle), "missing {needle:?} in\n{d}");
        }
    }

    #[test]
    fn build_rejects_inconsistent_parts() {
        let est = tiny_estimator(4, 2, 8);
        let m = est.meta.clone();
        let lat = est.latent.to_f32();
        let mask = est.mask.to_f32();
        let t = est.transform.clone();
        let ok = |meta: EstimatorMeta, dec: Mlp, t: ExitTransform, bits: u8| {
            BakedEstimator::from_f32_grids(meta, 3, &lat, 2, &mask, bits, dec, t)
        };
        assert!(ok(m.clone(), est.decoder.clone(), t.clone(), 8).is_ok());
        assert!(ok(m.clone(), est.decoder.clone(), t.clone(), 3).is_err());
        let mut m2 = m.clone();
        m2.noise_dim = 3;
        assert!(ok(m2, est.decoder.clone(), t.clone(), 8).unwrap_err().to_string().contains("decoder takes 6 inputs"));
        let mut t2 = t.clone();
        t2.std[3] = 0.0;
        assert!(ok(m.clone(), est.decoder.clone(), t2, 8).is_err());
        let mut m3 = m.clone();
        m3.sphere.radius = f32::NAN;
        assert!(ok(m3, est.decoder.clone(), t.clone(), 8).is_err());
        let mut d = est.decoder.clone();
        d.layers.pop();
        assert!(ok(m, d, t, 8).is_err());
    }

    fn err_of(bytes: &[u8]) -> String {
        match BakedEstimator::from_bytes(bytes, Path::new("models/x.nppp")) {
            Ok(_) => panic!("damaged file accepted"),
            Err(e) => e.to_string(),
        }
    }

    fn recrc(b: &mut [u8]) {
        let crc = crc32fast::hash(&b[PREFIX_LEN..]);
        b[12..16].copy_from_slice(&crc.to_le_bytes());
    }

    /// Replaces the JSON header, keeping the sections, with a valid checksum:
    /// reaches the size checks that a checksum would otherwise mask.
    fn with_header(bytes: &[u8], edit: impl Fn(&mut serde_json::Value)) -> Vec<u8> {
        let hlen = read_u32(bytes, PREFIX_LEN).unwrap() as usize;
        let mut v: serde_json::Value = serde_json::from_slice(&bytes[20..20 + hlen]).unwrap();
        edit(&mut v);
        let json = serde_json::to_vec(&v).unwrap();
        let mut out = bytes[..16].to_vec();
        out.extend_from_slice(&(json.len() as u32).to_le_bytes());
        out.extend_from_slice(&json);
        out.extend_from_slice(&bytes[20 + hlen..]);
        recrc(&mut out);
        out
    }

    #[test]
    fn damaged_files_are_rejected_with_clear_errors() {
        let good = tiny_estimator(4, 2, 8).to_bytes();
        assert!(BakedEstimator::from_bytes(&good, Path::new("x")).is_ok());

        // A flipped bit anywhere: the prefix gives magic/version errors, the rest
        // the checksum (or a header error that names the damage).
        for i in 0..good.len() {
            let mut b = good.clone();
            b[i] ^= 0x10;
            let e = err_of(&b);
            assert!(e.starts_with("models/x.nppp: "), "{e}");
            match i {
                0..8 => assert!(e.contains("wrong magic"), "{i}: {e}"),
                8..12 => assert!(e.contains("not supported"), "{i}: {e}"),
                _ => assert!(e.contains("checksum mismatch") || e.contains("truncated") || e.contains("header"), "{i}: {e}"),
            }
        }

        // Truncation at every offset.
        for n in 0..good.len() {
            let e = err_of(&good[..n]);
            assert!(e.contains("truncated") || (n < 8 && e.contains("magic")), "{n}: {e}");
        }
        let e = err_of(&good[..good.len() - 100]);
        assert!(e.contains("header says") && e.contains("present"), "{e}");

        let mut b = good.clone();
        b[..8].copy_from_slice(b"NPPPDAT\0");
        assert!(err_of(&b).contains("wrong magic"));
        let mut b = good.clone();
        b[8..12].copy_from_slice(&7u32.to_le_bytes());
        assert_eq!(err_of(&b), "models/x.nppp: version 7 not supported (this build reads 1 to 2; `make bake` or `nppp bake` rebuilds it)");
        let mut b = good.clone();
        b.push(0);
        recrc(&mut b);
        assert!(err_of(&b).contains("1 bytes after the last section"));
    }

    // Fuzzing past the checksum: random byte edits and truncations, with
    // the CRC then made valid again so the parser itself sees the damage.
    // Whatever loads must also build a sampler and give finite exits.
    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(3000))]
        #[test]
        fn checksummed_garbage_never_panics(
            edits in proptest::collection::vec((proptest::prelude::any::<proptest::sample::Index>(), proptest::prelude::any::<u8>()), 0..6),
            cut in proptest::prelude::any::<proptest::sample::Index>(),
            truncate in proptest::prelude::any::<bool>(),
            u in proptest::array::uniform4(0.0f32..1.0),
        ) {
            let mut b = tiny_estimator(4, 2, 8).to_bytes();
            for (i, v) in edits {
                let i = i.index(b.len());
                b[i] = v;
            }
            if truncate {
                b.truncate(cut.index(b.len()).max(16));
            }
            recrc(&mut b);
            if let Ok(est) = BakedEstimator::from_bytes(&b, Path::new("fuzz.nppp"))
                && let Ok(s) = crate::EstimatorSampler::try_new(est)
            {
                let mut rep = crate::DecodeRepairs::default();
                let r = vec![0.5f32; s.noise_dim()];
                let e = s.sample(&nppp_geom::SpherePair(u), &r, &mut rep);
                proptest::prop_assert!(e.position.is_finite() && e.direction.is_finite());
                proptest::prop_assert!(e.throughput.is_finite() && e.radiance.is_finite());
            }
        }
    }

    #[test]
    fn absurd_sizes_never_allocate() {
        let good = tiny_estimator(4, 2, 8).to_bytes();
        type Edit = Box<dyn Fn(&mut serde_json::Value)>;
        let cases: Vec<(Edit, &str)> = vec![
            (Box::new(|v| v["latent"]["res"] = (1u64 << 31).into()), "absurd"),
            (Box::new(|v| v["latent"]["res"] = 60000.into()), "absurd"),
            (Box::new(|v| v["latent"]["res"] = 1000.into()), "truncated: header says 4000000000000 latent bytes"),
            (Box::new(|v| v["mask"]["res"] = 4096.into()), "truncated: header says 281474976710656 mask bytes"),
            (Box::new(|v| v["mask"]["res"] = 65535.into()), "mask grid: resolution 65535 with 1 channels is absurd"),
            (Box::new(|v| v["latent"]["channels"] = u32::MAX.into()), "absurd"),
            (Box::new(|v| v["latent"]["res"] = 1.into()), "below 2"),
            (Box::new(|v| v["latent"]["bits"] = 3.into()), "3 bits not supported"),
            (Box::new(|v| v["decoder"][0] = serde_json::json!([u32::MAX, u32::MAX])), "decoder layer 0"),
            (Box::new(|v| v["decoder"] = serde_json::json!([])), "0 layers"),
            (Box::new(|v| v["decoder"] = serde_json::Value::Array(vec![serde_json::json!([8, 8]); 100000])), "layers"),
            (Box::new(|v| v["latent_dim"] = 5.into()), "latent grid has 4 channels but latent_dim is 5"),
            (Box::new(|v| v["noise_dim"] = 3.into()), "decoder takes 6 inputs"),
            (Box::new(|v| v["extra"] = 1.into()), "unknown field"),
            (Box::new(|v| v["mesh_hash"] = (-1).into()), "invalid header"),
        ];
        for (edit, want) in cases {
            let b = with_header(&good, edit);
            let e = err_of(&b);
            assert!(e.contains(want), "want {want:?}, got {e}");
        }
        // A huge header length.
        let mut b = good.clone();
        b[16..20].copy_from_slice(&u32::MAX.to_le_bytes());
        recrc(&mut b);
        assert!(err_of(&b).contains("header length"));
        // Non-finite values in the sections, checksum valid.
        let hlen = read_u32(&good, PREFIX_LEN).unwrap() as usize;
        let sphere_radius = 20 + hlen + 12;
        let mut b = good.clone();
        b[sphere_radius..sphere_radius + 4].copy_from_slice(&f32::NAN.to_le_bytes());
        recrc(&mut b);
        assert!(err_of(&b).contains("sphere"));
        let std0 = 20 + hlen + 16 + 4 * EXIT_FEATURES;
        let mut b = good.clone();
        b[std0..std0 + 4].copy_from_slice(&(-1.0f32).to_le_bytes());
        recrc(&mut b);
        assert!(err_of(&b).contains("transform"));
    }

    #[test]
    fn missing_file_names_the_path() {
        let e = BakedEstimator::load(Path::new("/nonexistent/dir/m.nppp")).unwrap_err().to_string();
        assert!(e.starts_with("/nonexistent/dir/m.nppp: "), "{e}");
    }

    #[test]
    fn save_replaces_atomically() {
        let dir = tmpdir("atomic");
        let path = dir.join("a.nppp");
        tiny_estimator(4, 2, 8).save(&path).unwrap();
        let second = tiny_estimator(4, 2, 4);
        second.save(&path).unwrap();
        assert_eq!(BakedEstimator::load(&path).unwrap(), second);
        // Saving into a missing folder fails cleanly and leaves nothing.
        assert!(second.save(&dir.join("missing/b.nppp")).is_err());
        let _ = std::fs::remove_dir_all(&dir);
    }
}
