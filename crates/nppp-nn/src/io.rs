//! Reading training data files and the model directory's identity file.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use indicatif::ProgressBar;
use nppp_estimator::{DatasetHeader, DatasetReader, ExitTransform, VertexTransform};
use nppp_geom::BoundingSphere;
use serde::{Deserialize, Serialize};

use crate::data::RaySample;

/// What the data file says about the object it was generated from; kept in
/// the model directory so that `bake` can stamp the estimator with the mesh
/// and material it is valid for, without the data file.
pub type DatasetInfo = DatasetHeader;

/// A header for synthetic data (tests, tools): unit sphere, zero hashes.
pub fn synthetic_header(name: &str, k: usize) -> DatasetInfo {
    DatasetHeader {
        mesh_name: name.into(),
        mesh_hash: 0,
        material_name: "synthetic".into(),
        material_hash: 0,
        material_json: "{}".into(),
        sphere: BoundingSphere {
            center: glam::Vec3::ZERO,
            radius: 1.0,
        },
        k: k as u32,
        seed: 0,
        max_internal_bounces: 64,
        shard: None,
        vertices: false,
    }
}

/// `meta.json` of a model directory.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ModelMeta {
    pub format: String,
    pub version: u32,
    pub dataset: DatasetInfo,
    /// Where the training data was (bake reads its held-out rays from here
    /// unless told otherwise).
    pub data_path: PathBuf,
    /// The target transform the decoder's outputs are expressed in.
    pub transform: ExitTransform,
    pub input_features: usize,
    /// The vertex head's target transform (a model trained on data with
    /// picked vertices); absent in older model folders.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub vertex_transform: Option<VertexTransform>,
}

impl ModelMeta {
    pub const FORMAT: &'static str = "nppp-model";
    /// The meta.json version this build writes and reads.
    pub const VERSION: u32 = 1;

    pub fn new(dataset: DatasetInfo, transform: ExitTransform, data_path: PathBuf) -> Self {
        Self {
            format: Self::FORMAT.into(),
            version: Self::VERSION,
            dataset,
            data_path: std::path::absolute(&data_path).unwrap_or(data_path),
            transform,
            input_features: crate::features::INPUT_FEATURES,
            vertex_transform: None,
        }
    }
}

/// Reads a whole data file (a progress bar on stderr unless `quiet`).
pub fn load_dataset(path: &Path, quiet: bool) -> Result<(DatasetInfo, Vec<RaySample>)> {
    load_dataset_where(path, quiet, 1.0, |_| true)
}

/// Memory held per ray and per exit while a data file is loaded and turned
/// into training arrays: the record, its features and pair; per exit the
/// decoded record, its encoded features, and the raw copy kept for
/// evaluation. An upper bound, from the types' sizes.
const MEM_PER_RAY: u64 = (size_of::<RaySample>()
    + size_of::<nppp_geom::SpherePair>()
    + 4 * crate::features::INPUT_FEATURES
    + 16) as u64;
const MEM_PER_EXIT: u64 = (2 * size_of::<nppp_estimator::Exit>()
    + 4 * nppp_estimator::EXIT_FEATURES
    + size_of::<nppp_estimator::PickedVertex>()
    + 4 * nppp_estimator::VERTEX_FEATURES) as u64;

/// How many times its own size a data file may claim in memory. Real files
/// take 10 to 20 times their size once loaded (exits are stored in about 8
/// compressed bytes and held in about 150); a file that claims more was
/// forged or damaged (deflate turns a megabyte of zeros into a gigabyte).
pub const MAX_MEMORY_PER_FILE_BYTE: u64 = 128;
/// Claims below this are never refused for their ratio (tiny files).
const SMALL_CLAIM: u64 = 64 << 20;

/// Bytes needed to load `share` of a file of `rays` rays, `hits` of them
/// with `k` exits each.
pub fn memory_to_load(rays: u64, hits: u64, k: u64, share: f64) -> u64 {
    let all = rays
        .saturating_mul(MEM_PER_RAY)
        .saturating_add(hits.saturating_mul(k).saturating_mul(MEM_PER_EXIT));
    (all as f64 * share.clamp(0.0, 1.0)).ceil() as u64
}

/// Refuses a data file whose claims (rays, hits, k) would need more memory
/// than its size can hold or than the machine has, before reading it.
fn check_claims(path: &Path, reader: &DatasetReader, share: f64) -> Result<()> {
    let file_bytes = std::fs::metadata(path).map(|m| m.len()).unwrap_or(0);
    let (rays, hits, k) = (
        reader.len() as u64,
        reader.hit_count(),
        reader.header().k as u64,
    );
    let need = memory_to_load(rays, hits, k, share);
    let claim = memory_to_load(rays, hits, k, 1.0);
    let what = format!("{rays} rays, {hits} of them hits with k = {k} exits each");
    if claim > SMALL_CLAIM && claim / MAX_MEMORY_PER_FILE_BYTE > file_bytes {
        bail!(
            "{}: claims {what}, which would take {} in memory from a {} file (more than \
             {MAX_MEMORY_PER_FILE_BYTE}x its size; real data takes 10-20x): the file is damaged \
             or forged. Regenerate it with `nppp gen`",
            path.display(),
            nppp_files::format_bytes(claim),
            nppp_files::format_bytes(file_bytes)
        );
    }
    if let Some(avail) = nppp_files::available_memory()
        && need > avail
    {
        bail!(
            "{}: holds {what}; loading it needs about {}, more than the {} of memory available. \
             Generate fewer rays or a smaller k (`nppp gen --rays N --k K`), or use a machine \
             with more memory",
            path.display(),
            nppp_files::format_bytes(need),
            nppp_files::format_bytes(avail)
        );
    }
    Ok(())
}

/// Reads the rays of a data file whose index passes `keep` (streaming, so
/// that reading only the held-out rays does not hold the whole file).
/// `share` is the fraction of the rays `keep` passes, for the memory check.
/// A file with no rays is an error; one whose rays `keep` all refuses gives
/// none (the caller knows what it asked for).
pub fn load_dataset_where(
    path: &Path,
    quiet: bool,
    share: f64,
    keep: impl Fn(usize) -> bool,
) -> Result<(DatasetInfo, Vec<RaySample>)> {
    if path.is_dir() {
        bail!(
            "training data {} is a directory; name the .nppd file `nppp gen --out` wrote",
            path.display()
        );
    }
    if !path.exists() {
        bail!(
            "training data {} does not exist (run `nppp gen` / `make data` first)",
            path.display()
        );
    }
    nppp_files::check_regular(path).with_context(|| format!("training data {}", path.display()))?;
    let mut reader = DatasetReader::open(path)?;
    check_claims(path, &reader, share)?;
    let header = reader.header().clone();
    let pb = if quiet {
        ProgressBar::hidden()
    } else {
        let pb = ProgressBar::new(reader.chunk_count() as u64);
        pb.set_style(nppp_files::progress_style(
            "read {bar:30} {pos}/{len} chunks {msg}",
            "chunks",
        ));
        pb
    };
    let mut rays = Vec::new();
    let mut index = 0usize;
    while let Some(chunk) = reader.next_chunk() {
        // Every reader error names the file already: no context of our own.
        for r in chunk? {
            if keep(index) {
                rays.push(r);
            }
            index += 1;
        }
        pb.inc(1);
    }
    pb.finish_and_clear();
    if index == 0 {
        bail!("{} holds no rays", path.display());
    }
    Ok((header, rays))
}
