//! `--estimators auto`: a short pilot decides, per estimator, whether to use
//! it and from which P (with next-event estimation through it where its
//! surface can take a light sample), by measured efficiency against plain
//! path tracing.
//!
//! The pilot renders the scene at a quarter of its resolution, 4 samples per
//! pixel, twice (two seeds), as plain PT and once per candidate P (1 and 2;
//! see [`PilotOptions::min_p`]) of each estimator (the others off), plus one
//! more PT render that only normalizes the error. For each configuration it measures
//! - the error per sample: each pixel's variance from the two halves,
//!   `(a - b)^2 / 4`, relative to the normalizing render as relMSE is to its
//!   reference (`/ (r^2 + 0.01)`, `r` blurred over 5 x 5 pixels), averaged
//!   over pixels and channels;
//! - the cost per sample: the work the render counted (BVH node visits,
//!   closest-hit rays, estimator entries) weighted by what each costs
//!   ([`COST_PER_RAY`], [`COST_PER_ENTRY`]). Counted work, not the wall
//!   clock: the decision, and so the image, is the same at any thread
//!   count and on a busy machine;
//! - its image mean against PT's: a configuration whose mean differs by more
//!   than noise and [`PilotOptions::bias_tolerance`] is rejected (a network
//!   that misses light has little variance and would look efficient).
//!
//! Efficiency is 1 / (cost x error). An estimator is used with its most
//! efficient P only if that beats PT's efficiency by
//! [`PilotOptions::margin`]: the pilot's estimates are noisy (heavy-tailed
//! per-pixel variance at 4 spp) and the cost model is within about 10% of
//! measured times, so a configuration that merely matches PT stays off.
//! Candidates are decided one estimator at a time, not by trying every
//! combination. The pilot is about 3-5% of a 64-spp render.

use crate::estimator::{EntryNee, Estimators};
use crate::image_io::Image;
use crate::integrator::WorkCounts;
use crate::render::{RenderOptions, render};
use crate::scene_data::RenderScene;
use crate::surface::SurfaceKind;

/// Cost of one closest-hit ray beyond its node visits (shading, sampling,
/// the wavefront's bookkeeping), in node visits. Fitted with the entry cost
/// by least squares to render times of 18 renders (PT and NPPP, P = 0..2,
/// with and without entry NEE) of every scene in data/scenes on the 2-core
/// machine (BENCHMARKS.md, "auto"): 14.2 ns per node visit, 54 ns per ray,
/// 358 ns per entry (two threads); predicted times within 0.89x-1.22x.
pub const COST_PER_RAY: f64 = 3.8;
/// Cost of one estimator entry (latent lookup, its row of the batched
/// decoder, decoding the exit), in node visits.
pub const COST_PER_ENTRY: f64 = 25.0;

/// Counted work of a render, in node-visit equivalents.
pub fn work_cost(work: &WorkCounts, entries: u64) -> f64 {
    work.node_visits as f64 + COST_PER_RAY * work.rays as f64 + COST_PER_ENTRY * entries as f64
}

#[derive(Clone, Copy, Debug)]
pub struct PilotOptions {
    /// Resolution factor of the pilot's camera.
    pub scale: f64,
    /// Samples per pixel of each of the two halves.
    pub spp: u32,
    pub max_bounces: u32,
    pub seed: u64,
    /// Efficiency over PT's a configuration needs to be chosen.
    pub margin: f64,
    /// Smallest P tried. 1 by default: at P = 0 what the camera sees of the
    /// object is the network's statistical answer (glass seen directly is
    /// blurred), a loss of sharpness that keeps the image mean and that no
    /// variance measurement sees.
    pub min_p: u32,
    /// Smallest P tried for a translucent object's estimator. 0 by default:
    /// what the camera sees of a dense medium is subsurface transport, which
    /// the network reproduces (cornell-jade at P = 0: image mean within 0.3%
    /// of PT's, 13x faster at equal error, BENCHMARKS.md); only the
    /// boundary's faint specular reflection is blurred.
    pub min_p_medium: u32,
    /// Largest P tried.
    pub max_p: u32,
    /// Relative difference of a configuration's image mean from PT's
    /// (beyond 4 standard deviations of noise) that rejects it as biased:
    /// a network that misses light (the tube at P = 0 renders its inside
    /// black) has little variance and would otherwise look efficient.
    pub bias_tolerance: f64,
}

impl Default for PilotOptions {
    fn default() -> Self {
        Self {
            scale: 0.25,
            spp: 4,
            max_bounces: 5,
            seed: 0,
            margin: 1.15,
            min_p: 1,
            min_p_medium: 0,
            max_p: 2,
            bias_tolerance: 0.03,
        }
    }
}

/// How one estimator is used.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Choice {
    pub min_bounces: u32,
    pub entry_nee: EntryNee,
}

/// One pilot measurement.
#[derive(Clone, Debug)]
pub struct Trial {
    /// `None`: plain path tracing.
    pub choice: Option<Choice>,
    /// Relative variance per sample (relMSE units x spp).
    pub rel_var: f64,
    /// Work per sample, node-visit equivalents.
    pub cost: f64,
    /// Efficiency as a multiple of PT's (0 when rejected as biased).
    pub efficiency: f64,
    /// The pilot image's mean (both halves, all pixels and channels) and
    /// the variance of that mean.
    pub mean: f64,
    pub mean_var: f64,
    /// Its mean differs from PT's by more than noise and
    /// [`PilotOptions::bias_tolerance`] allow: never chosen.
    pub biased: bool,
}

/// What the pilot decided for one estimator.
#[derive(Clone, Debug)]
pub struct EstimatorDecision {
    /// The estimator's index in [`Estimators::list`].
    pub index: usize,
    /// `None`: off.
    pub choice: Option<Choice>,
    pub trials: Vec<Trial>,
}

#[derive(Clone, Debug)]
pub struct Decision {
    pub pt: Trial,
    pub estimators: Vec<EstimatorDecision>,
    /// Camera samples the pilot rendered (all its renders).
    pub samples: u64,
    /// The pilot's image size.
    pub width: u32,
    pub height: u32,
}

impl Decision {
    /// One line per estimator, e.g. "estimator 0: P = 1, 1.31x PT's efficiency".
    pub fn describe(&self, names: &[String]) -> Vec<String> {
        self.estimators
            .iter()
            .map(|d| {
                let name = names.get(d.index).map_or("?", |s| s.as_str());
                let best = d
                    .trials
                    .iter()
                    .max_by(|a, b| a.efficiency.total_cmp(&b.efficiency));
                let tried = d
                    .trials
                    .iter()
                    .map(|t| {
                        if t.biased {
                            format!("{} biased", label(t.choice))
                        } else {
                            format!("{} {:.2}x", label(t.choice), t.efficiency)
                        }
                    })
                    .collect::<Vec<_>>()
                    .join(", ");
                match (d.choice, best) {
                    (Some(c), Some(b)) => format!(
                        "{name}: {}, {:.2}x PT's efficiency (tried {tried})",
                        label(Some(c)),
                        b.efficiency
                    ),
                    (_, Some(b)) => format!(
                        "{name}: off, best {:.2}x PT's efficiency (tried {tried})",
                        b.efficiency
                    ),
                    _ => format!("{name}: off"),
                }
            })
            .collect()
    }
}

/// "P = 1" or "P = 1 + first-vertex NEE" or "PT".
pub fn label(c: Option<Choice>) -> String {
    match c {
        None => "PT".into(),
        Some(c) => match c.entry_nee {
            EntryNee::Off => format!("P = {}", c.min_bounces),
            EntryNee::FirstVertex => format!("P = {} + first-vertex NEE", c.min_bounces),
            EntryNee::PickedVertex => format!("P = {} + picked-vertex NEE", c.min_bounces),
        },
    }
}

/// The configurations tried for an estimator: P = min_p..=max_p below M, with
/// first-vertex NEE where its surface can take a light sample (without it,
/// an opaque object's estimator lost 2x-5x more at equal error on every
/// scene measured, BENCHMARKS.md), without on delta lobes (smooth glass).
fn candidates(est: &crate::estimator::Estimator, opts: &PilotOptions) -> Vec<Choice> {
    let entry_nee = match est.surface {
        SurfaceKind::Scatter(b) if !b.is_delta() => EntryNee::FirstVertex,
        _ => EntryNee::Off,
    };
    let min_p = if est.medium.is_some() {
        opts.min_p_medium
    } else {
        opts.min_p
    };
    (min_p..=opts.max_p.min(opts.max_bounces.saturating_sub(1)))
        .map(|p| Choice {
            min_bounces: p,
            entry_nee,
        })
        .collect()
}

/// One configuration's pilot: (estimator index and choice, or `None` for
/// PT), its two halves, and its cost per sample.
type PilotRender = (Option<(usize, Choice)>, Image, Image, f64);

/// Runs the pilot on `rs` (its camera is swapped for the pilot's and put
/// back) and returns the estimators configured as decided, `None` when all
/// are off (the render is then plain path tracing).
pub fn decide(
    rs: &mut RenderScene,
    mut ests: Estimators,
    opts: &PilotOptions,
) -> (Option<Estimators>, Decision) {
    let camera = rs.camera;
    // A pilot smaller than the image it decides for, but at least 16 pixels
    // on its short side.
    let scale = opts
        .scale
        .max(16.0 / camera.width.min(camera.height).max(1) as f64)
        .min(1.0);
    rs.camera = camera.scaled(scale);
    let (width, height) = (rs.camera.width, rs.camera.height);
    let mut samples = 0u64;
    let mut run = |rs: &RenderScene, seed: u64| {
        let (img, st) = render(
            rs,
            &RenderOptions {
                spp: opts.spp,
                max_bounces: opts.max_bounces,
                seed,
                progress: false,
            },
        );
        samples += st.samples;
        (img, work_cost(&st.work, st.estimators.entries), st.samples)
    };
    let seeds = [
        opts.seed ^ 0xA070_0000_0000_0001,
        opts.seed ^ 0xA070_0000_0000_0002,
        opts.seed ^ 0xA070_0000_0000_0003,
    ];

    // Plain path tracing: the baseline and the error's normalization.
    let base_instances = ests.per_instance.clone();
    // The error's normalization, as relMSE's reference: a PT pilot of its
    // own (seeds no measured pilot uses), blurred over 5 x 5 pixels.
    // Unblurred, a few spp of PT miss what is rare (light seen through
    // glass), and any pixel PT missed would make an estimator's answer
    // there look like a huge error; made from the measured pilots, each
    // configuration's fireflies would normalize themselves away.
    let (n_img, _, _) = run(rs, seeds[2]);
    let norm = blur(&n_img.pixels, n_img.width as usize, 2);
    // Every pilot's two halves and cost per sample: PT first.
    let mut pilots: Vec<PilotRender> = Vec::new();
    let (pa, ca, na) = run(rs, seeds[0]);
    let (pb, cb, nb) = run(rs, seeds[1]);
    pilots.push((None, pa, pb, (ca + cb) / (na + nb).max(1) as f64));
    for index in 0..ests.list.len() {
        for choice in candidates(&ests.list[index], opts) {
            ests.per_instance = base_instances
                .iter()
                .map(|e| e.filter(|&i| i as usize == index))
                .collect();
            ests.configure_one(index, Some((choice.min_bounces, choice.entry_nee)));
            rs.estimators = Some(ests);
            let (a, ca, na) = run(rs, seeds[0]);
            let (b, cb, nb) = run(rs, seeds[1]);
            ests = rs.estimators.take().expect("put there above");
            pilots.push((
                Some((index, choice)),
                a,
                b,
                (ca + cb) / (na + nb).max(1) as f64,
            ));
        }
    }
    rs.camera = camera;

    let trial = |choice: Option<Choice>, a: &Image, b: &Image, cost: f64| {
        let (mean, mean_var) = mean_and_variance(a, b);
        Trial {
            choice,
            rel_var: rel_var(a, b, &norm),
            cost,
            efficiency: 1.0,
            mean,
            mean_var,
            biased: false,
        }
    };
    let pt = trial(None, &pilots[0].1, &pilots[0].2, pilots[0].3);
    let pt_product = pt.rel_var * pt.cost;
    let mut decisions = Vec::new();
    for index in 0..ests.list.len() {
        let mut trials: Vec<Trial> = pilots
            .iter()
            .filter_map(|(c, a, b, cost)| match c {
                Some((i, choice)) if *i == index => Some(trial(Some(*choice), a, b, *cost)),
                _ => None,
            })
            .collect();
        for t in trials.iter_mut() {
            let noise = 4.0 * (t.mean_var + pt.mean_var).sqrt();
            t.biased = (t.mean - pt.mean).abs() > noise + opts.bias_tolerance * pt.mean.abs();
            let product = t.rel_var * t.cost;
            t.efficiency = if product > 0.0 && !t.biased {
                pt_product / product
            } else {
                0.0
            };
        }
        let best = trials
            .iter()
            .filter(|t| t.efficiency.is_finite())
            .max_by(|a, b| a.efficiency.total_cmp(&b.efficiency));
        let choice = best
            .filter(|t| t.efficiency >= opts.margin)
            .and_then(|t| t.choice);
        decisions.push(EstimatorDecision {
            index,
            choice,
            trials,
        });
    }
    // The decided configuration.
    ests.per_instance = base_instances;
    for d in &decisions {
        ests.configure_one(d.index, d.choice.map(|c| (c.min_bounces, c.entry_nee)));
    }
    let decision = Decision {
        pt,
        estimators: decisions,
        samples,
        width,
        height,
    };
    (ests.any_in_use().then_some(ests), decision)
}

/// Box blur of a row-major image `width` pixels wide over (2r + 1)^2 pixels
/// (clipped at the borders).
fn blur(img: &[[f32; 3]], width: usize, r: usize) -> Vec<[f32; 3]> {
    let width = width.max(1);
    let height = img.len() / width;
    let mut out = vec![[0.0f32; 3]; img.len()];
    for y in 0..height {
        for x in 0..width {
            let mut s = [0.0f64; 3];
            let mut n = 0.0f64;
            for yy in y.saturating_sub(r)..(y + r + 1).min(height) {
                for xx in x.saturating_sub(r)..(x + r + 1).min(width) {
                    let p = img[yy * width + xx];
                    for c in 0..3 {
                        s[c] += p[c] as f64;
                    }
                    n += 1.0;
                }
            }
            out[y * width + x] = [(s[0] / n) as f32, (s[1] / n) as f32, (s[2] / n) as f32];
        }
    }
    out
}

/// The mean of the two halves' mean image over pixels and channels, and
/// its variance (from each pixel's `(a - b)^2 / 4`).
fn mean_and_variance(a: &Image, b: &Image) -> (f64, f64) {
    let mut sum = 0.0f64;
    let mut var = 0.0f64;
    let mut n = 0usize;
    for (x, y) in a.pixels.iter().zip(&b.pixels) {
        for c in 0..3 {
            let (x, y) = (x[c] as f64, y[c] as f64);
            sum += 0.5 * (x + y);
            var += 0.25 * (x - y) * (x - y);
            n += 1;
        }
    }
    let n = n.max(1) as f64;
    (sum / n, var / (n * n))
}

/// Variance of the two halves' mean per pixel, relative to `norm` as relMSE
/// is to its reference, averaged over pixels and channels. Non-finite
/// pixels count as infinite error.
fn rel_var(a: &Image, b: &Image, norm: &[[f32; 3]]) -> f64 {
    let mut sum = 0.0f64;
    let mut n = 0usize;
    for ((x, y), r) in a.pixels.iter().zip(&b.pixels).zip(norm) {
        for c in 0..3 {
            let d = (x[c] - y[c]) as f64;
            let r = r[c] as f64;
            sum += 0.25 * d * d / (r * r + 0.01);
            n += 1;
        }
    }
    if n == 0 || !sum.is_finite() {
        return f64::INFINITY;
    }
    sum / n as f64
}
