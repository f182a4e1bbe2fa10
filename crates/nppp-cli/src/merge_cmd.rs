//! `nppp merge`: put shards back together. Render parts (`nppp render
//! --shard I/K --out PART.nppr`) merge into the EXR the whole render would
//! have written, byte for byte; data parts (`nppp gen --shard I/K`) into the
//! `.nppd` file one run would have written. Also `--shard`'s parser.

use anyhow::{Context, Result, bail, ensure};
use clap::Args;
use nppp_render::image_io;
use std::path::{Path, PathBuf};

/// `--shard I/K`: the I-th (from 0) of K parts of a render or a data set.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Shard {
    pub index: u32,
    pub count: u32,
}

impl std::fmt::Display for Shard {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}", self.index, self.count)
    }
}

/// Parses `I/K` (clap value parser).
pub fn parse_shard(s: &str) -> Result<Shard, String> {
    let (i, k) = s
        .split_once('/')
        .ok_or_else(|| format!("\"{s}\": give I/K, e.g. 0/4 (the first of four shards)"))?;
    let num = |t: &str, what: &str| {
        t.trim()
            .parse::<u32>()
            .map_err(|_| match t.trim().parse::<u128>() {
                Ok(_) => format!("\"{s}\": {what} {t} is too large"),
                Err(_) => format!("\"{s}\": {what} \"{t}\" is not a whole number"),
            })
    };
    let (index, count) = (num(i, "I")?, num(k, "K")?);
    if count == 0 {
        return Err(format!("\"{s}\": K must be at least 1"));
    }
    if index >= count {
        return Err(format!(
            "\"{s}\": I must be below K (shards are numbered 0 to {})",
            count - 1
        ));
    }
    Ok(Shard { index, count })
}

#[derive(Args, Debug)]
pub struct MergeArgs {
    /// The parts, in any order: render parts (*.nppr) or data parts (*.nppd
    /// written with --shard), all of one render or one data set.
    #[arg(required = true)]
    pub parts: Vec<PathBuf>,
    /// The merged file: an EXR for render parts, an .nppd for data parts.
    #[arg(long)]
    pub out: PathBuf,
    /// Render parts: also write an sRGB PNG preview here.
    #[arg(long)]
    pub png: Option<PathBuf>,
    /// Data parts: replace an existing --out (without it merge refuses to,
    /// as `nppp gen` does: training data can be hours of tracing). A merged
    /// image replaces an existing one, as a render does.
    #[arg(long)]
    pub overwrite: bool,
}

pub fn run(a: &MergeArgs) -> Result<()> {
    for p in &a.parts {
        ensure!(
            !nppp_files::same_file(p, &a.out),
            "--out {} is one of the parts: the merge would replace it",
            a.out.display()
        );
        if let Some(png) = &a.png {
            ensure!(
                !nppp_files::same_file(p, png),
                "--png {} is one of the parts: the merge would replace it",
                png.display()
            );
        }
    }
    // What the output is decides what the parts must be: said before
    // the parts are read.
    ensure!(
        crate::has_extension(&a.out, "exr") || crate::has_extension(&a.out, "nppd"),
        "--out {}: name the merged file *.exr (render parts) or *.nppd (data parts)",
        a.out.display()
    );
    for (i, p) in a.parts.iter().enumerate() {
        if let Err(e) = nppp_files::open_regular(p) {
            bail!("{}: {e}", p.display());
        }
        if let Some(j) = a.parts[..i]
            .iter()
            .position(|q| nppp_files::same_file(p, q))
        {
            bail!(
                "{} is named twice (as parts {j} and {i}): it would count twice",
                p.display()
            );
        }
    }
    // Parts of the other kind than --out names: the fix is --out's name,
    // not the parts (which `merge_render` / `merge_data` would blame).
    let out_is_render = crate::has_extension(&a.out, "exr");
    if let Some(kind) = part_kind(&a.parts[0])
        && kind != out_is_render
    {
        let (parts, wanted) = if kind {
            ("render parts (`nppp render --shard`)", "*.exr")
        } else {
            ("training-data parts (`nppp gen --shard`)", "*.nppd")
        };
        bail!(
            "--out {}: the parts are {parts}; name the merged file {wanted}",
            a.out.display()
        );
    }
    if out_is_render {
        merge_render(a)
    } else {
        ensure!(
            a.png.is_none(),
            "--png is for render parts; data parts merge into an .nppd file"
        );
        crate::keep_existing_data(&a.out, a.overwrite, "merge")?;
        merge_data(a)
    }
}

/// What a part's first bytes say it is: `Some(true)` a render part,
/// `Some(false)` a training-data part, `None` neither (the merge's own
/// reading then says what is wrong with it).
fn part_kind(path: &Path) -> Option<bool> {
    use std::io::Read;
    let mut magic = [0u8; 8];
    std::fs::File::open(path)
        .ok()?
        .read_exact(&mut magic)
        .ok()?;
    if magic == nppp_render::render_part::RENDER_PART_MAGIC {
        Some(true)
    } else if magic == nppp_estimator::dataset::DATASET_MAGIC {
        Some(false)
    } else {
        None
    }
}

fn merge_render(a: &MergeArgs) -> Result<()> {
    image_io::check_writable(&a.out).context("--out")?;
    if let Some(p) = &a.png {
        ensure!(
            crate::has_extension(p, "png"),
            "--png {}: the preview is a PNG image; name it *.png",
            p.display()
        );
        image_io::check_writable(p).context("--png")?;
    }
    let first = nppp_render::render_part::read_part_header(&a.parts[0])?;
    crate::render_cmd::check_pixels_memory(
        first.width,
        first.height,
        nppp_render::render_part::MERGE_BYTES_PER_PIXEL,
        "merging render parts",
    )
    .with_context(|| format!("{}", a.parts[0].display()))?;
    let merged = nppp_render::render_part::merge_parts(&a.parts)?;
    let img = merged.image();
    image_io::write_exr(&img, &a.out).context("writing the EXR")?;
    if let Some(p) = &a.png {
        image_io::write_png(&img, p)?;
    }
    let h = &merged.header;
    let m = img.mean();
    let dropped = merged.dropped_samples();
    nppp_files::note!(
        "{}: {} parts of {} ({}x{} spp {} M {} seed {}), {:.2}s rendering in all, mean rgb [{:.4} {:.4} {:.4}]{}",
        a.out.display(),
        a.parts.len(),
        h.scene,
        h.width,
        h.height,
        h.spp,
        h.max_bounces,
        h.seed,
        h.seconds,
        m[0],
        m[1],
        m[2],
        if dropped > 0 {
            format!(", {dropped} non-finite samples dropped")
        } else {
            String::new()
        }
    );
    Ok(())
}

fn merge_data(a: &MergeArgs) -> Result<()> {
    nppp_files::check_writable(&a.out)
        .map_err(|e| anyhow::anyhow!("--out {}: {e}", a.out.display()))?;
    let parts: Vec<&Path> = a.parts.iter().map(|p| p.as_path()).collect();
    let s = nppp_estimator::shard::merge_datasets(&parts, &a.out, a.overwrite)?;
    nppp_files::note!(
        "{}: {} parts, {} rays ({} hits, {} exits) in {} chunks, {}",
        s.path.display(),
        a.parts.len(),
        s.rays,
        s.hits,
        s.exits,
        s.chunks,
        nppp_files::format_bytes(s.file_bytes)
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shard_flags() {
        assert_eq!(parse_shard("0/4"), Ok(Shard { index: 0, count: 4 }));
        assert_eq!(parse_shard(" 3 / 4 "), Ok(Shard { index: 3, count: 4 }));
        for bad in ["4/4", "1/0", "a/2", "1", "-1/2", "1/2/3", ""] {
            assert!(parse_shard(bad).is_err(), "{bad}");
        }
        assert!(parse_shard("4/4").unwrap_err().contains("0 to 3"));
        // Whole but too large for a shard count: said so, not "not a number".
        let e = parse_shard("0/4294967296").unwrap_err();
        assert!(e.contains("too large"), "{e}");
        assert!(
            parse_shard("0/x")
                .unwrap_err()
                .contains("not a whole number")
        );
    }
}
