//! Baking a trained model into a `.nppp` estimator: the encoder and the mask
//! network are evaluated at every node of their 4D grids (in large batches),
//! quantized, and stored with the exported decoder and the output transform.
//! Then the baked estimator is scored against the unbaked model on the same
//! held-out rays with the same random numbers, so the difference is what
//! the grid and the quantization cost.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use indicatif::ProgressBar;
use nppp_estimator::grid::{checked_node_count, node_coords};
use nppp_estimator::{
    BakedEstimator, DecodeRepairs, EstimatorMeta, EstimatorSampler, Exit, ExitBatch, PickedVertex,
    VertexHead,
};
use nppp_geom::SpherePair;
use serde::{Deserialize, Serialize};

use crate::backend::BackendKind;
use crate::data::{DataSplit, is_heldout};
use crate::eval::{
    BurnEstimator, EvalOptions, ExitSource, HeldoutMetrics, eval_rng, eval_vertex_rng, evaluate,
};
use crate::io::load_dataset_where;
use crate::model_dir::{LoadedModel, load_model_dir};

/// What `nppp bake` was asked for (`nppp-cli`'s `BakeArgs` map onto this).
#[derive(Clone, Debug)]
pub struct BakeOptions {
    /// Model directory written by `nppp train`.
    pub model: PathBuf,
    /// Latent grid resolution S (S^4 nodes x latent_dim channels).
    pub latent_grid: u32,
    /// Mask grid resolution (S^4 logits).
    pub mask_grid: u32,
    /// Bits per latent value: 8, 4 or 2.
    pub bits: u8,
    /// Bits per mask logit: 8, 4 or 2.
    pub mask_bits: u8,
    /// The `.nppp` file to write.
    pub out: PathBuf,
    /// Burn backend that evaluates the encoder and mask network.
    pub backend: BackendKind,
    /// Data file whose held-out rays score the result (default: the
    /// training data recorded in the model directory).
    pub data: Option<PathBuf>,
    /// Skip the held-out comparison of baked and unbaked estimators.
    pub no_eval: bool,
    /// Held-out hit rays scored.
    pub eval_rays: usize,
    /// No progress bars.
    pub quiet: bool,
}

impl BakeOptions {
    pub fn new(model: impl Into<PathBuf>, out: impl Into<PathBuf>) -> Self {
        Self {
            model: model.into(),
            latent_grid: 32,
            mask_grid: 32,
            bits: 8,
            mask_bits: 8,
            out: out.into(),
            backend: BackendKind::default(),
            data: None,
            no_eval: false,
            eval_rays: 512,
            quiet: false,
        }
    }
}

/// What a bake produced and how accurate it is.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct BakeReport {
    /// The file written (`None` for sweep rows, which write nothing).
    pub out: Option<PathBuf>,
    pub latent_res: u32,
    pub mask_res: u32,
    pub bits: u8,
    pub mask_bits: u8,
    /// Grids, decoder and parameters as the renderer holds them.
    pub memory_bytes: usize,
    pub seconds: f64,
    /// Largest |baked latent - encoder output| over all nodes, in units of
    /// that channel's quantization step (at most 0.5 up to rounding).
    pub max_node_error_steps: f64,
    pub unbaked: Option<HeldoutMetrics>,
    pub baked: Option<HeldoutMetrics>,
}

/// The summary `nppp bake` prints: the file, its memory, and the held-out
/// accuracy of the baked estimator beside the unbaked model's.
impl std::fmt::Display for BakeReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if let Some(out) = &self.out {
            writeln!(f, "{}", out.display())?;
        }
        writeln!(
            f,
            "  grids       latent {}^4 at {} bits, mask {}^4 at {} bits: {} with the decoder",
            self.latent_res,
            self.bits,
            self.mask_res,
            self.mask_bits,
            nppp_files::format_bytes(self.memory_bytes as u64)
        )?;
        writeln!(
            f,
            "  time        {:.1} s; largest node error {:.2} quantization steps",
            self.seconds, self.max_node_error_steps
        )?;
        match (&self.unbaked, &self.baked) {
            (Some(u), Some(b)) => {
                writeln!(f, "  held-out    {} rays ({} hits)", b.rays, b.hit_rays)?;
                let row = |f: &mut std::fmt::Formatter<'_>, name: &str, x: String, y: String| {
                    writeln!(f, "    {name:<30} {x:>9} {y:>9}")
                };
                row(f, "", "unbaked".into(), "baked".into())?;
                row(
                    f,
                    "chamfer",
                    format!("{:.4}", u.chamfer),
                    format!("{:.4}", b.chamfer),
                )?;
                row(
                    f,
                    "mask accuracy",
                    format!("{:.2}%", 100.0 * u.mask_accuracy),
                    format!("{:.2}%", 100.0 * b.mask_accuracy),
                )?;
                row(
                    f,
                    "throughput RMS error per ray",
                    format!("{:.2}%", 100.0 * u.throughput_rms_error),
                    format!("{:.2}%", 100.0 * b.throughput_rms_error),
                )?;
                write!(
                    f,
                    "    {:<30} {:>9} {:>9}",
                    "throughput bias",
                    format!("{:+.2}%", 100.0 * u.throughput_bias),
                    format!("{:+.2}%", 100.0 * b.throughput_bias)
                )?;
                if let (Some(uv), Some(bv)) = (&u.vertex, &b.vertex) {
                    writeln!(f)?;
                    row(
                        f,
                        "vertex chamfer",
                        format!("{:.4}", uv.chamfer),
                        format!("{:.4}", bv.chamfer),
                    )?;
                    row(
                        f,
                        "vertex throughput error",
                        format!("{:.2}%", 100.0 * uv.throughput_error),
                        format!("{:.2}%", 100.0 * bv.throughput_error),
                    )?;
                    row(
                        f,
                        "vertex throughput bias",
                        format!("{:+.2}%", 100.0 * uv.throughput_bias),
                        format!("{:+.2}%", 100.0 * bv.throughput_bias),
                    )?;
                    write!(
                        f,
                        "    {:<30} {:>9} {:>9}",
                        "vertex off the nearest real",
                        format!("{:.4}", uv.position_error),
                        format!("{:.4}", bv.position_error)
                    )?;
                }
                Ok(())
            }
            _ => write!(f, "  held-out    not scored (--no-eval)"),
        }
    }
}

/// Nodes per Burn call: see `eval::ROWS_PER_CALL`.
const NODES_PER_CALL: usize = 32_768;

/// Refuses grids whose f32 staging buffer would not fit comfortably.
const MAX_STAGING_BYTES: usize = 8 << 30;

fn check_res(name: &str, res: u32, channels: usize) -> Result<usize> {
    if !(2..=256).contains(&res) {
        bail!("--{name} {res}: the resolution must be between 2 and 256");
    }
    let n = checked_node_count(res).context("grid size overflows")?;
    let bytes = n.saturating_mul(channels).saturating_mul(4);
    if bytes > MAX_STAGING_BYTES {
        bail!(
            "--{name} {res}: {res}^4 nodes x {channels} channels need {:.1} GiB while baking \
             (limit {} GiB); choose a smaller grid",
            bytes as f64 / (1u64 << 30) as f64,
            MAX_STAGING_BYTES >> 30
        );
    }
    // The staging buffer, and a quarter more for the quantized codes and
    // the decoder's batches beside it.
    let need = (bytes as u64).saturating_add(bytes as u64 / 4);
    if let Some(available) = nppp_files::available_memory()
        && need > available
    {
        bail!(
            "--{name} {res}: {res}^4 nodes x {channels} channels need about {} while baking, \
             more than the {} of memory available; choose a smaller grid",
            nppp_files::format_bytes(need),
            nppp_files::format_bytes(available)
        );
    }
    Ok(n)
}

fn progress(quiet: bool, len: u64, what: &str) -> ProgressBar {
    if quiet {
        return ProgressBar::hidden();
    }
    let pb = ProgressBar::new(len);
    pb.set_style(nppp_files::progress_style(
        &format!("{what} {{bar:30}} {{pos}}/{{len}} nodes ({{rate}}, eta {{eta}})"),
        "nodes",
    ));
    pb
}

/// Evaluates `f` (the encoder or the mask network) at every node of a grid
/// of resolution `res`, node-major, `channels` values per node.
fn eval_grid(
    res: u32,
    channels: usize,
    quiet: bool,
    what: &str,
    mut f: impl FnMut(&[SpherePair]) -> Result<Vec<f32>>,
) -> Result<Vec<f32>> {
    let n = check_res(what, res, channels)?;
    let pb = progress(quiet, n as u64, what);
    let mut out = Vec::with_capacity(n * channels);
    let mut pairs = Vec::with_capacity(NODES_PER_CALL);
    let mut start = 0;
    while start < n {
        let end = (start + NODES_PER_CALL).min(n);
        pairs.clear();
        pairs.extend((start..end).map(|i| SpherePair(node_coords(res, i))));
        let v = f(&pairs)?;
        if v.len() != pairs.len() * channels {
            bail!("{what}: got {} values for {} nodes", v.len(), pairs.len());
        }
        if let Some(i) = v.iter().position(|x| !x.is_finite()) {
            bail!(
                "{what}: the network gives a non-finite value at node {} (the model is broken)",
                start + i / channels
            );
        }
        out.extend(v);
        pb.set_position(end as u64);
        start = end;
    }
    pb.finish_and_clear();
    Ok(out)
}

/// The baked estimator through the estimator interface the renderer uses
/// ([`EstimatorSampler::sample_batch`]).
pub struct BakedSource {
    pub sampler: EstimatorSampler,
    pub repairs: DecodeRepairs,
    batch: ExitBatch,
}

impl BakedSource {
    pub fn new(sampler: EstimatorSampler) -> Self {
        Self {
            sampler,
            repairs: DecodeRepairs::default(),
            batch: ExitBatch::default(),
        }
    }
}

impl ExitSource for BakedSource {
    fn mask_logits(&mut self, pairs: &[SpherePair]) -> Result<Vec<f32>> {
        Ok(pairs.iter().map(|p| self.sampler.mask_logit(p)).collect())
    }

    fn sample_exits(
        &mut self,
        pairs: &[SpherePair],
        first_index: u64,
        k: usize,
        seed: u64,
    ) -> Result<Vec<Exit>> {
        // Row i * k + j is pair i's j-th exit; a pair's k noise rows come
        // from its own stream, the same r as the Burn side draws for this
        // ray (eval_rng). Batches of about 16 k rows keep the decoder's
        // buffers small.
        let sampler = &self.sampler;
        let mut out = Vec::with_capacity(pairs.len() * k);
        let per_batch = (16384 / k.max(1)).max(1);
        for (c, chunk) in pairs.chunks(per_batch).enumerate() {
            let first = first_index + (c * per_batch) as u64;
            let mut rng = eval_rng(seed, first);
            let fill = |row: usize, z: &mut [f32], noise: &mut [f32]| {
                let (i, j) = (row / k, row % k);
                if j == 0 {
                    rng = eval_rng(seed, first + i as u64);
                }
                sampler.latent(&chunk[i], z);
                noise.iter_mut().for_each(|x| *x = rng.normal());
            };
            let rows = chunk.len() * k;
            let decoded = sampler.sample_batch(&mut self.batch, rows, fill, &mut self.repairs);
            out.extend_from_slice(decoded.exits);
        }
        Ok(out)
    }

    fn sample_vertices(
        &mut self,
        pairs: &[SpherePair],
        first_index: u64,
        k: usize,
        seed: u64,
    ) -> Result<Option<Vec<PickedVertex>>> {
        // The rows' latents as `sample_exits` lays them out (the exit
        // decoder runs on them, with zero noise, only for that), then the
        // vertex head with the vertex noise stream (the Burn side draws the
        // same r').
        let sampler = &self.sampler;
        if !sampler.has_vertex_head() {
            return Ok(None);
        }
        let mut out = Vec::with_capacity(pairs.len() * k);
        let per_batch = (16384 / k.max(1)).max(1);
        for (c, chunk) in pairs.chunks(per_batch).enumerate() {
            let first = first_index + (c * per_batch) as u64;
            let fill = |row: usize, z: &mut [f32], noise: &mut [f32]| {
                sampler.latent(&chunk[row / k], z);
                noise.iter_mut().for_each(|x| *x = 0.0);
            };
            let rows = chunk.len() * k;
            sampler.sample_batch(&mut self.batch, rows, fill, &mut self.repairs);
            let mut rng = eval_vertex_rng(seed, first);
            let noise = |row: usize, r: &mut [f32]| {
                let (i, j) = (row / k, row % k);
                if j == 0 {
                    rng = eval_vertex_rng(seed, first + i as u64);
                }
                r.iter_mut().for_each(|x| *x = rng.normal());
            };
            let verts = sampler
                .sample_vertices(&mut self.batch, noise, &mut self.repairs)
                .context("the estimator has no vertex head")?;
            out.extend_from_slice(verts);
        }
        Ok(Some(out))
    }
}

/// The f32 grids of a model, before quantization.
pub struct RawGrids {
    pub latent_res: u32,
    pub latent: Vec<f32>,
    pub mask_res: u32,
    pub mask_logits: Vec<f32>,
}

/// Evaluates the encoder and the mask network at every node.
pub fn compute_grids(
    loaded: &LoadedModel,
    latent_res: u32,
    mask_res: u32,
    quiet: bool,
) -> Result<RawGrids> {
    // Both sizes are checked before the (long) encoder pass.
    check_res("latent-grid", latent_res, loaded.model_config.latent_dim)?;
    check_res("mask-grid", mask_res, 1)?;
    let est = BurnEstimator::new(
        &loaded.model,
        loaded.meta.transform.clone(),
        &loaded.meta.dataset,
        loaded.model_config.noise_dim,
    )?;
    let latent = eval_grid(
        latent_res,
        loaded.model_config.latent_dim,
        quiet,
        "latent-grid",
        |p| est.latents(p),
    )?;
    let mut est = est;
    let mask_logits = eval_grid(mask_res, 1, quiet, "mask-grid", |p| est.mask_logits(p))?;
    Ok(RawGrids {
        latent_res,
        latent,
        mask_res,
        mask_logits,
    })
}

/// Quantizes raw grids into an estimator stamped with the model's identity.
pub fn assemble(
    loaded: &LoadedModel,
    grids: &RawGrids,
    bits: u8,
    mask_bits: u8,
) -> Result<BakedEstimator> {
    let ds = &loaded.meta.dataset;
    let meta = EstimatorMeta {
        mesh_name: ds.mesh_name.clone(),
        mesh_hash: ds.mesh_hash,
        material_name: ds.material_name.clone(),
        material_hash: ds.material_hash,
        sphere: ds.sphere,
        latent_dim: loaded.model_config.latent_dim as u32,
        noise_dim: loaded.model_config.noise_dim as u32,
        max_internal_bounces: ds.max_internal_bounces,
        notes: format!(
            "nppp-nn: {} training steps; latent {}^4 x {} at {} bits, mask {}^4 at {} bits; \
             decoder {} multiply-adds",
            loaded.state.step,
            grids.latent_res,
            loaded.model_config.latent_dim,
            bits,
            grids.mask_res,
            mask_bits,
            loaded.model_config.decoder_macs()
        ),
    };
    let decoder = loaded.model.export_decoder()?;
    let vertex = match (
        loaded.model.export_vertex_decoder()?,
        &loaded.meta.vertex_transform,
    ) {
        (Some(decoder), Some(transform)) => Some(VertexHead {
            decoder,
            transform: transform.clone(),
        }),
        (None, None) => None,
        _ => bail!(
            "the model folder's vertex head and its meta.json's vertex_transform do not come \
             together (one is missing): retrain with `nppp train`"
        ),
    };
    let baked = BakedEstimator::from_f32_grids_with_mask_bits(
        meta,
        grids.latent_res,
        &grids.latent,
        grids.mask_res,
        &grids.mask_logits,
        bits,
        mask_bits,
        decoder,
        loaded.meta.transform.clone(),
    )
    .context("assembling the estimator")?;
    match vertex {
        Some(v) => baked
            .with_vertex_head(v)
            .context("assembling the estimator's vertex head"),
        None => Ok(baked),
    }
}

/// Largest |dequantized node value - f32 value| in quantization steps.
pub fn max_node_error_steps(baked: &BakedEstimator, latent: &[f32]) -> f64 {
    let g = &baked.latent;
    let c = g.channels as usize;
    let mut worst = 0.0f64;
    for (k, &x) in latent.iter().enumerate() {
        let ch = k % c;
        let err = (g.node_value(k / c, ch) - x).abs() as f64;
        let step = g.scale[ch] as f64;
        let e = if step > 0.0 {
            err / step
        } else if err > 0.0 {
            f64::INFINITY
        } else {
            0.0
        };
        worst = worst.max(e);
    }
    worst
}

/// The held-out rays of the model's data (or of `data`), encoded with the
/// model's own transform.
pub fn load_heldout(loaded: &LoadedModel, data: Option<&Path>, quiet: bool) -> Result<DataSplit> {
    let path = data.unwrap_or(&loaded.meta.data_path);
    let every = loaded.train_config.holdout_every;
    if every == 0 {
        bail!(
            "{}: the model's train_config.json holds out no rays (holdout_every 0), so there is \
             nothing to score it on: bake with --no-eval",
            loaded.dir.display()
        );
    }
    check_training_data(loaded, path)?;
    let (header, rays) =
        load_dataset_where(path, quiet, 1.0 / every as f64, |i| is_heldout(i, every))
            .with_context(|| {
                format!(
                    "reading held-out rays from {} (to bake without scoring them: --no-eval)",
                    path.display()
                )
            })?;
    if rays.is_empty() {
        bail!(
            "{}: none of its rays is held out (every {every}th is, and the file has fewer): it \
             is not the data the model was trained on; name that with --data, or bake with \
             --no-eval",
            path.display()
        );
    }
    if header.mesh_hash != loaded.meta.dataset.mesh_hash
        || header.material_hash != loaded.meta.dataset.material_hash
    {
        // The names alone may agree (an edited mesh keeps its name): say the hashes.
        bail!(
            "{} was generated for mesh {} (hash {:016x}) / material {} (hash {:016x}), the model \
             for mesh {} (hash {:016x}) / material {} (hash {:016x}): bake with the data the \
             model was trained on, or --no-eval",
            path.display(),
            header.mesh_name,
            header.mesh_hash,
            header.material_name,
            header.material_hash,
            loaded.meta.dataset.mesh_name,
            loaded.meta.dataset.mesh_hash,
            loaded.meta.dataset.material_name,
            loaded.meta.dataset.material_hash
        );
    }
    // The picked vertices are scored when both the model and the data have them.
    let vt = loaded
        .meta
        .vertex_transform
        .as_ref()
        .filter(|_| header.vertices);
    crate::data::encode_split(rays, header.k as usize, &loaded.meta.transform, vt, true)
}

/// Refuses data whose held-out rays are not the model's: rays are held out
/// by their index in the file, so a shard of the training data (numbered
/// from its own first ray), or a file with other rays or another k, would
/// score the model on rays it trained on, or fail later without naming a
/// file. The mesh and material are compared after reading.
fn check_training_data(loaded: &LoadedModel, path: &Path) -> Result<()> {
    let Ok(reader) = nppp_estimator::DatasetReader::open(path) else {
        // Reading it again below says what is wrong with it.
        return Ok(());
    };
    let h = reader.header();
    let no_eval = "name the file the model was trained on with --data, or bake with --no-eval";
    if let Some(s) = &h.shard {
        bail!(
            "{} is a shard (rays {}..{} of {}) of a data set: its rays are numbered from its \
             own first one, so its held-out rays are not the ones the model was kept from; \
             merge the shards (`nppp merge`) and name the merged file, or bake with --no-eval",
            path.display(),
            s.first_ray,
            s.end_ray,
            s.rays
        );
    }
    let fp = &loaded.state.data;
    let (rays, hits, k) = (reader.len(), reader.hit_count() as usize, h.k as usize);
    if (rays, hits, k) != (fp.rays, fp.hits, fp.k) {
        bail!(
            "{} holds {rays} rays, {hits} hits, k = {k}; the model was trained on {} rays, {} \
             hits, k = {} ({}'s checkpoint): its held-out rays would not be the model's; {no_eval}",
            path.display(),
            fp.rays,
            fp.hits,
            fp.k,
            loaded.dir.display()
        );
    }
    Ok(())
}

fn eval_pair(
    loaded: &LoadedModel,
    baked: BakedEstimator,
    heldout: &DataSplit,
    eval_rays: usize,
) -> Result<(HeldoutMetrics, HeldoutMetrics)> {
    let k = loaded.meta.dataset.k as usize;
    let opts = EvalOptions {
        max_hit_rays: eval_rays,
        ..EvalOptions::default()
    };
    let tr = &loaded.meta.transform;
    let vt = loaded.meta.vertex_transform.as_ref();
    let mut unbaked = BurnEstimator::new(
        &loaded.model,
        tr.clone(),
        &loaded.meta.dataset,
        loaded.model_config.noise_dim,
    )?;
    unbaked.vertex_transform = vt.cloned();
    let mu = evaluate(&mut unbaked, heldout, k, tr, vt, &opts)?;
    let mut sampler = EstimatorSampler::try_new(baked)?;
    sampler.bounds = loaded.meta.dataset.exit_bounds();
    let mut bs = BakedSource::new(sampler);
    let mb = evaluate(&mut bs, heldout, k, tr, vt, &opts)?;
    Ok((mu, mb))
}

/// Refuses, before any work, an `--out` that is not a `.nppp` name, cannot
/// be written, or names one of bake's inputs: the training data (a typo of
/// `.nppd` for `.nppp`), a file of the model directory, or a place inside
/// its checkpoint, which training replaces wholesale.
fn check_out(opts: &BakeOptions, loaded: &LoadedModel) -> Result<()> {
    let out = &opts.out;
    let is_nppp = out
        .extension()
        .is_some_and(|e| e.to_string_lossy().eq_ignore_ascii_case("nppp"));
    if !is_nppp {
        bail!(
            "--out {}: an estimator file is named *.nppp (bake never writes under another \
             extension, so a slip cannot overwrite training data or a model file)",
            out.display()
        );
    }
    nppp_files::check_writable(out).map_err(|e| anyhow::anyhow!("--out {}: {e}", out.display()))?;
    let data = opts.data.as_deref().unwrap_or(&loaded.meta.data_path);
    nppp_files::ensure_not_input("--out", out, &[("the training data bake reads", data)])
        .map_err(anyhow::Error::msg)?;
    for d in [
        crate::model_dir::files::CHECKPOINT,
        crate::model_dir::files::CHECKPOINT_OLD,
        crate::model_dir::files::CHECKPOINT_TMP,
    ] {
        if nppp_files::is_inside(out, &opts.model.join(d)) {
            bail!(
                "--out {} is inside the model's {d}/ folder, which training replaces as a whole; \
                 write the estimator elsewhere (for example models/NAME.nppp)",
                out.display()
            );
        }
    }
    if let Ok(entries) = std::fs::read_dir(&opts.model) {
        for e in entries.flatten() {
            let p = e.path();
            if p.is_file() && nppp_files::same_file(out, &p) {
                bail!(
                    "--out {} is a file of the model directory {}; write the estimator elsewhere",
                    out.display(),
                    opts.model.display()
                );
            }
        }
    }
    Ok(())
}

/// `nppp bake`: bakes, scores the result against the unbaked model, and
/// only then writes the estimator file (atomically): a failure at any step
/// leaves an existing `--out` as it was.
pub fn bake(opts: &BakeOptions) -> Result<BakeReport> {
    let t0 = Instant::now();
    let device = opts.backend.device()?;
    let loaded = load_model_dir(&opts.model, &device)?;
    check_out(opts, &loaded)?;
    // The held-out rays are read before the (long) grid pass, so a missing
    // or mismatched data file fails at once.
    let heldout = if opts.no_eval {
        None
    } else {
        Some(load_heldout(&loaded, opts.data.as_deref(), opts.quiet)?)
    };
    let grids = compute_grids(&loaded, opts.latent_grid, opts.mask_grid, opts.quiet)?;
    let baked = assemble(&loaded, &grids, opts.bits, opts.mask_bits)?;
    let max_node_error_steps = max_node_error_steps(&baked, &grids.latent);
    let memory_bytes = baked.memory_bytes();
    let bytes = baked.to_bytes();
    let seconds = t0.elapsed().as_secs_f64();
    let (unbaked, baked_m) = match &heldout {
        None => (None, None),
        Some(h) => {
            let (a, b) = eval_pair(&loaded, baked, h, opts.eval_rays)?;
            (Some(a), Some(b))
        }
    };
    nppp_files::create_parent(&opts.out)
        .and_then(|_| nppp_files::write_atomic(&opts.out, &bytes))
        .with_context(|| format!("writing {}", opts.out.display()))?;
    Ok(BakeReport {
        out: Some(opts.out.clone()),
        latent_res: opts.latent_grid,
        mask_res: opts.mask_grid,
        bits: opts.bits,
        mask_bits: opts.mask_bits,
        memory_bytes,
        seconds,
        max_node_error_steps,
        unbaked,
        baked: baked_m,
    })
}

/// Held-out accuracy of the baked estimator at several grid resolutions
/// (latent and mask grids alike) and latent bit depths, against the unbaked
/// model; writes no file. The encoder runs once per resolution.
pub fn bake_sweep(opts: &BakeOptions, resolutions: &[u32], bits: &[u8]) -> Result<Vec<BakeReport>> {
    let device = opts.backend.device()?;
    let loaded = load_model_dir(&opts.model, &device)?;
    let heldout = load_heldout(&loaded, opts.data.as_deref(), opts.quiet)?;
    let mut rows = Vec::new();
    for &res in resolutions {
        let t0 = Instant::now();
        let grids = compute_grids(&loaded, res, res, opts.quiet)?;
        let grid_s = t0.elapsed().as_secs_f64();
        for &b in bits {
            let t1 = Instant::now();
            let baked = assemble(&loaded, &grids, b, opts.mask_bits)?;
            let max_node_error_steps = max_node_error_steps(&baked, &grids.latent);
            let memory_bytes = baked.memory_bytes();
            let seconds = grid_s + t1.elapsed().as_secs_f64();
            let (u, m) = eval_pair(&loaded, baked, &heldout, opts.eval_rays)?;
            rows.push(BakeReport {
                out: None,
                latent_res: res,
                mask_res: res,
                bits: b,
                mask_bits: opts.mask_bits,
                memory_bytes,
                seconds,
                max_node_error_steps,
                unbaked: Some(u),
                baked: Some(m),
            });
        }
    }
    Ok(rows)
}

/// A Markdown table of sweep rows (the README's).
pub fn sweep_table(rows: &[BakeReport]) -> String {
    let mut s = String::from(
        "| grid | bits | memory | chamfer | energy | throughput RMS err | throughput bias | mask acc | bake s |\n\
         |---|---|---|---|---|---|---|---|---|\n",
    );
    let line = |s: &mut String,
                grid: String,
                bits: String,
                mem: String,
                m: &HeldoutMetrics,
                secs: String| {
        s.push_str(&format!(
            "| {grid} | {bits} | {mem} | {:.3} | {:.3} | {:.2}% | {:+.2}% | {:.2}% | {secs} |\n",
            m.chamfer,
            m.energy,
            100.0 * m.throughput_rms_error,
            100.0 * m.throughput_bias,
            100.0 * m.mask_accuracy
        ));
    };
    if let Some(u) = rows.first().and_then(|r| r.unbaked) {
        line(
            &mut s,
            "unbaked".into(),
            "-".into(),
            "-".into(),
            &u,
            "-".into(),
        );
    }
    for r in rows {
        if let Some(b) = r.baked {
            line(
                &mut s,
                format!("{}^4", r.latent_res),
                r.bits.to_string(),
                format!("{:.2} MiB", r.memory_bytes as f64 / (1u64 << 20) as f64),
                &b,
                format!("{:.1}", r.seconds),
            );
        }
    }
    s
}
