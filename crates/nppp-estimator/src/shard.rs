//! Shards of a training-data set: `nppp gen --shard I/K` traces the I-th of
//! K ranges of the input rays into a file of its own; [`merge_datasets`]
//! writes the one file a single run would have written, byte for byte.
//!
//! Every input ray's random stream is keyed by (seed, ray index), so a range
//! of rays is traced the same wherever it runs; ranges start at multiples of
//! the chunk size, where the single run's chunks also start
//! ([`crate::DatasetWriter`] ends a chunk at every such multiple), so the
//! merge copies the shards' chunks as stored, in ray order.

use crate::dataset::{DatasetError, DatasetHeader, DatasetReader, DatasetSummary, DatasetWriter, WriterOptions};
use serde::{Deserialize, Serialize};
use std::ops::Range;
use std::path::Path;

/// Which rays of a data set a shard holds, and how the whole set is chunked.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DatasetShard {
    /// The shard's first ray and one past its last, of `0..rays`.
    pub first_ray: u64,
    pub end_ray: u64,
    /// Rays of the whole data set.
    pub rays: u64,
    /// The writer's chunk size (a shard starts at a multiple of it).
    pub chunk_rays: u32,
    /// Whether chunks are deflated (the merged file is written the same way).
    pub compress: bool,
}

/// Rays of shard `index` of `count` over `0..rays`: whole chunks of
/// `chunk_rays`, the chunk counts of the shards differing by at most one.
/// `Err` says why there cannot be `count` shards.
pub fn shard_rays(index: u32, count: u32, rays: u64, chunk_rays: u32) -> Result<Range<u64>, String> {
    let chunk = u64::from(chunk_rays.max(1));
    let chunks = rays.div_ceil(chunk);
    if count == 0 || index >= count {
        return Err(format!("shard {index} of {count} does not exist (shards are numbered 0 to K-1)"));
    }
    if u64::from(count) > chunks {
        return Err(format!(
            "{rays} rays make {chunks} chunk(s) of {chunk_rays} rays, and a shard is whole chunks: \
             use at most {chunks} shards (or more --rays)"
        ));
    }
    let at = |i: u32| (u64::from(i) * chunks / u64::from(count) * chunk).min(rays);
    Ok(at(index)..at(index + 1))
}

fn merge_err(msg: String) -> DatasetError {
    DatasetError::Merge(msg)
}

/// Merges the shards at `parts` (any order) into `out`: checks that they are
/// shards of one data set (same object, recipe and seed) that hold each of
/// its rays exactly once, then copies their chunks in ray order. `replace`:
/// put `out` in place over a file there (see [`WriterOptions::replace`]).
pub fn merge_datasets(parts: &[&Path], out: &Path, replace: bool) -> Result<DatasetSummary, DatasetError> {
    if parts.is_empty() {
        return Err(merge_err("no parts to merge".into()));
    }
    let mut readers = Vec::with_capacity(parts.len());
    for p in parts {
        let r = DatasetReader::open(p)?;
        let Some(s) = r.header().shard else {
            return Err(merge_err(format!(
                "{} is a whole data set, not a shard (written by `nppp gen --shard I/K`): nothing to merge it with",
                p.display()
            )));
        };
        if r.len() as u64 != s.end_ray - s.first_ray {
            return Err(merge_err(format!(
                "{} holds {} rays, its header says rays {}..{}: the file is damaged",
                p.display(),
                r.len(),
                s.first_ray,
                s.end_ray
            )));
        }
        readers.push((*p, s, r));
    }
    let first_header = unsharded(readers[0].2.header());
    let first_shard = readers[0].1;
    for (p, s, r) in &readers[1..] {
        let h = unsharded(r.header());
        if h != first_header || (s.rays, s.chunk_rays, s.compress) != (first_shard.rays, first_shard.chunk_rays, first_shard.compress) {
            return Err(merge_err(format!(
                "{} is not a shard of the data set {} is a shard of: {}",
                p.display(),
                readers[0].0.display(),
                header_difference(&first_header, &first_shard, &h, s)
            )));
        }
    }
    let ranges: Vec<Range<u64>> = readers.iter().map(|(_, s, _)| s.first_ray..s.end_ray).collect();
    match check_cover(&ranges, first_shard.rays) {
        Ok(()) => {}
        Err(CoverError::Gap(g)) => {
            return Err(merge_err(format!(
                "rays {}..{} of the {} are in no part: generate them with --shard (or name the missing part)",
                g.start, g.end, first_shard.rays
            )));
        }
        Err(CoverError::Overlap { a, b, overlap }) => {
            let (pa, pb) = (readers[a].0, readers[b].0);
            return Err(merge_err(format!(
                "{} (rays {}..{}) and {} (rays {}..{}) overlap: rays {}..{} would be in the data twice",
                pa.display(),
                ranges[a].start,
                ranges[a].end,
                pb.display(),
                ranges[b].start,
                ranges[b].end,
                overlap.start,
                overlap.end
            )));
        }
    }
    readers.sort_by_key(|(_, s, _)| (s.first_ray, s.end_ray));
    let options = WriterOptions { chunk_rays: first_shard.chunk_rays, compress: first_shard.compress, replace };
    let mut w = DatasetWriter::create_with(out, first_header, options)?;
    for (_, _, r) in &mut readers {
        for c in 0..r.chunk_count() {
            let chunk = r.read_raw_chunk(c)?;
            w.write_raw_chunk(&chunk)?;
        }
    }
    w.finish()
}

/// Why parts do not hold each of `0..total` exactly once.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum CoverError {
    /// This range is in no part.
    Gap(Range<u64>),
    /// Parts `a` and `b` (indices into the list given) share `overlap`.
    Overlap { a: usize, b: usize, overlap: Range<u64> },
}

/// Checks that `ranges`, in any order, cover `0..total` with each value in
/// exactly one of them (render parts' samples, data shards' rays). Reports
/// the first gap or overlap in increasing order.
pub fn check_cover(ranges: &[Range<u64>], total: u64) -> Result<(), CoverError> {
    let mut order: Vec<usize> = (0..ranges.len()).collect();
    order.sort_by_key(|&i| (ranges[i].start, ranges[i].end));
    let mut covered = 0u64;
    let mut last: Option<usize> = None;
    for &i in &order {
        let r = &ranges[i];
        if r.start > covered {
            return Err(CoverError::Gap(covered..r.start));
        }
        if let Some(j) = last.filter(|_| r.start < covered) {
            return Err(CoverError::Overlap { a: j, b: i, overlap: r.start..covered.min(r.end) });
        }
        covered = covered.max(r.end);
        last = Some(i);
    }
    if covered < total {
        return Err(CoverError::Gap(covered..total));
    }
    Ok(())
}

fn unsharded(h: &DatasetHeader) -> DatasetHeader {
    DatasetHeader { shard: None, ..h.clone() }
}

/// The first field in which two shards' headers differ, for the message.
fn header_difference(a: &DatasetHeader, sa: &DatasetShard, b: &DatasetHeader, sb: &DatasetShard) -> String {
    let pairs = [
        ("mesh", format!("{} ({:016x})", a.mesh_name, a.mesh_hash), format!("{} ({:016x})", b.mesh_name, b.mesh_hash)),
        ("material", format!("{} ({:016x})", a.material_name, a.material_hash), format!("{} ({:016x})", b.material_name, b.material_hash)),
        ("k", a.k.to_string(), b.k.to_string()),
        ("seed", a.seed.to_string(), b.seed.to_string()),
        ("max_internal_bounces", a.max_internal_bounces.to_string(), b.max_internal_bounces.to_string()),
        ("rays in the data set", sa.rays.to_string(), sb.rays.to_string()),
        ("chunk size", sa.chunk_rays.to_string(), sb.chunk_rays.to_string()),
        ("compression", sa.compress.to_string(), sb.compress.to_string()),
    ];
    pairs
        .iter()
        .find(|(_, x, y)| x != y)
        .map(|(k, x, y)| format!("{k} {y} where the first part has {x}"))
        .unwrap_or_else(|| "the bounding sphere or material description differs".into())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shards_are_whole_chunks_covering_every_ray() {
        for (rays, chunk, k) in [(10_000u64, 4096u32, 3u32), (8192, 4096, 2), (100, 7, 5), (100, 7, 15), (1, 4096, 1)] {
            let mut at = 0;
            for i in 0..k {
                let r = shard_rays(i, k, rays, chunk).unwrap();
                assert_eq!(r.start, at);
                assert!(r.start.is_multiple_of(u64::from(chunk)));
                assert!(r.end > r.start, "{rays} {chunk} {k}: shard {i} empty");
                at = r.end;
            }
            assert_eq!(at, rays);
        }
        assert!(shard_rays(0, 4, 10_000, 4096).unwrap_err().contains("at most 3 shards"));
        assert!(shard_rays(4, 4, 10_000, 4096).is_err());
    }

    #[test]
    fn cover_finds_gaps_and_overlaps_in_any_order() {
        assert_eq!(check_cover(&[4..6, 0..2, 2..4], 6), Ok(()));
        assert_eq!(check_cover(&[4..6, 0..2], 6), Err(CoverError::Gap(2..4)));
        assert_eq!(check_cover(&[0..2, 2..4], 6), Err(CoverError::Gap(4..6)));
        assert_eq!(check_cover(&[], 3), Err(CoverError::Gap(0..3)));
        assert_eq!(check_cover(&[2..6, 0..3], 6), Err(CoverError::Overlap { a: 1, b: 0, overlap: 2..3 }));
        assert_eq!(check_cover(&[0..3, 0..2], 3), Err(CoverError::Overlap { a: 1, b: 0, overlap: 0..2 }));
    }
}
