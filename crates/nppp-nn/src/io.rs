//! Reading training data files and the model directory's identity file.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use indicatif::{ProgressBar, ProgressStyle};
use nppp_estimator::{DatasetHeader, DatasetReader, ExitTransform};
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
}

impl ModelMeta {
    pub const FORMAT: &'static str = "nppp-model";

    pub fn new(dataset: DatasetInfo, transform: ExitTransform, data_path: PathBuf) -> Self {
        Self {
            format: Self::FORMAT.into(),
            version: 1,
            dataset,
            data_path: std::path::absolute(&data_path).unwrap_or(data_path),
            transform,
            input_features: crate::features::INPUT_FEATURES,
        }
    }
}

/// Reads a whole data file (a progress bar on stderr unless `quiet`).
pub fn load_dataset(path: &Path, quiet: bool) -> Result<(DatasetInfo, Vec<RaySample>)> {
    load_dataset_where(path, quiet, |_| true)
}

/// Reads the rays of a data file whose index passes `keep` (streaming, so
/// that reading only the held-out rays does not hold the whole file).
pub fn load_dataset_where(
    path: &Path,
    quiet: bool,
    keep: impl Fn(usize) -> bool,
) -> Result<(DatasetInfo, Vec<RaySample>)> {
    if !path.is_file() {
        bail!(
            "training data {} does not exist (run `nppp gen` / `make data` first)",
            path.display()
        );
    }
    let mut reader = DatasetReader::open(path)?;
    let header = reader.header().clone();
    let pb = if quiet {
        ProgressBar::hidden()
    } else {
        let pb = ProgressBar::new(reader.chunk_count() as u64);
        pb.set_style(
            ProgressStyle::with_template("read {bar:30} {pos}/{len} chunks {msg}")
                .expect("static template"),
        );
        pb
    };
    let mut rays = Vec::new();
    let mut index = 0usize;
    while let Some(chunk) = reader.next_chunk() {
        for r in chunk.with_context(|| format!("reading {}", path.display()))? {
            if keep(index) {
                rays.push(r);
            }
            index += 1;
        }
        pb.inc(1);
    }
    pb.finish_and_clear();
    if rays.is_empty() {
        bail!("{} holds no rays", path.display());
    }
    Ok((header, rays))
}
