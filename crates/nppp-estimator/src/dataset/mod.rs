//! The training-data file: input rays with their mask label and, for hits,
//! k exits each (layout: `FORMAT.md`).
//!
//! The thesis stored 200k rays x k = 512 in 10 GiB. Here an exit takes about
//! 16 bytes before compression (octahedral unit vectors in 2 x u16, colours
//! as f16, all-zero colours as a flag bit, bounces in one byte), columns are
//! grouped per chunk so that deflate finds the repetition in flags, bounces
//! and throughputs, and every chunk carries its own length and CRC so a
//! trainer can stream (or randomly access) chunks in bounded memory.

use crate::exit::Exit;
use crate::vertex::PickedVertex;
use nppp_geom::{BoundingSphere, SpherePair, Vec3};
use serde::{Deserialize, Serialize};
use std::io::{BufReader, Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use thiserror::Error;

pub const DATASET_MAGIC: [u8; 8] = *b"NPPPDAT\0";
/// Version 2 added the picked vertex per exit (`DatasetHeader::vertices`);
/// version 1 files (no vertices) are still read.
pub const DATASET_VERSION: u32 = 2;
/// The oldest version this build reads.
pub const DATASET_VERSION_MIN: u32 = 1;
const CHUNK_MAGIC: [u8; 4] = *b"CHNK";
const END_MAGIC: [u8; 4] = *b"NEND";
const CHUNK_HEADER_LEN: usize = 28;
const TRAILER_LEN: usize = 40;
const INDEX_ENTRY_LEN: usize = 16;
const MAX_HEADER_LEN: usize = 1 << 20;
/// Rays per chunk by default: big enough for deflate and for few seeks,
/// small enough that a chunk of misses is not a whole epoch.
pub const DEFAULT_CHUNK_RAYS: u32 = 4096;
/// A chunk is closed early once its encoded columns reach this size, so
/// memory stays bounded whatever k and the hit rate are.
const CHUNK_TARGET_BYTES: usize = 32 << 20;
/// Readers refuse chunks that claim more than this (a writer never makes
/// one: the target above plus one ray of at most `MAX_K` exits).
const MAX_CHUNK_RAYS: u32 = 1 << 20;
const MAX_CHUNK_RAW: usize = 256 << 20;
pub const MAX_K: u32 = 1 << 20;
/// Worst-case angle (radians) between a unit vector and its stored 2 x u16
/// octahedral encoding, with a margin over the 1.27e-4 rad (0.0073 degrees)
/// measured by a test over 200k random directions.
pub const OCT_MAX_ANGLE: f32 = 1.5e-4;

/// Chunk payload encodings.
const ENC_RAW: u32 = 0;
const ENC_DEFLATE: u32 = 1;

/// What the data was generated for and how.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DatasetHeader {
    pub mesh_name: String,
    pub mesh_hash: u64,
    pub material_name: String,
    pub material_hash: u64,
    /// The material's full description, so a trainer can record exactly what
    /// it learned without the scene file.
    pub material_json: String,
    pub sphere: BoundingSphere,
    /// Exits per hit ray.
    pub k: u32,
    pub seed: u64,
    /// The generator's internal bounce cap; stored bounces saturate here.
    pub max_internal_bounces: u32,
    /// Set in a shard (`nppp gen --shard`): which of the data set's rays this
    /// file holds. Absent in a whole data set, whose header is then what it
    /// always was. A shard is a valid data set of its own rays.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub shard: Option<crate::shard::DatasetShard>,
    /// Whether every exit comes with the vertex of its walk picked for
    /// next-event estimation ([`PickedVertex`]): objects with a non-delta
    /// surface (version 2 on). Absent (false) in version 1 files.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub vertices: bool,
}

impl DatasetHeader {
    /// Whether the data is of a translucent object (a medium inside), read
    /// from the recorded material.
    pub fn has_medium(&self) -> bool {
        Self::is_translucent(&self.material())
    }

    /// The recorded material (null when it is not JSON).
    fn material(&self) -> serde_json::Value {
        serde_json::from_str(&self.material_json).unwrap_or_default()
    }

    fn is_translucent(material: &serde_json::Value) -> bool {
        material["type"] == "translucent"
    }

    /// The most throughput and radiance per channel this object's exits can
    /// carry (radiance only for an emitter, read from the recorded material).
    pub fn exit_bounds(&self) -> crate::ExitBounds {
        let material = self.material();
        let emitted = if material["type"] == "emitter" {
            material["radiance"].as_array().map_or(0.0, |c| c.iter().filter_map(|x| x.as_f64()).fold(0.0, f64::max))
        } else {
            0.0
        };
        crate::ExitBounds::new(Self::is_translucent(&material), emitted as f32)
    }
}

/// One input ray: its chord, whether it hits the mesh, and for a hit its k
/// exits (and, when the header says so, each walk's picked vertex).
#[derive(Clone, Debug, PartialEq)]
pub struct RayRecord {
    pub pair: SpherePair,
    pub hit: bool,
    pub exits: Vec<Exit>,
    /// Parallel to `exits` when [`DatasetHeader::vertices`], else empty.
    pub vertices: Vec<PickedVertex>,
}

#[derive(Clone, Debug, PartialEq)]
pub struct DatasetSummary {
    pub path: PathBuf,
    pub rays: u64,
    pub hits: u64,
    pub exits: u64,
    pub chunks: u64,
    /// The whole file.
    pub file_bytes: u64,
    /// Chunk payloads before compression.
    pub raw_bytes: u64,
}

impl DatasetSummary {
    pub fn bytes_per_exit(&self) -> f64 {
        if self.exits == 0 { 0.0 } else { self.file_bytes as f64 / self.exits as f64 }
    }
}

#[derive(Debug, Error)]
pub enum DatasetError {
    /// Shards that do not make one data set (`nppp merge`).
    #[error("{0}")]
    Merge(String),
    // `err`, not `source`: see `EstimatorFileError::Io`.
    #[error("{}: {err}", path.display())]
    Io { path: PathBuf, err: std::io::Error },
    #[error("{}: not an nppp training-data file (wrong magic; expected \"NPPPDAT\\0\")", path.display())]
    Magic { path: PathBuf },
    #[error("{}: version {found} not supported (this build reads {DATASET_VERSION_MIN} to {DATASET_VERSION}; `nppp gen` rebuilds the data)", path.display())]
    Version { path: PathBuf, found: u32 },
    #[error("{}: invalid header: {what}", path.display())]
    Header { path: PathBuf, what: String },
    #[error("{}: {what}", path.display())]
    Index { path: PathBuf, what: String },
    #[error("{}: chunk {chunk} (at byte {offset}): {what}", path.display())]
    Chunk { path: PathBuf, chunk: u64, offset: u64, what: String },
    #[error("{}: ray {ray}: {what}", path.display())]
    Record { path: PathBuf, ray: u64, what: String },
}

/// Options of a [`DatasetWriter`].
#[derive(Clone, Copy, Debug)]
pub struct WriterOptions {
    pub chunk_rays: u32,
    /// Deflate each chunk (kept raw when that does not make it smaller).
    pub compress: bool,
    /// Put the file in place over an existing one. Without it a file that
    /// appeared at the path while the data was made (another run finishing
    /// first) is left as it was, this one kept beside it, and
    /// [`DatasetWriter::finish`] says so ([`nppp_files::AtomicFile::commit_new`]).
    pub replace: bool,
}

impl Default for WriterOptions {
    fn default() -> Self {
        Self { chunk_rays: DEFAULT_CHUNK_RAYS, compress: true, replace: true }
    }
}

// ---------------------------------------------------------------------------
// Scalar encodings

/// f32 -> IEEE half bits, round to nearest even; values at or above 65504
/// saturate to the largest finite half (a training target must stay finite),
/// negative and NaN become 0 (the writer rejects those before this point).
pub fn f32_to_f16(x: f32) -> u16 {
    if x.is_nan() || x <= 0.0 {
        return 0;
    }
    half::f16::from_f32(x.min(65504.0)).to_bits()
}

pub fn f16_to_f32(h: u16) -> f32 {
    half::f16::from_bits(h).to_f32()
}

#[inline]
fn sign_nz(x: f32) -> f32 {
    if x >= 0.0 { 1.0 } else { -1.0 }
}

fn oct_decode_f(px: f32, py: f32) -> Vec3 {
    let z = 1.0 - px.abs() - py.abs();
    let (x, y) = if z < 0.0 { ((1.0 - py.abs()) * sign_nz(px), (1.0 - px.abs()) * sign_nz(py)) } else { (px, py) };
    Vec3::new(x, y, z).normalize()
}

/// Unit vector from its octahedral encoding.
pub fn oct_decode(e: [u16; 2]) -> Vec3 {
    let f = |q: u16| q as f32 * (2.0 / 65535.0) - 1.0;
    oct_decode_f(f(e[0]), f(e[1]))
}

/// Octahedral encoding of a unit vector in 2 x 16 bits. Of the four
/// roundings around the exact point the one that decodes closest to `v` is
/// kept ("precise" variant): it roughly halves the worst-case error.
pub fn oct_encode(v: Vec3) -> [u16; 2] {
    let n = v / (v.x.abs() + v.y.abs() + v.z.abs());
    let (px, py) = if n.z < 0.0 { ((1.0 - n.y.abs()) * sign_nz(n.x), (1.0 - n.x.abs()) * sign_nz(n.y)) } else { (n.x, n.y) };
    let to_q = |p: f32| ((p.clamp(-1.0, 1.0) + 1.0) * (65535.0 / 2.0)).clamp(0.0, 65535.0);
    let (qx, qy) = (to_q(px), to_q(py));
    let vn = v.normalize();
    let mut best = [qx.round() as u16, qy.round() as u16];
    let mut best_dot = -2.0f32;
    for ax in [qx.floor(), qx.ceil()] {
        for ay in [qy.floor(), qy.ceil()] {
            let cand = [ax as u16, ay as u16];
            let d = oct_decode(cand).dot(vn);
            if d > best_dot {
                best_dot = d;
                best = cand;
            }
        }
    }
    best
}

/// Bytes per stored bounce count: the narrowest that holds the cap.
fn bounce_width(max_internal_bounces: u32) -> usize {
    match max_internal_bounces {
        0..=0xff => 1,
        0x100..=0xffff => 2,
        _ => 4,
    }
}

// ---------------------------------------------------------------------------
// Chunk payload

/// The columns of one chunk (payload layout in `FORMAT.md`).
#[derive(Default)]
struct Columns {
    rays: u32,
    hits: u32,
    pairs: Vec<u8>,
    hit_bits: Vec<u8>,
    positions: Vec<u8>,
    directions: Vec<u8>,
    flags: Vec<u8>,
    bounces: Vec<u8>,
    throughput: Vec<u8>,
    radiance: Vec<u8>,
    /// Picked vertices, [`VERTEX_BYTES`] + bounce width each (empty in a
    /// data set without vertices).
    vertices: Vec<u8>,
}

/// A stored vertex before its bounce index: position 3 x f16 (signed),
/// normal and direction octahedral 2 x u16 each, throughput 3 x f16.
const VERTEX_BYTES: usize = 6 + 4 + 4 + 6;

/// Signed f32 -> f16 bits (a vertex position); non-finite becomes 0 (the
/// writer rejects those before this point).
fn f32_to_f16_signed(x: f32) -> u16 {
    if !x.is_finite() {
        return 0;
    }
    half::f16::from_f32(x).to_bits()
}

impl Columns {
    /// Empties the columns but keeps their capacity for the next chunk.
    fn clear(&mut self) {
        self.rays = 0;
        self.hits = 0;
        for c in self.columns_mut() {
            c.clear();
        }
    }

    fn columns_mut(&mut self) -> [&mut Vec<u8>; 9] {
        [
            &mut self.pairs,
            &mut self.hit_bits,
            &mut self.positions,
            &mut self.directions,
            &mut self.flags,
            &mut self.bounces,
            &mut self.throughput,
            &mut self.radiance,
            &mut self.vertices,
        ]
    }

    fn bytes(&self) -> usize {
        self.pairs.len()
            + self.hit_bits.len()
            + self.positions.len()
            + self.directions.len()
            + self.flags.len()
            + self.bounces.len()
            + self.throughput.len()
            + self.radiance.len()
            + self.vertices.len()
    }

    fn push(&mut self, rec: &RayRecord, max_b: u32, bw: usize) {
        let r = self.rays as usize;
        if r.is_multiple_of(8) {
            self.hit_bits.push(0);
        }
        if rec.hit {
            self.hit_bits[r / 8] |= 1 << (r % 8);
            self.hits += 1;
        }
        self.rays += 1;
        for x in rec.pair.0 {
            self.pairs.extend_from_slice(&x.to_le_bytes());
        }
        for e in &rec.exits {
            for q in oct_encode(e.position) {
                self.positions.extend_from_slice(&q.to_le_bytes());
            }
            for q in oct_encode(e.direction) {
                self.directions.extend_from_slice(&q.to_le_bytes());
            }
            let t = [e.throughput.x, e.throughput.y, e.throughput.z].map(f32_to_f16);
            let l = [e.radiance.x, e.radiance.y, e.radiance.z].map(f32_to_f16);
            let tn = t != [0; 3];
            let ln = l != [0; 3];
            self.flags.push(tn as u8 | (ln as u8) << 1);
            if tn {
                t.iter().for_each(|h| self.throughput.extend_from_slice(&h.to_le_bytes()));
            }
            if ln {
                l.iter().for_each(|h| self.radiance.extend_from_slice(&h.to_le_bytes()));
            }
            let b = e.bounces.min(max_b);
            self.bounces.extend_from_slice(&b.to_le_bytes()[..bw]);
        }
        for v in &rec.vertices {
            for x in [v.position.x, v.position.y, v.position.z] {
                self.vertices.extend_from_slice(&f32_to_f16_signed(x).to_le_bytes());
            }
            for q in oct_encode(v.normal).into_iter().chain(oct_encode(v.wo)) {
                self.vertices.extend_from_slice(&q.to_le_bytes());
            }
            for x in [v.beta.x, v.beta.y, v.beta.z] {
                self.vertices.extend_from_slice(&f32_to_f16(x).to_le_bytes());
            }
            self.vertices.extend_from_slice(&v.index.min(max_b).to_le_bytes()[..bw]);
        }
    }

    fn payload(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(self.bytes());
        for c in [
            &self.pairs,
            &self.hit_bits,
            &self.positions,
            &self.directions,
            &self.flags,
            &self.bounces,
            &self.throughput,
            &self.radiance,
            &self.vertices,
        ] {
            out.extend_from_slice(c);
        }
        out
    }
}

/// The rules every ray record of a data set keeps, for its header: checked
/// when it is written and again when it is read (a forged or damaged file
/// with valid checksums passed NaN vertices into training, which then
/// "diverged", and negative vertex throughput trained without a word).
pub(crate) fn check_record(header: &DatasetHeader, rec: &RayRecord) -> Result<(), String> {
    let want = if rec.hit { header.k as usize } else { 0 };
    if rec.exits.len() != want {
        return Err(format!("{} exits for a {} (k = {})", rec.exits.len(), if rec.hit { "hit" } else { "miss" }, header.k));
    }
    if !rec.pair.0.iter().all(|x| x.is_finite()) {
        return Err(format!("sphere pair {:?} is not finite", rec.pair.0));
    }
    let want_vertices = if header.vertices { rec.exits.len() } else { 0 };
    if rec.vertices.len() != want_vertices {
        return Err(format!(
            "{} picked vertices for {} exits (the header says the data set {} vertices)",
            rec.vertices.len(),
            rec.exits.len(),
            if header.vertices { "has" } else { "has no" }
        ));
    }
    for (i, v) in rec.vertices.iter().enumerate() {
        if !(v.position.is_finite() && v.position.abs().max_element() <= 1.0) {
            return Err(format!("vertex {i}: position {} is not inside the unit sphere's box", v.position));
        }
        for (name, d) in [("normal", v.normal), ("direction", v.wo)] {
            if !(d.is_finite() && d.abs().max_element() > 0.0) {
                return Err(format!("vertex {i}: {name} {d} is not a finite non-zero vector"));
            }
        }
        if !(v.beta.is_finite() && v.beta.min_element() >= 0.0) {
            return Err(format!("vertex {i}: throughput {} is not finite and >= 0", v.beta));
        }
    }
    for (i, e) in rec.exits.iter().enumerate() {
        for (name, v) in [("position", e.position), ("direction", e.direction)] {
            let l = v.abs().max_element();
            if !(v.is_finite() && l > 0.0) {
                return Err(format!("exit {i}: {name} {v} is not a finite non-zero vector"));
            }
        }
        for (name, v) in [("throughput", e.throughput), ("radiance", e.radiance)] {
            if !(v.is_finite() && v.min_element() >= 0.0) {
                return Err(format!("exit {i}: {name} {v} is not finite and >= 0"));
            }
        }
    }
    Ok(())
}

/// Splits a payload back into records. Every column's size is checked
/// against the payload before any record is allocated, so a damaged count
/// cannot ask for more memory than the (bounded) payload justifies.
fn decode_payload(p: &[u8], rays: u32, hits: u32, k: u32, bw: usize, with_vertices: bool) -> Result<Vec<RayRecord>, String> {
    let rays = rays as usize;
    let n_exits = hits as usize * k as usize;
    let mut at = 0usize;
    let mut take = |n: usize| -> Result<&[u8], String> {
        let s = at.checked_add(n).and_then(|end| p.get(at..end)).ok_or_else(|| format!("payload ends early ({} bytes)", p.len()))?;
        at += n;
        Ok(s)
    };
    let pairs = take(16 * rays)?;
    let hit_bits = take(rays.div_ceil(8))?;
    let positions = take(4 * n_exits)?;
    let directions = take(4 * n_exits)?;
    let flags = take(n_exits)?;
    let bounces = take(bw * n_exits)?;
    let n_t = flags.iter().filter(|f| *f & 1 != 0).count();
    let n_l = flags.iter().filter(|f| *f & 2 != 0).count();
    let thr = take(6 * n_t)?;
    let rad = take(6 * n_l)?;
    let verts = take(if with_vertices { (VERTEX_BYTES + bw) * n_exits } else { 0 })?;
    if at != p.len() {
        return Err(format!("{} unexpected bytes after the last column", p.len() - at));
    }
    let counted = (0..rays).filter(|r| hit_bits[r / 8] >> (r % 8) & 1 == 1).count();
    if counted != hits as usize {
        return Err(format!("hit bits say {counted} hits, chunk header {hits}"));
    }
    let u16_at = |s: &[u8], i: usize| u16::from_le_bytes([s[2 * i], s[2 * i + 1]]);
    let f32_at = |s: &[u8], i: usize| f32::from_le_bytes([s[4 * i], s[4 * i + 1], s[4 * i + 2], s[4 * i + 3]]);
    let color =
        |s: &[u8], i: usize| Vec3::new(f16_to_f32(u16_at(s, 3 * i)), f16_to_f32(u16_at(s, 3 * i + 1)), f16_to_f32(u16_at(s, 3 * i + 2)));
    let mut out = Vec::with_capacity(rays);
    let (mut e, mut ti, mut li) = (0usize, 0usize, 0usize);
    for r in 0..rays {
        let pair = SpherePair([f32_at(pairs, 4 * r), f32_at(pairs, 4 * r + 1), f32_at(pairs, 4 * r + 2), f32_at(pairs, 4 * r + 3)]);
        let hit = hit_bits[r / 8] >> (r % 8) & 1 == 1;
        let mut exits = Vec::with_capacity(if hit { k as usize } else { 0 });
        if hit {
            for _ in 0..k {
                let f = flags[e];
                let throughput = if f & 1 != 0 {
                    ti += 1;
                    color(thr, ti - 1)
                } else {
                    Vec3::ZERO
                };
                let radiance = if f & 2 != 0 {
                    li += 1;
                    color(rad, li - 1)
                } else {
                    Vec3::ZERO
                };
                let mut b = [0u8; 4];
                b[..bw].copy_from_slice(&bounces[bw * e..bw * (e + 1)]);
                exits.push(Exit {
                    position: oct_decode([u16_at(positions, 2 * e), u16_at(positions, 2 * e + 1)]),
                    direction: oct_decode([u16_at(directions, 2 * e), u16_at(directions, 2 * e + 1)]),
                    throughput,
                    radiance,
                    bounces: u32::from_le_bytes(b),
                });
                e += 1;
            }
        }
        let mut vertices = Vec::with_capacity(if hit && with_vertices { k as usize } else { 0 });
        if hit && with_vertices {
            let first = e - k as usize;
            for x in first..e {
                let s = &verts[(VERTEX_BYTES + bw) * x..(VERTEX_BYTES + bw) * (x + 1)];
                let h = |i: usize| u16::from_le_bytes([s[2 * i], s[2 * i + 1]]);
                let signed = |i: usize| half::f16::from_bits(h(i)).to_f32();
                let mut b = [0u8; 4];
                b[..bw].copy_from_slice(&s[VERTEX_BYTES..]);
                vertices.push(PickedVertex {
                    position: Vec3::new(signed(0), signed(1), signed(2)),
                    normal: oct_decode([h(3), h(4)]),
                    wo: oct_decode([h(5), h(6)]),
                    beta: Vec3::new(f16_to_f32(h(7)), f16_to_f32(h(8)), f16_to_f32(h(9))),
                    index: u32::from_le_bytes(b),
                });
            }
        }
        out.push(RayRecord { pair, hit, exits, vertices });
    }
    Ok(out)
}

// ---------------------------------------------------------------------------
// Header

/// The JSON header: the public header plus the sphere's exact bit patterns
/// (JSON floats are for people; the bake copies the sphere from here and it
/// must be bit-identical to what the generator used).
#[derive(Serialize, Deserialize)]
struct HeaderJson {
    #[serde(flatten)]
    header: DatasetHeader,
    sphere_bits: [u32; 4],
}

fn header_bytes(h: &DatasetHeader) -> Vec<u8> {
    let s = &h.sphere;
    let j = HeaderJson { header: h.clone(), sphere_bits: [s.center.x, s.center.y, s.center.z, s.radius].map(f32::to_bits) };
    // A JSON value made of strings, integers and finite floats always serializes.
    serde_json::to_vec(&j).unwrap_or_default()
}

impl DatasetHeader {
    /// What a data file's header must hold (a k the format allows, a finite
    /// sphere with a positive radius); a model folder's `meta.json` carries
    /// a copy, checked with this before it is baked.
    pub fn check(&self) -> Result<(), String> {
        check_header(self)
    }
}

fn check_header(h: &DatasetHeader) -> Result<(), String> {
    if h.k == 0 || h.k > MAX_K {
        return Err(format!("k = {} (1 to {MAX_K} allowed)", h.k));
    }
    let s = &h.sphere;
    if !(s.center.is_finite() && s.radius.is_finite() && s.radius > 0.0) {
        return Err(format!(
            "bounding sphere (centre [{} {} {}], radius {}) is not finite with a positive radius",
            s.center.x, s.center.y, s.center.z, s.radius
        ));
    }
    Ok(())
}

// ---------------------------------------------------------------------------
// Writer

pub struct DatasetWriter {
    path: PathBuf,
    file: Option<nppp_files::AtomicFile>,
    header: DatasetHeader,
    options: WriterOptions,
    bounce_width: usize,
    offset: u64,
    cols: Columns,
    index: Vec<(u64, u32, u32)>,
    rays: u64,
    hits: u64,
    raw_bytes: u64,
}

impl DatasetWriter {
    pub fn create(path: &Path, header: DatasetHeader) -> Result<Self, DatasetError> {
        Self::create_with(path, header, WriterOptions::default())
    }

    /// Writes to a temporary file next to `path`; [`Self::finish`] renames
    /// it into place, so an interrupted run never leaves a file that looks
    /// complete (and never destroys the previous good one).
    pub fn create_with(path: &Path, header: DatasetHeader, options: WriterOptions) -> Result<Self, DatasetError> {
        check_header(&header).map_err(|what| DatasetError::Header { path: path.into(), what })?;
        let io = |err| DatasetError::Io { path: path.into(), err };
        let mut file = nppp_files::AtomicFile::create(path).map_err(io)?;
        let json = header_bytes(&header);
        let mut prefix = Vec::with_capacity(20 + json.len());
        prefix.extend_from_slice(&DATASET_MAGIC);
        prefix.extend_from_slice(&DATASET_VERSION.to_le_bytes());
        prefix.extend_from_slice(&(json.len() as u32).to_le_bytes());
        prefix.extend_from_slice(&json);
        let crc = crc32fast::hash(&prefix[8..]);
        prefix.extend_from_slice(&crc.to_le_bytes());
        file.write_all(&prefix).map_err(io)?;
        let bounce_width = bounce_width(header.max_internal_bounces);
        let options = WriterOptions { chunk_rays: options.chunk_rays.clamp(1, MAX_CHUNK_RAYS), ..options };
        Ok(Self {
            path: path.into(),
            file: Some(file),
            header,
            options,
            bounce_width,
            offset: prefix.len() as u64,
            cols: Columns::default(),
            index: Vec::new(),
            rays: 0,
            hits: 0,
            raw_bytes: 0,
        })
    }

    pub fn header(&self) -> &DatasetHeader {
        &self.header
    }

    /// Rays written so far.
    pub fn len(&self) -> u64 {
        self.rays
    }

    pub fn is_empty(&self) -> bool {
        self.rays == 0
    }

    pub fn write(&mut self, rec: &RayRecord) -> Result<(), DatasetError> {
        self.check_record(rec).map_err(|what| DatasetError::Record { path: self.path.clone(), ray: self.rays, what })?;
        self.cols.push(rec, self.header.max_internal_bounces, self.bounce_width);
        self.rays += 1;
        self.hits += rec.hit as u64;
        // Chunks end at every multiple of `chunk_rays` rays (and earlier when
        // large): a shard that starts at such a multiple then chunks its rays
        // exactly as the whole run does, and shards merge by copying chunks.
        if self.rays.is_multiple_of(u64::from(self.options.chunk_rays)) || self.cols.bytes() >= CHUNK_TARGET_BYTES {
            self.flush_chunk()?;
        }
        Ok(())
    }

    /// Appends a chunk copied from another file of the same data set
    /// (merging shards). Only between chunks: the rays written so far must
    /// end at a chunk boundary.
    pub(crate) fn write_raw_chunk(&mut self, c: &RawChunk) -> Result<(), DatasetError> {
        let io = |err| DatasetError::Io { path: self.path.clone(), err };
        if self.cols.rays != 0 {
            return Err(io(std::io::Error::other("internal: copying a chunk into an open chunk")));
        }
        let f = self.file.as_mut().ok_or_else(|| io(std::io::Error::other("writer already finished")))?;
        f.write_all(&c.bytes).map_err(io)?;
        self.index.push((self.offset, c.rays, c.hits));
        self.offset += c.bytes.len() as u64;
        self.raw_bytes += c.raw_len as u64;
        self.rays += u64::from(c.rays);
        self.hits += u64::from(c.hits);
        Ok(())
    }

    fn check_record(&self, rec: &RayRecord) -> Result<(), String> {
        check_record(&self.header, rec)
    }

    fn flush_chunk(&mut self) -> Result<(), DatasetError> {
        if self.cols.rays == 0 {
            return Ok(());
        }
        let raw = self.cols.payload();
        // Level 1: most of the gain at several hundred MB/s, far faster than
        // the path tracing that produces the data.
        let z = if self.options.compress { Some(miniz_oxide::deflate::compress_to_vec(&raw, 1)) } else { None };
        let (enc, stored): (u32, &[u8]) = match &z {
            Some(z) if z.len() < raw.len() => (ENC_DEFLATE, z),
            _ => (ENC_RAW, &raw),
        };
        let mut head = [0u8; CHUNK_HEADER_LEN];
        head[..4].copy_from_slice(&CHUNK_MAGIC);
        for (i, v) in [self.cols.rays, self.cols.hits, enc, stored.len() as u32, raw.len() as u32].into_iter().enumerate() {
            head[4 + 4 * i..8 + 4 * i].copy_from_slice(&v.to_le_bytes());
        }
        let mut h = crc32fast::Hasher::new();
        h.update(&head[4..24]);
        h.update(stored);
        head[24..28].copy_from_slice(&h.finalize().to_le_bytes());
        let io = |err| DatasetError::Io { path: self.path.clone(), err };
        let f = self.file.as_mut().ok_or_else(|| io(std::io::Error::other("writer already finished")))?;
        f.write_all(&head).map_err(io)?;
        f.write_all(stored).map_err(io)?;
        self.index.push((self.offset, self.cols.rays, self.cols.hits));
        self.offset += (CHUNK_HEADER_LEN + stored.len()) as u64;
        self.raw_bytes += raw.len() as u64;
        self.cols.clear();
        Ok(())
    }

    /// Writes the last chunk, the chunk index and the trailer, then moves the
    /// file into place.
    pub fn finish(mut self) -> Result<DatasetSummary, DatasetError> {
        self.flush_chunk()?;
        let mut tail = Vec::with_capacity(self.index.len() * INDEX_ENTRY_LEN + TRAILER_LEN);
        for &(off, rays, hits) in &self.index {
            tail.extend_from_slice(&off.to_le_bytes());
            tail.extend_from_slice(&rays.to_le_bytes());
            tail.extend_from_slice(&hits.to_le_bytes());
        }
        for v in [self.offset, self.index.len() as u64, self.rays, self.hits] {
            tail.extend_from_slice(&v.to_le_bytes());
        }
        let crc = crc32fast::hash(&tail);
        tail.extend_from_slice(&crc.to_le_bytes());
        tail.extend_from_slice(&END_MAGIC);
        let io = |err| DatasetError::Io { path: self.path.clone(), err };
        let f = self.file.take().ok_or_else(|| io(std::io::Error::other("writer already finished")))?;
        let done = (|| {
            let mut f = f;
            f.write_all(&tail)?;
            if self.options.replace { f.commit() } else { f.commit_new() }
        })();
        done.map_err(io)?;
        Ok(DatasetSummary {
            path: self.path.clone(),
            rays: self.rays,
            hits: self.hits,
            exits: self.hits * self.header.k as u64,
            chunks: self.index.len() as u64,
            file_bytes: self.offset + tail.len() as u64,
            raw_bytes: self.raw_bytes,
        })
    }
}

// ---------------------------------------------------------------------------
// Reader

#[derive(Clone, Copy, Debug)]
struct ChunkEntry {
    offset: u64,
    rays: u32,
    hits: u32,
}

/// A chunk as stored in a file: its header and payload, checked.
pub(crate) struct RawChunk {
    pub bytes: Vec<u8>,
    pub rays: u32,
    pub hits: u32,
    pub raw_len: usize,
}

/// Anything a data file can be read from (a file, or bytes in memory).
pub trait ReadSeek: Read + Seek + Send {}
impl<T: Read + Seek + Send> ReadSeek for T {}

/// Streams a training-data file chunk by chunk.
pub struct DatasetReader {
    path: PathBuf,
    file: Box<dyn ReadSeek>,
    header: DatasetHeader,
    index: Vec<ChunkEntry>,
    index_offset: u64,
    next: usize,
    rays: u64,
    hits: u64,
}

fn le_u32(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]])
}

fn le_u64(b: &[u8], at: usize) -> u64 {
    let mut x = [0u8; 8];
    x.copy_from_slice(&b[at..at + 8]);
    u64::from_le_bytes(x)
}

impl DatasetReader {
    /// Reads and checks the header, the trailer and the chunk index; chunk
    /// payloads are read (and checked) only when asked for.
    pub fn open(path: &Path) -> Result<Self, DatasetError> {
        let io = |err| DatasetError::Io { path: path.into(), err };
        let f = nppp_files::open_regular(path).map_err(io)?;
        let len = f.metadata().map_err(io)?.len();
        Self::from_source(Box::new(BufReader::with_capacity(1 << 20, f)), len, path)
    }

    /// A data set held in memory; `path` only names it in errors.
    pub fn from_bytes(bytes: Vec<u8>, path: &Path) -> Result<Self, DatasetError> {
        let len = bytes.len() as u64;
        Self::from_source(Box::new(std::io::Cursor::new(bytes)), len, path)
    }

    /// Reads from `file`, which holds `len` bytes.
    pub fn from_source(mut file: Box<dyn ReadSeek>, len: u64, path: &Path) -> Result<Self, DatasetError> {
        let p = || path.to_path_buf();
        let io = |err| DatasetError::Io { path: p(), err };
        let mut prefix = [0u8; 16];
        let got = read_up_to(&mut file, &mut prefix).map_err(io)?;
        if prefix[..got.min(8)] != DATASET_MAGIC[..got.min(8)] {
            return Err(DatasetError::Magic { path: p() });
        }
        if got < 16 {
            return Err(DatasetError::Index { path: p(), what: format!("truncated: file is {len} bytes, the fixed prefix alone is 16") });
        }
        let version = le_u32(&prefix, 8);
        if !(DATASET_VERSION_MIN..=DATASET_VERSION).contains(&version) {
            return Err(DatasetError::Version { path: p(), found: version });
        }
        let hlen = le_u32(&prefix, 12) as usize;
        if hlen > MAX_HEADER_LEN {
            return Err(DatasetError::Header { path: p(), what: format!("header length {hlen} is absurd") });
        }
        let data_start = 16 + hlen as u64 + 4;
        if data_start + TRAILER_LEN as u64 > len {
            return Err(DatasetError::Header {
                path: p(),
                what: format!("truncated: header says {hlen} header bytes, file is {len} bytes"),
            });
        }
        let mut hbuf = vec![0u8; hlen + 4];
        file.read_exact(&mut hbuf).map_err(io)?;
        let mut crc = crc32fast::Hasher::new();
        crc.update(&prefix[8..16]);
        crc.update(&hbuf[..hlen]);
        if crc.finalize() != le_u32(&hbuf, hlen) {
            return Err(DatasetError::Header { path: p(), what: "checksum mismatch (file corrupted)".into() });
        }
        let hj: HeaderJson = serde_json::from_slice(&hbuf[..hlen]).map_err(|e| DatasetError::Header { path: p(), what: e.to_string() })?;
        let mut header = hj.header;
        let b = hj.sphere_bits.map(f32::from_bits);
        header.sphere = BoundingSphere { center: Vec3::new(b[0], b[1], b[2]), radius: b[3] };
        check_header(&header).map_err(|what| DatasetError::Header { path: p(), what })?;
        if header.vertices && version < 2 {
            return Err(DatasetError::Header {
                path: p(),
                what: format!("\"vertices\" in a version {version} file (vertices came with version 2)"),
            });
        }

        // Trailer, then the index it points to.
        let incomplete = |what: String| DatasetError::Index { path: p(), what };
        let mut trailer = [0u8; TRAILER_LEN];
        file.seek(SeekFrom::Start(len - TRAILER_LEN as u64)).map_err(io)?;
        file.read_exact(&mut trailer).map_err(io)?;
        if trailer[36..40] != END_MAGIC {
            return Err(incomplete("no chunk index at the end (file truncated, or its writer did not finish)".into()));
        }
        let (index_offset, chunks, rays, hits) = (le_u64(&trailer, 0), le_u64(&trailer, 8), le_u64(&trailer, 16), le_u64(&trailer, 24));
        let index_len = chunks.checked_mul(INDEX_ENTRY_LEN as u64);
        let expect_len = index_len.and_then(|l| index_offset.checked_add(l)).and_then(|e| e.checked_add(TRAILER_LEN as u64));
        if expect_len != Some(len) || index_offset < data_start {
            return Err(incomplete(format!(
                "index of {chunks} chunks at byte {index_offset} does not fit a {len}-byte file (truncated or corrupted)"
            )));
        }
        // Fits in the file, so this allocation is bounded by the file's size.
        let mut ibuf = vec![0u8; (len - index_offset) as usize];
        file.seek(SeekFrom::Start(index_offset)).map_err(io)?;
        file.read_exact(&mut ibuf).map_err(io)?;
        let body = ibuf.len() - 8;
        if crc32fast::hash(&ibuf[..body]) != le_u32(&ibuf, body) {
            return Err(incomplete("chunk index checksum mismatch (file corrupted)".into()));
        }
        let mut index = Vec::with_capacity(chunks as usize);
        let (mut sum_r, mut sum_h) = (0u64, 0u64);
        for c in 0..chunks as usize {
            let e = ChunkEntry { offset: le_u64(&ibuf, 16 * c), rays: le_u32(&ibuf, 16 * c + 8), hits: le_u32(&ibuf, 16 * c + 12) };
            let prev_end = index.last().map_or(data_start, |q: &ChunkEntry| q.offset + CHUNK_HEADER_LEN as u64);
            if (c == 0 && e.offset != data_start)
                || e.offset < prev_end
                || e.offset.checked_add(CHUNK_HEADER_LEN as u64).is_none_or(|end| end > index_offset)
            {
                return Err(incomplete(format!("chunk index entry {c} points at byte {} (out of order or outside the data)", e.offset)));
            }
            if e.rays == 0 || e.rays > MAX_CHUNK_RAYS || e.hits > e.rays {
                return Err(incomplete(format!("chunk index entry {c} claims {} rays and {} hits", e.rays, e.hits)));
            }
            sum_r += e.rays as u64;
            sum_h += e.hits as u64;
            index.push(e);
        }
        if sum_r != rays || sum_h != hits {
            return Err(incomplete(format!("chunk index sums to {sum_r} rays / {sum_h} hits, trailer says {rays} / {hits}")));
        }
        if chunks == 0 && index_offset != data_start {
            return Err(incomplete("bytes between the header and an empty index".into()));
        }
        Ok(Self { path: p(), file, header, index, index_offset, next: 0, rays, hits })
    }

    pub fn header(&self) -> &DatasetHeader {
        &self.header
    }

    /// Number of rays (hits and misses).
    pub fn len(&self) -> usize {
        self.rays as usize
    }

    pub fn is_empty(&self) -> bool {
        self.rays == 0
    }

    pub fn hit_count(&self) -> u64 {
        self.hits
    }

    pub fn exit_count(&self) -> u64 {
        self.hits * self.header.k as u64
    }

    pub fn chunk_count(&self) -> usize {
        self.index.len()
    }

    /// Rays in chunk `i` (for shuffling at chunk granularity).
    pub fn chunk_rays(&self, i: usize) -> Option<u32> {
        self.index.get(i).map(|e| e.rays)
    }

    /// Starts streaming from the first chunk again (one epoch = one pass).
    pub fn rewind(&mut self) {
        self.next = 0;
    }

    /// The next chunk's records; `None` after the last one. After an error
    /// the stream ends (a corrupted chunk is reported once, not forever).
    pub fn next_chunk(&mut self) -> Option<Result<Vec<RayRecord>, DatasetError>> {
        if self.next >= self.index.len() {
            return None;
        }
        let i = self.next;
        let r = self.read_chunk(i);
        self.next = if r.is_ok() { i + 1 } else { self.index.len() };
        Some(r)
    }

    /// Chunk `i`, read and checked on its own (random access).
    pub fn read_chunk(&mut self, i: usize) -> Result<Vec<RayRecord>, DatasetError> {
        let c = self.read_raw_chunk(i)?;
        let offset = self.index[i].offset;
        let err = |what: String| DatasetError::Chunk { path: self.path.clone(), chunk: i as u64, offset, what };
        let stored = &c.bytes[CHUNK_HEADER_LEN..];
        let raw = match le_u32(&c.bytes, 12) {
            ENC_RAW => stored.to_vec(),
            ENC_DEFLATE => {
                let raw = miniz_oxide::inflate::decompress_to_vec_with_limit(stored, c.raw_len)
                    .map_err(|e| err(format!("cannot inflate: {e}")))?;
                if raw.len() != c.raw_len {
                    return Err(err(format!("inflates to {} bytes, header says {}", raw.len(), c.raw_len)));
                }
                raw
            }
            other => return Err(err(format!("unknown payload encoding {other}"))),
        };
        let records =
            decode_payload(&raw, c.rays, c.hits, self.header.k, bounce_width(self.header.max_internal_bounces), self.header.vertices)
                .map_err(err)?;
        for (j, rec) in records.iter().enumerate() {
            check_record(&self.header, rec).map_err(|what| err(format!("ray {j} of the chunk: {what}")))?;
        }
        Ok(records)
    }

    /// Chunk `i` as stored, its header and payload checked (marker, sizes,
    /// CRC, counts against the index) but not decoded: what merging shards
    /// copies, so that the merged file is the single run's byte for byte.
    pub(crate) fn read_raw_chunk(&mut self, i: usize) -> Result<RawChunk, DatasetError> {
        let e = *self.index.get(i).ok_or_else(|| DatasetError::Index {
            path: self.path.clone(),
            what: format!("no chunk {i} (file has {})", self.index.len()),
        })?;
        let err = |what: String| DatasetError::Chunk { path: self.path.clone(), chunk: i as u64, offset: e.offset, what };
        let end = self.index.get(i + 1).map_or(self.index_offset, |n| n.offset);
        let span = (end - e.offset) as usize;
        self.file.seek(SeekFrom::Start(e.offset)).map_err(|s| err(s.to_string()))?;
        let mut head = [0u8; CHUNK_HEADER_LEN];
        self.file.read_exact(&mut head).map_err(|s| err(s.to_string()))?;
        if head[..4] != CHUNK_MAGIC {
            return Err(err("no chunk marker (file corrupted)".into()));
        }
        let (rays, hits, stored_len, raw_len, crc) =
            (le_u32(&head, 4), le_u32(&head, 8), le_u32(&head, 16) as usize, le_u32(&head, 20) as usize, le_u32(&head, 24));
        if stored_len != span - CHUNK_HEADER_LEN {
            return Err(err(format!(
                "chunk header says {stored_len} payload bytes, {} present before the next chunk",
                span - CHUNK_HEADER_LEN
            )));
        }
        if raw_len > MAX_CHUNK_RAW {
            return Err(err(format!("chunk claims {raw_len} uncompressed bytes (limit {MAX_CHUNK_RAW})")));
        }
        // Bounded by the file's own size (checked against the index above).
        let mut bytes = vec![0u8; span];
        bytes[..CHUNK_HEADER_LEN].copy_from_slice(&head);
        self.file.read_exact(&mut bytes[CHUNK_HEADER_LEN..]).map_err(|s| err(s.to_string()))?;
        let mut h = crc32fast::Hasher::new();
        h.update(&head[4..24]);
        h.update(&bytes[CHUNK_HEADER_LEN..]);
        if h.finalize() != crc {
            return Err(err("checksum mismatch (file corrupted)".into()));
        }
        if rays != e.rays || hits != e.hits {
            return Err(err(format!("chunk says {rays} rays / {hits} hits, index {} / {}", e.rays, e.hits)));
        }
        Ok(RawChunk { bytes, rays, hits, raw_len })
    }

    /// Every record, from the first chunk (memory: the whole data set).
    pub fn read_all(&mut self) -> Result<Vec<RayRecord>, DatasetError> {
        self.rewind();
        let mut out = Vec::with_capacity(self.rays.min(1 << 24) as usize);
        while let Some(c) = self.next_chunk() {
            out.extend(c?);
        }
        Ok(out)
    }
}

fn read_up_to(r: &mut impl Read, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut n = 0;
    while n < buf.len() {
        match r.read(&mut buf[n..])? {
            0 => break,
            k => n += k,
        }
    }
    Ok(n)
}

#[cfg(test)]
mod tests;
