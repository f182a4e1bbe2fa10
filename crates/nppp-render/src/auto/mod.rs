//! `--estimators auto`: a short pilot decides, per estimator, whether to use
//! it and from which P (with next-event estimation through it where its
//! surface can take a light sample), by measured efficiency against plain
//! path tracing.
//!
//! The pilot renders the scene at a quarter of its resolution, a few
//! samples per pixel (`nppp render` gives it a sixteenth of the render's,
//! 1 to 16), twice (two seeds), as plain PT and once per candidate P (1 and 2;
//! see [`PilotOptions::min_p`]) of each estimator (the others off); a
//! candidate whose first sample per pixel shows it too costly to tie the
//! best one measured so far is not rendered further
//! ([`PilotOptions::hopeless_sigmas`]).
//! For each configuration it measures
//! - the error per sample: each pixel's variance from the two halves,
//!   `(a - b)^2 / 4`, relative to the mean of all the pilot's renders as
//!   relMSE is to its reference (`/ (r^2 + 0.01)`, `r` blurred over 5 x 5
//!   pixels), averaged over pixels and channels;
//! - the cost per sample: the work the render counted (inner BVH node
//!   visits of all but the camera rays, shadow rays, estimator entries and
//!   their decoder rows by size, mask skips) weighted by what each costs
//!   ([`work_cost`]). Counted work, not the wall clock: the decision, and
//!   so the image, is the same at any thread count and on a busy machine;
//! - its image mean against PT's: a configuration whose mean differs by more
//!   than noise and [`PilotOptions::bias_tolerance`] is rejected (a network
//!   that misses light has little variance and would look efficient).
//!
//! Efficiency is 1 / (cost x error), with the error's ratio to PT's shrunk
//! towards 1 as far as the pilot cannot measure it ([`efficiency`]): the
//! per-pixel variance at 4 spp is heavy-tailed, and one configuration
//! catching a firefly that another missed moved the raw ratio 10x-100x
//! between seeds. An estimator is used only if its best configuration
//! beats PT's efficiency by [`PilotOptions::margin`] (the cost model
//! predicts time ratios to PT's within 6% RMS, 12% at most), and among its
//! configurations within [`PilotOptions::tie`] of the best the cheapest
//! wins (`choose`).
//! Candidates are decided one estimator at a time, not by trying every
//! combination. The pilot is 2-4% of a 64-spp render where PT is the
//! cost, 6-8% on cornell-jade, where the estimator is 4x cheaper than PT.

use crate::estimator::{EntryNee, EstimatorStats, Estimators};
use crate::film::{PixelSum, film_image};
use crate::image_io::Image;
use crate::integrator::WorkCounts;
use crate::render::{RenderOptions, render_film};
use crate::scene_data::RenderScene;
use nppp_geom::rng::mix64;

mod confirm;
pub use confirm::{Plan, Segment, plan};

/// The cost model, in units of one inner BVH node visit of a path's later
/// rays (8 boxes tested; incoherent rays miss the cache). Fitted by
/// `tools/fit_cost_model.py` (least squares on relative error) to the 8-wide
/// BVH's counts and the faster of two timed sets of 86 renders each (the
/// seven benchmark scenes, PT and NPPP at P = 0..2 with and without
/// first-vertex NEE, 24 spp, 2 rounds) on the 2-core machine (BENCHMARKS.md,
/// "auto"): 31.4 ns per later inner node visit, 84 ns per shadow ray beyond
/// its visits, 560 ns per entry, 46 ns per mask skip (two threads); time
/// ratios to PT predicted with an RMS error of 6.1% (largest 12%: the room's
/// P = 1 with first-vertex NEE, 1.04x predicted, 1.18x measured).
///
/// Left out, and why: the camera rays' node visits (coherent, in cache,
/// fitted at -0.02, and the same in every configuration of a scene); leaf
/// visits (0.12 of an inner visit: a leaf's packets were prefetched while
/// its parent was tested); closest-hit rays (they track node visits too
/// closely for the fit to tell them apart). Counting leaves and camera
/// rays' visits as the 4-wide model did predicted the 8-wide renderer's
/// time ratios with 12% RMS error.
///
/// A shadow ray beyond its node visits (the light sample, the BSDF
/// evaluation, the MIS weights).
pub const COST_PER_SHADOW_RAY: f64 = 2.7;
/// One estimator entry beyond its decoder rows: the latent lookup, decoding
/// the exit, its mask test. The fit above gave 17.8 per entry with the
/// 11,072-multiply-add decoder and 16 noise dimensions every file then had;
/// that is split here by the shares of an entry's criterion time (noise
/// 90 ns and decoder 450 ns of 890 ns, BENCHMARKS.md "cornell-glass"), so
/// that a smaller or larger decoder, and a vertex head's second row, are
/// counted by what they compute: 7.0 (this) + 1.1 (the row) + 7.9 (its
/// 11,072 multiply-adds) + 1.8 (16 normals) = 17.8 for such an entry, with
/// `matrixmultiply` as the decoder's kernel. Its own kernel
/// (`nppp_estimator::dense_kernel`) made a row's fixed part 0.15x and a
/// multiply-add 0.70x as costly (the two decoder sizes' criterion times,
/// `estimator_decoder_rows`, on one CPU): 0.17 + 5.5 for that row then.
///
/// Since rays that cannot enter the only estimator's sphere take the merged
/// layout (BENCHMARKS.md, "Rays inside the only estimator's sphere"), a
/// path's later rays are counted in the tree plain PT walks, and the model
/// with these prices predicted the default scene's and gold's NPPP renders
/// 6-11% cheaper than they timed (time ratios to PT: 7.4% RMS error, 12%
/// at most). Refitted on the same 72 renders (`tools/fit_cost_model.py`,
/// 24 spp, 3 rounds) with the shadow ray's and the mask skip's prices held,
/// the entry's whole split came out 1.29x: all four entry prices are 1.3x
/// what the split above gives (5.6% RMS, 13% at most).
pub const COST_PER_ENTRY: f64 = 9.1;
/// The part of a decoder row's time that does not grow with its size (the
/// per-row overhead of the products): from the times of a 128-row batch of
/// the 3,488- and the 11,072-multiply-add decoders (`estimator_decoder_rows`,
/// 8.9 us and 26.0 us; BENCHMARKS.md "Cheaper entries"); 1.3 x 0.17.
pub const COST_PER_DECODER_ROW: f64 = 0.22;
/// One multiply-add of a decoder row: 0.70x the 7.9 units per 11,072 that
/// `matrixmultiply` took (the slope between the two decoder sizes, 17.5 ps
/// against 24.9 ps a multiply-add on one core); 1.3 x 5.5 per 11,072.
pub const COST_PER_DECODER_MULTIPLY_ADD: f64 = 7.15 / 11_072.0;
/// One standard normal of a decoder row's noise (the ziggurat). The
/// 32-bit ziggurat that replaced `rand_distr`'s draws them in 0.57x the
/// time (criterion); the price stays, because on the AVX-512 machine the
/// model already predicts the default scene's picked-NEE renders 5% cheaper
/// than they time (`tools/fit_cost_model.py`: 1.08x PT's time against
/// 1.14x measured), and a lower price would move a losing estimator
/// towards the margin, not a winning one; 1.3 x 0.1125.
pub const COST_PER_DECODER_NORMAL: f64 = 0.146;
/// A ray whose chord the mask judged a miss (the chord's coordinates and a
/// mask lookup): the room of 2,025 knots makes about one per sample.
pub const COST_PER_MASK_SKIP: f64 = 1.5;

/// Counted work of a render, in later-inner-node-visit equivalents.
pub fn work_cost(work: &WorkCounts, estimators: &EstimatorStats) -> f64 {
    later_inner_node_visits(work) as f64
        + COST_PER_SHADOW_RAY * work.shadow_rays as f64
        + COST_PER_ENTRY * estimators.entries as f64
        + COST_PER_DECODER_ROW * estimators.decoder_rows as f64
        + COST_PER_DECODER_MULTIPLY_ADD * estimators.decoder_multiply_adds as f64
        + COST_PER_DECODER_NORMAL * estimators.decoder_normals as f64
        + COST_PER_MASK_SKIP * estimators.mask_skips as f64
}

/// The inner BVH node visits of every ray but the camera rays: the cost
/// model's unit.
pub fn later_inner_node_visits(work: &WorkCounts) -> u64 {
    let later = work.node_visits.saturating_sub(work.camera_node_visits);
    later.saturating_sub(work.leaf_visits)
}

/// The closest-hit rays after the camera rays: one per path vertex beyond
/// the first. Logged, not priced: refitted on 2026-11-26 with the glass
/// scenes, whose bounces have no shadow ray, a later ray's own weight came
/// out -0.07 and +0.33 node visits in two fits of the same renders
/// (`tools/fit_cost_model.py`, BENCHMARKS.md "auto"): the machine's timing
/// noise hides it.
pub fn later_rays(work: &WorkCounts) -> u64 {
    work.rays.saturating_sub(work.camera_rays)
}

/// What [`work_cost`] counted, term by term, for the render's log (and for
/// `tools/fit_cost_model.py`, which reads it back).
pub fn describe_work(work: &WorkCounts, estimators: &EstimatorStats) -> String {
    format!(
        "{:.4} M units of auto's cost model: {} later inner node visits, {} later rays, {} shadow rays, {} estimator entries, {} decoder rows of {} multiply-adds and {} noise normals in all, {} mask skips",
        work_cost(work, estimators) / 1e6,
        later_inner_node_visits(work),
        later_rays(work),
        work.shadow_rays,
        estimators.entries,
        estimators.decoder_rows,
        estimators.decoder_multiply_adds,
        estimators.decoder_normals,
        estimators.mask_skips
    )
}

#[derive(Clone, Copy, Debug)]
pub struct PilotOptions {
    /// Resolution factor of the pilot's camera.
    pub scale: f64,
    /// Samples per pixel of each of the two halves.
    pub spp: u32,
    pub max_bounces: u32,
    pub seed: u64,
    /// Efficiency over PT's a configuration needs to be chosen. 1.05
    /// since rays inside the only estimator's sphere take the merged
    /// layout (2026-11-26, late night): at 1.10 the glass scenes' pilots,
    /// whose variance ratios have a 30-60% standard error at 64 spp, left
    /// their winning estimators off at 2-5 seeds of 8 (auto at 0.75-0.92
    /// of the best fixed P's efficiency), and at 1.05 at 1-2 (0.86-0.91);
    /// the knots this admits more often, gold's (1.00x-1.04x at equal
    /// error now, from 0.69x when 1.10 was chosen for it), do not lose,
    /// and the default scene's, tube's and the rooms' stay off at every
    /// seed (BENCHMARKS.md, "auto's margin"). `nppp render --auto-margin`.
    pub margin: f64,
    /// Smallest P tried. 1 by default: at P = 0 what the camera sees of the
    /// object is the network's statistical answer (glass seen directly is
    /// blurred), a loss of sharpness that keeps the image mean and that no
    /// variance measurement sees.
    pub min_p: u32,
    /// Smallest P tried for an estimator whose object takes light samples
    /// (diffuse, rough conductor: its configurations use next-event
    /// estimation at the network's picked vertex). 2 by default: the
    /// networks' picked vertices and exits are accurate to about 1% under
    /// light like the Cornell box's ceiling lamp, but under light they
    /// were not checked with their error grows, most at small P, and no
    /// pilot sees it (the knot beside a lamp at its side: 4.2% dark at
    /// P = 1, 0.7% at P = 2; its pilot measured +1.3%; BENCHMARKS.md,
    /// "Where NPPP loses"). Since the picked vertex takes its light sample
    /// on the real surface that knot is 1.3% dark at P = 1, but P = 1 no
    /// longer wins anywhere measured (gold 0.96x-0.98x, the default scene
    /// 0.93x), so P = 2 stays the smallest tried;
    /// `--estimators neural --min-bounces 1` still runs them.
    pub min_p_light_sampled: u32,
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
    /// Prior standard deviation of the log of a configuration's variance
    /// over PT's; see [`efficiency`]. 0.35 (ratios of 0.7x to 1.4x are
    /// typical a priori): chosen over 8 seeds of the benchmark scenes and
    /// data/scenes/variants, where it made cornell-jade's decision (P = 0)
    /// at every seed and turned no losing estimator on, with the pilots of
    /// 1 and 4 spp per half; with the 1-spp pilot, at 0.5 cornell-gold's
    /// turned on at one seed, at 1 jade's was off or P = 1 at two
    /// (BENCHMARKS.md, "auto").
    pub variance_ratio_prior: f64,
    /// Efficiencies within this factor of each other are a tie, which the
    /// cheaper configuration wins (see `choose`).
    pub tie: f64,
    /// A candidate gets its pilot halves only if its cost ratio to PT
    /// (counted on its first sample per pixel) times
    /// `exp(hopeless_sigmas x variance_ratio_prior)` (the efficiency it
    /// would have with a variance that far below PT's: 0.42x at 2.5 and
    /// 0.35, a priori 0.6% likely) reaches the best efficiency measured so
    /// far for its estimator, within [`Self::tie`]. On cornell-jade P = 1
    /// and 2 cost 0.72x and 0.96x of PT's per sample where P = 0 is 4x
    /// more efficient: their halves were 40% of the pilot.
    pub hopeless_sigmas: f64,
    /// Samples per pixel of each half of a confirmation round ([`plan`]);
    /// 0 (the default): no confirmation.
    pub confirm_spp: u32,
    /// Most rounds of the confirmation pass (each: two halves per
    /// configuration still undecided).
    pub confirm_rounds: u32,
    /// An estimator goes to the confirmation pass unless the pilot is sure
    /// that it does not beat PT by [`Self::margin`] even with its variance
    /// ratio `confirm_sigmas` posterior standard deviations lower, or that
    /// it does even with the ratio that much higher.
    pub confirm_sigmas: f64,
    /// A confirmation round decides before the last one only where the
    /// variance ratio this many standard errors worse still beats
    /// [`Self::confirm_margin`] (on), or this many better still does not
    /// (off). 3, not 2: the standard error is the pixels' spread, and after
    /// one round of 1-spp halves a firefly or two make it (at 2,
    /// cornell-glass's estimator, 1.2x PT's efficiency, was turned off
    /// after one round at one seed of 8, measured at 0.77x +-15%), while a
    /// loser's further rounds cost little (a few samples per pixel).
    pub confirm_stop_sigmas: f64,
    /// Efficiency over PT's that the confirmation pass needs to turn an
    /// estimator on. Lower than [`Self::margin`]: it measures the render's
    /// own image, not a quarter-resolution one, and its samples are the
    /// image's, so a near tie costs nothing whichever way it goes.
    pub confirm_margin: f64,
    /// Largest image (pixels) the confirmation pass runs for: it holds two
    /// films of 128 bytes per pixel (268 MB at 1 Mpx). Larger images have
    /// larger pilots.
    pub confirm_max_pixels: u64,
}

impl Default for PilotOptions {
    fn default() -> Self {
        Self {
            scale: 0.25,
            spp: 4,
            max_bounces: 5,
            seed: 0,
            margin: 1.05,
            min_p: 1,
            min_p_light_sampled: 2,
            min_p_medium: 0,
            max_p: 2,
            bias_tolerance: 0.03,
            variance_ratio_prior: 0.35,
            tie: 1.15,
            hopeless_sigmas: 2.5,
            confirm_spp: 0,
            confirm_rounds: 2,
            confirm_sigmas: 2.0,
            confirm_stop_sigmas: 3.0,
            confirm_margin: 1.05,
            confirm_max_pixels: 1 << 21,
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
    /// Standard error of `rel_var`, from its spread over pixels.
    pub rel_var_se: f64,
    /// Relative variance per pixel (`rel_var` is their mean): with PT's,
    /// the standard error of the ratio of the two
    /// (`Trial::log_variance_ratio_var`). Empty where not measured.
    pub pixel_rel_var: Vec<f64>,
    /// Work per sample, node-visit equivalents.
    pub cost: f64,
    /// Efficiency as a multiple of PT's (0 when rejected as biased).
    pub efficiency: f64,
    /// The pilot image's mean (both halves, all pixels and channels) and
    /// the variance of that mean.
    pub mean: f64,
    pub mean_var: f64,
    /// The variance of the mean of its difference from PT's pilot, pixel
    /// by pixel, where both were rendered with the same seeds (infinite
    /// where not measured so). Paths agree until they meet the estimator,
    /// so this is far below `mean_var + pt.mean_var` (0.8% of the mean
    /// against 6.6% for a knot lit from one side). It is still blind to a
    /// bias carried by rare, bright samples a pilot hardly draws: that
    /// knot's network is 4.4% dark at P = 1, and its pilot measured +1.3%
    /// ([`PilotOptions::min_p_light_sampled`]).
    pub paired_diff_var: f64,
    /// Its mean differs from PT's by more than noise and
    /// [`PilotOptions::bias_tolerance`] allow: never chosen.
    pub biased: bool,
    /// Not measured beyond its cost, counted on its first sample per
    /// pixel: it could not have tied the best configuration however low
    /// its variance ([`decide`]).
    /// Never chosen; `rel_var` is infinite.
    pub skipped: bool,
}

impl Trial {
    /// A measured configuration, not yet scored ([`score`]): its relative
    /// variance per pixel, its cost per sample, its image mean and the
    /// variance of that mean.
    fn measured(
        choice: Option<Choice>,
        pixel_rel_var: Vec<f64>,
        cost: f64,
        mean: f64,
        mean_var: f64,
    ) -> Self {
        let (rel_var, rel_var_se) = mean_and_standard_error(&pixel_rel_var);
        Self {
            choice,
            rel_var,
            rel_var_se,
            pixel_rel_var,
            cost,
            efficiency: 1.0,
            mean,
            mean_var,
            paired_diff_var: f64::INFINITY,
            biased: false,
            skipped: false,
        }
    }

    /// A candidate not measured beyond its first sample per pixel, whose
    /// cost per sample that sample counted (see [`Trial::skipped`]).
    fn not_measured(choice: Choice, cost: f64) -> Self {
        Self {
            choice: Some(choice),
            rel_var: f64::INFINITY,
            rel_var_se: f64::INFINITY,
            pixel_rel_var: Vec::new(),
            cost,
            efficiency: 0.0,
            mean: f64::NAN,
            mean_var: f64::INFINITY,
            paired_diff_var: f64::INFINITY,
            biased: false,
            skipped: true,
        }
    }

    /// Variance of the log of this trial's variance ratio to `pt`'s, by the
    /// delta method for a ratio of two means over the same pixels:
    /// `Var(v_t / mean_t - v_pt / mean_pt) / n` over pixels. The pilot
    /// renders PT and every candidate with the same seeds (common random
    /// numbers): their paths agree until they enter the estimator's sphere,
    /// and so do the pixel errors those paths make, which cancel in the
    /// difference. Treating the two as independent (the sum of the squared
    /// relative standard errors, what serves when the per-pixel values are
    /// missing) ignores that. On cornell-glass it changes little (P = 1's
    /// +-30-34% became +-28-35% over seeds 0-7): the bright pixels there are
    /// the glass's own, where the two configurations' paths differ.
    fn log_variance_ratio_var(&self, pt: &Trial) -> f64 {
        let n = self.pixel_rel_var.len();
        if n == 1 {
            // One pixel says nothing about its own spread: unmeasured, so
            // the prior (and the work) decides. Its standard error of 0
            // read as certainty, and one pixel chose (efficiency 0.84x to
            // 261x over four seeds of a 1x1 image).
            return f64::INFINITY;
        }
        if n == 0 || n != pt.pixel_rel_var.len() {
            return (self.rel_var_se / self.rel_var).powi(2) + (pt.rel_var_se / pt.rel_var).powi(2);
        }
        let diff: Vec<f64> = self
            .pixel_rel_var
            .iter()
            .zip(&pt.pixel_rel_var)
            .map(|(t, p)| t / self.rel_var - p / pt.rel_var)
            .collect();
        let se = mean_and_standard_error(&diff).1;
        se * se
    }

    /// What its efficiency is made of, against PT's trial: "work 0.96x,
    /// variance 0.79x +-45%" (the work and the variance per sample as
    /// multiples of PT's, the latter with its relative standard error, the
    /// part [`efficiency`] believes only in part).
    pub fn against(&self, pt: &Trial) -> String {
        let work = self.cost / pt.cost;
        let var = self.rel_var / pt.rel_var;
        let se = self.log_variance_ratio_var(pt).sqrt();
        if work.is_finite() && var.is_finite() && se.is_finite() {
            format!("work {work:.2}x, variance {var:.2}x +-{:.0}%", 100.0 * se)
        } else {
            "not measurable".into()
        }
    }
}

/// What the pilot decided for one estimator.
#[derive(Clone, Debug)]
pub struct EstimatorDecision {
    /// The estimator's index in [`Estimators::list`].
    pub index: usize,
    /// `None`: off.
    pub choice: Option<Choice>,
    pub trials: Vec<Trial>,
    /// Where the pilot could not tell: the candidate measured again at the
    /// render's full resolution by the confirmation pass ([`plan`]), which
    /// then made `choice`.
    pub confirmed: Option<Trial>,
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
    /// PT's trial in the confirmation pass at full resolution, if there was
    /// one ([`plan`]; its samples are [`Plan::rest_start`]'s).
    pub confirmation_pt: Option<Trial>,
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
                        } else if t.skipped {
                            format!(
                                "{} not measured (work {:.2}x: cannot win)",
                                label(t.choice),
                                t.cost / self.pt.cost
                            )
                        } else {
                            format!(
                                "{} {:.2}x ({})",
                                label(t.choice),
                                t.efficiency,
                                t.against(&self.pt)
                            )
                        }
                    })
                    .collect::<Vec<_>>()
                    .join(", ");
                if let (Some(t), Some(pt)) = (&d.confirmed, &self.confirmation_pt) {
                    // Decided by the confirmation pass.
                    return format!(
                        "{name}: {}, {} {:.2}x PT's efficiency at full resolution ({}; pilot: {tried})",
                        if d.choice.is_some() { label(d.choice) } else { "off".into() },
                        label(t.choice),
                        t.efficiency,
                        t.against(pt)
                    );
                }
                let chosen = d
                    .trials
                    .iter()
                    .find(|t| t.choice.is_some() && t.choice == d.choice);
                match (d.choice, chosen, best) {
                    // The chosen configuration's own efficiency: a tie may
                    // have given it to a cheaper one than the best measured.
                    (Some(c), Some(t), _) => format!(
                        "{name}: {}, {:.2}x PT's efficiency (tried {tried})",
                        label(Some(c)),
                        t.efficiency
                    ),
                    (_, _, Some(b)) => format!(
                        "{name}: off, best {:.2}x PT's efficiency (tried {tried})",
                        b.efficiency
                    ),
                    // No candidate: P, from the smallest auto tries for
                    // this object (PilotOptions), reaches no bounce below M.
                    _ => format!(
                        "{name}: off (no P that auto tries is below M; objects that take light \
                         samples are tried from P = 2: --estimators neural --min-bounces sets P)"
                    ),
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
            EntryNee::PickedVertexLightOnly => {
                format!(
                    "P = {} + picked-vertex NEE (light sample alone)",
                    c.min_bounces
                )
            }
        },
    }
}

/// The configurations tried for an estimator: P = min_p..=max_p below M, with
/// next-event estimation through the estimator where its surface can take a
/// light sample (without it, an opaque object's estimator lost 2x-5x more at
/// equal error on every scene measured, BENCHMARKS.md): at the picked vertex
/// its file's vertex head returns, or else at the first vertex found on the
/// real mesh; without on delta lobes (smooth glass).
fn candidates(est: &crate::estimator::Estimator, opts: &PilotOptions) -> Vec<Choice> {
    let entry_nee = est.light_sampling_entry_nee();
    let min_p = if est.medium.is_some() {
        opts.min_p_medium
    } else if entry_nee != EntryNee::Off {
        opts.min_p.max(opts.min_p_light_sampled)
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

/// A candidate's first sample per pixel of its first pilot half: what it
/// costs per sample, counted, before the rest of the pilot is spent on it.
struct Probe {
    index: usize,
    choice: Choice,
    film: Vec<PixelSum>,
    /// Counted work of the probe ([`work_cost`]) and its camera samples.
    cost: f64,
    samples: u64,
}

impl Probe {
    fn cost_per_sample(&self) -> f64 {
        self.cost / self.samples.max(1) as f64
    }
}

/// [`render_film`], cut into sample ranges rendered at once where the
/// image has fewer tiles than there are threads: the pilot's 32 x 24
/// pixels are four tiles, which kept 4 of 16 threads busy (`auto` took
/// 1.13x PT's time on the room at half resolution on a 16-core Xeon, where
/// PT took 1.04 s). Films of disjoint sample ranges merge into exactly the
/// film of their union, and the work counted is the same, so the pilot
/// decides the same on any number of threads.
fn render_film_on_all_threads(
    rs: &RenderScene,
    opts: &RenderOptions,
    range: std::ops::Range<u32>,
) -> (Vec<PixelSum>, crate::render::RenderStats) {
    use rayon::prelude::*;
    let tile = crate::render::TILE;
    let tiles = (rs.camera.width.div_ceil(tile) * rs.camera.height.div_ceil(tile)) as usize;
    let parts = rayon::current_num_threads()
        .div_ceil(tiles.max(1))
        .min(range.len())
        .max(1) as u32;
    if parts == 1 {
        return render_film(rs, opts, range);
    }
    let n = range.len() as u32;
    let cut = |k: u32| range.start + n * k / parts;
    let films: Vec<_> = (0..parts)
        .into_par_iter()
        .map(|k| render_film(rs, opts, cut(k)..cut(k + 1)))
        .collect();
    let mut films = films.into_iter();
    let (mut film, mut stats) = films.next().expect("at least one part");
    for (f, st) in films {
        for (a, b) in film.iter_mut().zip(&f) {
            a.merge(b);
        }
        stats.merge(&st);
    }
    (film, stats)
}

/// A candidate measured with both pilot halves.
struct Measured {
    index: usize,
    choice: Choice,
    a: Image,
    b: Image,
    /// Counted work per sample over both halves.
    cost: f64,
}

/// Runs the pilot on `rs` (its camera is swapped for the pilot's and put
/// back) and returns the estimators configured as decided, `None` when all
/// are off (the render is then plain path tracing).
pub fn decide(
    rs: &mut RenderScene,
    ests: Estimators,
    opts: &PilotOptions,
) -> (Option<Estimators>, Decision) {
    let base = ests.per_instance().to_vec();
    let (mut ests, decision) = pilot(rs, ests, opts);
    configure_decided(&mut ests, &base, &decision);
    (ests.any_in_use().then_some(ests), decision)
}

/// The pilot of [`decide`]: its decision, and `ests` with the instances
/// they had (each estimator in the configuration it was last tried in).
fn pilot(
    rs: &mut RenderScene,
    mut ests: Estimators,
    opts: &PilotOptions,
) -> (Estimators, Decision) {
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
    // Samples `range` of a half rendered with `seed`: films of disjoint
    // ranges merge into exactly the film of their union.
    let mut run = |rs: &RenderScene, seed: u64, range: std::ops::Range<u32>| {
        let (film, st) = render_film_on_all_threads(
            rs,
            &RenderOptions {
                spp: opts.spp,
                max_bounces: opts.max_bounces,
                seed,
                progress: false,
            },
            range,
        );
        samples += st.samples;
        (film, work_cost(&st.work, &st.estimators), st.samples)
    };
    let image = |film: &[PixelSum]| film_image(width, height, film);
    // Hashed, so that the pilots of different render seeds share no
    // stream (XOR with small constants mapped seed 0's pilots onto seed 3's).
    let seeds = [1u64, 2].map(|k| mix64(mix64(opts.seed) ^ (0xA070_0000_0000_0000 | k)));
    let whole = 0..opts.spp;

    let base_instances = ests.per_instance().to_vec();
    let configure = |ests: &mut Estimators, index: usize, choice: Choice| {
        configure_alone(ests, &base_instances, index, choice)
    };
    // PT's two halves.
    let (fa, ca, na) = run(rs, seeds[0], whole.clone());
    let (fb, cb, nb) = run(rs, seeds[1], whole.clone());
    let (pa, pb) = (image(&fa), image(&fb));
    let pt_cost = (ca + cb) / (na + nb).max(1) as f64;
    // Every candidate's first sample per pixel: its cost per sample is then
    // counted, at a fraction of a half (a quarter of the 4-spp pilot), and
    // the sample is the start of its first half if it goes on.
    let mut probes: Vec<Probe> = Vec::new();
    for index in 0..ests.list.len() {
        // An estimator no instance uses (each one's object obstructed, see
        // `crate::estimator_overlap`) has nothing to try: it stays off.
        if !base_instances.contains(&Some(index as u32)) {
            continue;
        }
        for choice in candidates(&ests.list[index], opts) {
            configure(&mut ests, index, choice);
            rs.estimators = Some(ests);
            let (film, cost, n) = run(rs, seeds[0], 0..1);
            ests = rs.estimators.take().expect("put there above");
            probes.push(Probe {
                index,
                choice,
                film,
                cost,
                samples: n,
            });
        }
    }

    // The error's normalization: see [`normalization`]. While candidates
    // are still being measured, the mean of those rendered so far serves.
    let normalization = |renders: &[&Image]| normalization(renders, width);
    // PT's halves and every measured candidate's.
    fn renders<'a>(pt: [&'a Image; 2], measured: &'a [Measured]) -> Vec<&'a Image> {
        pt.into_iter()
            .chain(measured.iter().flat_map(|m| [&m.a, &m.b]))
            .collect()
    }
    let score = |pt: &Trial, t: &mut Trial| score(pt, t, opts);

    // Per estimator, its candidates from the cheapest up: each gets the
    // rest of its first half and its second half, unless even a variance
    // far below PT's could not make it tie the best measured so far (see
    // PilotOptions::hopeless_sigmas).
    let optimism = (opts.hopeless_sigmas * opts.variance_ratio_prior).exp();
    let mut measured: Vec<Measured> = Vec::new();
    for index in 0..ests.list.len() {
        let mut mine: Vec<usize> = (0..probes.len())
            .filter(|&k| probes[k].index == index)
            .collect();
        mine.sort_by(|&a, &b| {
            probes[a]
                .cost_per_sample()
                .total_cmp(&probes[b].cost_per_sample())
        });
        let mut best = 0.0f64;
        for k in mine {
            let probe = &probes[k];
            if best > 0.0 && pt_cost / probe.cost_per_sample() * optimism * opts.tie < best {
                continue;
            }
            configure(&mut ests, index, probe.choice);
            rs.estimators = Some(ests);
            let (mut first, c1, n1) = run(rs, seeds[0], 1..opts.spp);
            let (second, c2, n2) = run(rs, seeds[1], whole.clone());
            ests = rs.estimators.take().expect("put there above");
            for (f, p) in first.iter_mut().zip(&probe.film) {
                f.merge(p);
            }
            let cost = (probe.cost + c1 + c2) / (probe.samples + n1 + n2).max(1) as f64;
            let m = Measured {
                index,
                choice: probe.choice,
                a: image(&first),
                b: image(&second),
                cost,
            };
            let so_far = renders([&pa, &pb], &measured);
            let norm = normalization(&[so_far, vec![&m.a, &m.b]].concat());
            let pt = trial(&norm, None, &pa, &pb, pt_cost);
            let mut t = paired_trial(&norm, m.choice, (&m.a, &m.b), (&pa, &pb), m.cost);
            score(&pt, &mut t);
            if t.efficiency.is_finite() {
                best = best.max(t.efficiency);
            }
            measured.push(m);
        }
    }

    // The final measurements, against the normalization of every render.
    let norm = normalization(&renders([&pa, &pb], &measured));
    let pt = trial(&norm, None, &pa, &pb, pt_cost);
    let mut decisions = Vec::new();
    for index in 0..ests.list.len() {
        // In candidate order (P ascending), as printed.
        let mut trials: Vec<Trial> = Vec::new();
        for probe in probes.iter().filter(|p| p.index == index) {
            let done = measured
                .iter()
                .find(|m| m.index == index && m.choice == probe.choice);
            trials.push(match done {
                Some(m) => {
                    let mut t = paired_trial(&norm, m.choice, (&m.a, &m.b), (&pa, &pb), m.cost);
                    score(&pt, &mut t);
                    t
                }
                // Skipped above: it could not win.
                None => Trial::not_measured(probe.choice, probe.cost_per_sample()),
            });
        }
        let choice = choose(&trials, opts);
        decisions.push(EstimatorDecision {
            index,
            choice,
            trials,
            confirmed: None,
        });
    }
    rs.camera = camera;
    ests.set_per_instance(base_instances);
    let decision = Decision {
        pt,
        estimators: decisions,
        samples,
        width,
        height,
        confirmation_pt: None,
    };
    (ests, decision)
}

/// Estimator `index` alone (its instances; the others' traced as plain
/// geometry), in configuration `choice`. `base`: every instance's
/// estimator as loaded.
fn configure_alone(ests: &mut Estimators, base: &[Option<u32>], index: usize, choice: Choice) {
    ests.set_per_instance(
        base.iter()
            .map(|e| e.filter(|&i| i as usize == index))
            .collect(),
    );
    ests.configure_one(index, Some((choice.min_bounces, choice.entry_nee)));
}

/// Every estimator as `decision` chose (off ones' instances traced as
/// plain geometry).
fn configure_decided(ests: &mut Estimators, base: &[Option<u32>], decision: &Decision) {
    ests.set_per_instance(base.to_vec());
    for d in &decision.estimators {
        ests.configure_one(d.index, d.choice.map(|c| (c.min_bounces, c.entry_nee)));
    }
}

/// The error's normalization, as relMSE's reference: the mean of
/// `renders` (PT's halves and each measured candidate's), blurred over
/// 5 x 5 pixels. Unblurred, a few spp miss what is rare (light seen through
/// glass), and any pixel the reference missed would make an answer there
/// look like a huge error; made of one configuration's renders, its
/// fireflies would normalize themselves away, while in the mean of all of
/// them (and blurred) a firefly weighs 1 / (25 x renders) of itself. (A PT
/// render of its own served before, at a third of PT's pilot cost.)
fn normalization(renders: &[&Image], width: u32) -> Vec<[f32; 3]> {
    let len = renders.first().map_or(0, |r| r.pixels.len());
    let mut mean = vec![[0.0f32; 3]; len];
    for img in renders {
        for (m, p) in mean.iter_mut().zip(&img.pixels) {
            for c in 0..3 {
                // The film drops non-finite samples; a broken pilot
                // render still must not make every error NaN.
                if p[c].is_finite() {
                    m[c] += p[c] / renders.len() as f32;
                }
            }
        }
    }
    blur(&mean, width as usize, 2)
}

/// A configuration's measurement from its two halves `a` and `b`, against
/// the normalization `norm`, with its counted `cost` per sample (not yet
/// scored: see [`score`]).
fn trial(norm: &[[f32; 3]], choice: Option<Choice>, a: &Image, b: &Image, cost: f64) -> Trial {
    let (mean, mean_var) = mean_and_variance(a, b);
    Trial::measured(choice, pixel_rel_var(a, b, norm), cost, mean, mean_var)
}

/// [`trial`] of a candidate rendered with PT's seeds, whose halves `a` and
/// `b` pair with PT's `pa` and `pb`: with [`Trial::paired_diff_var`].
fn paired_trial(
    norm: &[[f32; 3]],
    choice: Choice,
    (a, b): (&Image, &Image),
    (pa, pb): (&Image, &Image),
    cost: f64,
) -> Trial {
    let mut t = trial(norm, Some(choice), a, b, cost);
    t.paired_diff_var = paired_difference_variance(a, b, pa, pb);
    t
}

/// The variance of the mean of `(a + b) / 2 - (pa + pb) / 2` over pixels
/// and channels, where `a` pairs with `pa` and `b` with `pb` (same seeds):
/// per pixel, the two pairs' differences are independent estimates of the
/// same difference, so their spread gives its variance.
fn paired_difference_variance(a: &Image, b: &Image, pa: &Image, pb: &Image) -> f64 {
    if a.pixels.len() != pa.pixels.len()
        || b.pixels.len() != pb.pixels.len()
        || a.pixels.len() != b.pixels.len()
    {
        return f64::INFINITY;
    }
    let differences = channel_pairs(a, b)
        .zip(channel_pairs(pa, pb))
        .map(|((x, y), (px, py))| (x - px, y - py));
    let (_, var) = halves_mean_and_variance(differences);
    if var.is_finite() { var } else { f64::INFINITY }
}

/// Bias test and efficiency of `t` against PT's trial: its image mean may
/// differ from PT's by 4 standard deviations of noise (of the paired
/// difference where measured, else of the two means) and
/// [`PilotOptions::bias_tolerance`].
fn score(pt: &Trial, t: &mut Trial, opts: &PilotOptions) {
    let var = if t.paired_diff_var.is_finite() {
        t.paired_diff_var
    } else {
        t.mean_var + pt.mean_var
    };
    let noise = 4.0 * var.sqrt();
    t.biased = (t.mean - pt.mean).abs() > noise + opts.bias_tolerance * pt.mean.abs();
    t.efficiency = if t.biased {
        0.0
    } else {
        efficiency(pt, t, opts.variance_ratio_prior)
    };
}

/// The configuration to use among one estimator's trials, `None` for off:
/// the cheapest of those whose efficiency is within
/// [`PilotOptions::tie`] of the best, if the best beats PT's by
/// [`PilotOptions::margin`].
///
/// Between configurations of one estimator the cost per sample is what the
/// pilot knows exactly and the variance what it knows least: efficiencies
/// within the pilot's noise of each other are a tie, and the tie goes to the
/// configuration that does less work (on cornell-glass P = 1 over P = 2, on
/// cornell-jade P = 0 over P = 1).
fn choose(trials: &[Trial], opts: &PilotOptions) -> Option<Choice> {
    let best = trials
        .iter()
        .filter(|t| t.efficiency.is_finite())
        .max_by(|a, b| a.efficiency.total_cmp(&b.efficiency))?;
    if best.efficiency < opts.margin {
        return None;
    }
    trials
        .iter()
        .filter(|t| t.efficiency.is_finite() && t.efficiency * opts.tie >= best.efficiency)
        .filter(|t| t.efficiency >= opts.margin)
        .min_by(|a, b| a.cost.total_cmp(&b.cost))
        .and_then(|t| t.choice)
}

/// Box blur of a row-major image `width` pixels wide over (2r + 1)^2 pixels
/// (clipped at the borders). Rows in parallel: the confirmation pass blurs
/// the full-resolution image after each round.
fn blur(img: &[[f32; 3]], width: usize, r: usize) -> Vec<[f32; 3]> {
    use rayon::prelude::*;
    let width = width.max(1);
    let height = img.len() / width;
    let mut out = vec![[0.0f32; 3]; img.len()];
    out.par_chunks_mut(width).enumerate().for_each(|(y, row)| {
        for (x, o) in row.iter_mut().enumerate() {
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
            *o = [(s[0] / n) as f32, (s[1] / n) as f32, (s[2] / n) as f32];
        }
    });
    out
}

/// The mean of the two halves' mean image over pixels and channels, and
/// its variance (from each pixel's `(a - b)^2 / 4`).
fn mean_and_variance(a: &Image, b: &Image) -> (f64, f64) {
    halves_mean_and_variance(channel_pairs(a, b))
}

/// Every channel of every pixel of `a` beside `b`'s.
fn channel_pairs<'i>(a: &'i Image, b: &'i Image) -> impl Iterator<Item = (f64, f64)> + 'i {
    a.pixels
        .iter()
        .zip(&b.pixels)
        .flat_map(|(x, y)| (0..3).map(move |c| (x[c] as f64, y[c] as f64)))
}

/// The mean of `(x + y) / 2` over `halves`, and its variance from the two
/// halves' spread.
fn halves_mean_and_variance(halves: impl Iterator<Item = (f64, f64)>) -> (f64, f64) {
    let mut sum = 0.0f64;
    let mut var = 0.0f64;
    let mut n = 0usize;
    for (x, y) in halves {
        sum += 0.5 * (x + y);
        var += 0.25 * (x - y) * (x - y);
        n += 1;
    }
    let n = n.max(1) as f64;
    (sum / n, var / (n * n))
}

/// Variance of the two halves' mean per pixel, relative to `norm` as relMSE
/// is to its reference, averaged over channels: one value per pixel, whose
/// mean is the trial's relative variance per pixel. Non-finite pixels count
/// as infinite error.
fn pixel_rel_var(a: &Image, b: &Image, norm: &[[f32; 3]]) -> Vec<f64> {
    a.pixels
        .iter()
        .zip(&b.pixels)
        .zip(norm)
        .map(|((x, y), r)| {
            let mut pixel = 0.0f64;
            for c in 0..3 {
                let d = (x[c] - y[c]) as f64;
                let r = r[c] as f64;
                pixel += 0.25 * d * d / (r * r + 0.01) / 3.0;
            }
            if pixel.is_finite() {
                pixel
            } else {
                f64::INFINITY
            }
        })
        .collect()
}

/// The mean of `values` and the standard error of that mean (from their
/// spread: pixels are the unit of independent samples); infinite when any
/// value is.
fn mean_and_standard_error(values: &[f64]) -> (f64, f64) {
    let n = values.len();
    let (mut sum, mut sum_sq) = (0.0f64, 0.0f64);
    for v in values {
        sum += v;
        sum_sq += v * v;
    }
    if n == 0 || !sum_sq.is_finite() {
        return (f64::INFINITY, f64::INFINITY);
    }
    let n = n as f64;
    let mean = sum / n;
    let var = (sum_sq / n - mean * mean).max(0.0) * n / (n - 1.0).max(1.0);
    (mean, (var / n).sqrt())
}

/// Efficiency of trial `t` as a multiple of PT's: PT's cost over its own
/// times its variance ratio to PT's, the latter shrunk towards 1 as far as
/// the pilot cannot measure it.
///
/// The cost per sample is counted, so it is exact for the pilot's paths;
/// the variance is not. A pilot of a few thousand samples per pixel block
/// sees a configuration's rare bright paths (caustics through glass, a long
/// walk in a dense medium) a handful of times or not at all, so one
/// configuration catching one firefly that another missed moved the
/// measured ratio by 10x-100x between seeds (BENCHMARKS.md, "auto").
/// Treating the log variance ratio `r` as normally distributed around the
/// truth with the delta-method variance `s2` of
/// `Trial::log_variance_ratio_var` (from the spread over pixels, so a
/// single firefly makes it as large as the ratio), and the truth as drawn from a
/// prior `N(0, tau^2)`, the posterior mean is `r tau^2 / (tau^2 + s2)`: a
/// ratio measured from many similar pixels is kept, one made by a few
/// pixels is pulled towards 1, where the exactly counted cost decides.
pub fn efficiency(pt: &Trial, t: &Trial, tau: f64) -> f64 {
    if !(t.cost > 0.0 && pt.cost > 0.0 && t.rel_var.is_finite() && pt.rel_var.is_finite()) {
        return if t.rel_var.is_finite() { 1.0 } else { 0.0 };
    }
    let cost_ratio = pt.cost / t.cost;
    if !(t.rel_var > 0.0 && pt.rel_var > 0.0) {
        // A black image on either side: no variance to compare.
        return cost_ratio.min(1.0);
    }
    let r = (t.rel_var / pt.rel_var).ln();
    let s2 = t.log_variance_ratio_var(pt);
    let tau2 = tau * tau;
    let shrunk = if tau2 + s2 > 0.0 {
        r * tau2 / (tau2 + s2)
    } else {
        0.0
    };
    cost_ratio * (-shrunk).exp()
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// A one-pixel pilot measures no spread: its variance ratio is not
    /// believed at all (the prior keeps it at 1 and the work decides),
    /// where a standard error of 0 made one pixel decide.
    #[test]
    fn one_pixel_measures_no_variance_ratio() {
        let mut pt = trial(1.0, 0.0, 1.0, None);
        let mut t = trial(0.01, 0.0, 2.0, Some(1));
        pt.pixel_rel_var = vec![1.0];
        t.pixel_rel_var = vec![0.01];
        assert!(t.log_variance_ratio_var(&pt).is_infinite());
        assert!((efficiency(&pt, &t, 0.35) - 0.5).abs() < 1e-12);
        let (low, high) = confirm::efficiency_bounds(&pt, &t, 2.0, 0.35);
        assert!(low.is_finite() && high.is_finite() && low < 0.5 && 0.5 < high);
    }

    /// The paired difference's noise: none where the candidate differs
    /// from PT by the same amount in both halves (a bias, not noise), and
    /// the unpaired value where the two are independent.
    #[test]
    fn the_paired_difference_cancels_what_both_renders_share() {
        let img = |v: &[f32]| Image {
            width: v.len() as u32,
            height: 1,
            pixels: v.iter().map(|&x| [x; 3]).collect(),
        };
        let (pa, pb) = (img(&[1.0, 5.0, 2.0, 8.0]), img(&[3.0, 1.0, 7.0, 2.0]));
        let shifted = |p: &Image| img(&p.pixels.iter().map(|q| q[0] + 0.5).collect::<Vec<_>>());
        assert_eq!(
            paired_difference_variance(&shifted(&pa), &shifted(&pb), &pa, &pb),
            0.0
        );
        let zero = img(&[0.0; 4]);
        let (_, pt_var) = mean_and_variance(&pa, &pb);
        let v = paired_difference_variance(&zero, &zero, &pa, &pb);
        assert!((v - pt_var).abs() < 1e-12 * pt_var, "{v} {pt_var}");
        assert_eq!(
            paired_difference_variance(&zero, &img(&[0.0; 3]), &pa, &pb),
            f64::INFINITY
        );
    }

    /// The split of the fitted entry cost adds back up to it for the
    /// decoder it was fitted on, and a smaller decoder costs less.
    #[test]
    fn an_entry_costs_what_was_fitted_and_less_with_a_smaller_decoder() {
        let work = WorkCounts::default();
        let entry = |macs: usize, noise: usize, heads: usize| {
            let mut st = EstimatorStats {
                entries: 1,
                ..Default::default()
            };
            for _ in 0..heads {
                st.count_decoder_rows(1, macs, noise);
            }
            work_cost(&work, &st)
        };
        // The fitted 17.8 with the decoder's row rescaled from 9.0 (1.1 +
        // 7.9 with matrixmultiply) to its own kernel's 5.67, all of it
        // 1.3x since the merged layout serves rays that cannot enter.
        let scale = 1.3;
        assert!(
            (entry(11_072, 16, 1) - scale * (17.8 - 9.0 + 5.67)).abs() < 0.02,
            "{}",
            entry(11_072, 16, 1)
        );
        // A vertex head of the same size: its row and its noise.
        assert!((entry(11_072, 16, 2) - entry(11_072, 16, 1) - scale * (5.67 + 1.8)).abs() < 0.02);
        // A smaller decoder saves what its multiply-adds cost.
        let saved = entry(11_072, 16, 1) - entry(3_488, 16, 1);
        assert!(
            (saved - scale * 5.5 * (11_072.0 - 3_488.0) / 11_072.0).abs() < 0.01,
            "{saved}"
        );
        assert!(entry(3_488, 8, 1) < entry(3_488, 16, 1));
    }

    /// A trial of P = `min_bounces` (`None`: PT), image mean 0.5.
    pub(super) fn trial(
        rel_var: f64,
        rel_var_se: f64,
        cost: f64,
        min_bounces: Option<u32>,
    ) -> Trial {
        Trial {
            choice: min_bounces.map(|p| Choice {
                min_bounces: p,
                entry_nee: EntryNee::Off,
            }),
            rel_var,
            rel_var_se,
            pixel_rel_var: Vec::new(),
            cost,
            efficiency: 0.0,
            mean: 0.5,
            mean_var: 0.0,
            paired_diff_var: f64::INFINITY,
            biased: false,
            skipped: false,
        }
    }

    #[test]
    fn a_precisely_measured_variance_ratio_is_kept() {
        let pt = trial(2.0, 0.0, 40.0, None);
        let t = trial(1.0, 0.0, 20.0, Some(1));
        // Cost ratio 2, variance ratio 0.5: 4x PT's efficiency.
        assert!((efficiency(&pt, &t, 0.35) - 4.0).abs() < 1e-12);
        // A vague prior keeps even a noisy ratio (the raw estimate).
        let noisy = trial(1.0, 1.0, 20.0, Some(1));
        assert!((efficiency(&pt, &noisy, 1e9) - 4.0).abs() < 1e-6);
    }

    #[test]
    fn a_ratio_made_by_one_firefly_falls_back_to_the_cost_ratio() {
        // The configuration's variance is one pixel's (its standard error
        // as large as the value) and 100x PT's: believed hardly at all.
        let pt = trial(0.1, 0.01, 170.0, None);
        let t = trial(10.0, 10.0, 42.0, Some(0));
        let e = efficiency(&pt, &t, 0.35);
        let cost_ratio = 170.0 / 42.0;
        assert!(e > 0.5 * cost_ratio && e < cost_ratio, "{e}");
        assert!(e > 50.0 * efficiency(&pt, &t, 1e9), "{e}");
    }

    /// A trial measured pixel by pixel, as the pilot makes them.
    fn trial_of_pixels(pixels: Vec<f64>, cost: f64, min_bounces: Option<u32>) -> Trial {
        let (rel_var, rel_var_se) = mean_and_standard_error(&pixels);
        Trial {
            pixel_rel_var: pixels,
            ..trial(rel_var, rel_var_se, cost, min_bounces)
        }
    }

    #[test]
    fn errors_shared_with_pt_pixel_by_pixel_do_not_blur_the_ratio() {
        // PT's pixel errors spread widely (a few bright pixels); the
        // candidate's follow them at 0.8x, as paths that agree with PT's
        // (same seeds) until they meet the estimator do.
        let pt_pixels: Vec<f64> = (0..64)
            .map(|i| if i % 16 == 0 { 50.0 } else { 1.0 })
            .collect();
        let pt = trial_of_pixels(pt_pixels.clone(), 40.0, None);
        let follows = trial_of_pixels(pt_pixels.iter().map(|v| 0.8 * v).collect(), 40.0, Some(1));
        assert!(follows.log_variance_ratio_var(&pt) < 1e-20);
        assert!((efficiency(&pt, &follows, 0.35) - 1.25).abs() < 1e-9);
        // The same two spreads, but in different pixels (the candidate's
        // bright pixels are not PT's): the ratio is as uncertain as the
        // two spreads say, and it is discounted.
        let mut shifted = pt_pixels.iter().map(|v| 0.8 * v).collect::<Vec<_>>();
        shifted.rotate_left(8);
        let apart = trial_of_pixels(shifted, 40.0, Some(1));
        let independent =
            (apart.rel_var_se / apart.rel_var).powi(2) + (pt.rel_var_se / pt.rel_var).powi(2);
        let paired = apart.log_variance_ratio_var(&pt);
        assert!(
            (paired / independent - 1.0).abs() < 0.2,
            "{paired} {independent}"
        );
        let e = efficiency(&pt, &apart, 0.35);
        assert!(e > 1.0 && e < 1.2, "{e}");
    }

    #[test]
    fn unusable_measurements_never_choose_an_estimator() {
        let pt = trial(1.0, 0.1, 40.0, None);
        for t in [
            trial(f64::INFINITY, f64::INFINITY, 20.0, Some(1)),
            trial(f64::NAN, 0.0, 20.0, Some(1)),
            trial(0.0, 0.0, 20.0, Some(1)),
            trial(1.0, 0.1, 0.0, Some(1)),
        ] {
            let e = efficiency(&pt, &t, 0.35);
            assert!(e <= 1.0, "{t:?}: {e}");
        }
    }

    #[test]
    fn ties_go_to_the_cheaper_configuration_and_losers_stay_off() {
        let opts = PilotOptions::default();
        let with = |eff: f64, cost: f64, p: u32| Trial {
            efficiency: eff,
            ..trial(1.0, 0.1, cost, Some(p))
        };
        // P = 2 measured 10% more efficient, but P = 1 does less work.
        let c = choose(&[with(1.3, 30.0, 1), with(1.43, 32.0, 2)], &opts);
        assert_eq!(c.map(|c| c.min_bounces), Some(1));
        // Beyond the tie the more efficient one wins.
        let c = choose(&[with(1.2, 30.0, 1), with(2.0, 32.0, 2)], &opts);
        assert_eq!(c.map(|c| c.min_bounces), Some(2));
        // A cheap configuration below the margin is not chosen by the tie.
        let below = opts.margin * 0.98;
        let c = choose(&[with(below, 20.0, 0), with(below * 1.1, 32.0, 2)], &opts);
        assert_eq!(c.map(|c| c.min_bounces), Some(2));
        // Nothing beats PT by the margin: off.
        assert_eq!(
            choose(&[with(below, 30.0, 1), with(0.0, 10.0, 0)], &opts),
            None
        );
        assert_eq!(choose(&[], &opts), None);
    }

    #[test]
    fn a_trial_says_what_its_efficiency_is_made_of() {
        let pt = trial(1.0, 0.3, 40.0, None);
        let t = trial(2.0, 0.8, 20.0, Some(1));
        // se: sqrt(0.4^2 + 0.3^2) = 0.5.
        assert_eq!(t.against(&pt), "work 0.50x, variance 2.00x +-50%");
        let broken = trial(f64::INFINITY, f64::INFINITY, 20.0, Some(1));
        assert_eq!(broken.against(&pt), "not measurable");
    }

    proptest! {
        /// Shrinkage only ever moves the efficiency from its raw value
        /// towards the cost ratio, and more uncertainty moves it further.
        #[test]
        fn efficiency_lies_between_the_cost_ratio_and_the_raw_estimate(
            v_pt in 1e-3f64..10.0, v_t in 1e-3f64..10.0,
            rel_se_pt in 0.0f64..2.0, rel_se_t in 0.0f64..2.0, more in 0.0f64..2.0,
            c_pt in 1.0f64..200.0, c_t in 1.0f64..200.0, tau in 0.05f64..3.0,
        ) {
            let pt = trial(v_pt, rel_se_pt * v_pt, c_pt, None);
            let t = trial(v_t, rel_se_t * v_t, c_t, Some(1));
            let e = efficiency(&pt, &t, tau);
            let cost_ratio = c_pt / c_t;
            let raw = cost_ratio * v_pt / v_t;
            let (lo, hi) = (cost_ratio.min(raw), cost_ratio.max(raw));
            prop_assert!(e >= lo * (1.0 - 1e-9) && e <= hi * (1.0 + 1e-9), "{e} not in [{lo}, {hi}]");
            let vaguer = trial(v_t, (rel_se_t + more) * v_t, c_t, Some(1));
            let e2 = efficiency(&pt, &vaguer, tau);
            prop_assert!((e2 / cost_ratio).ln().abs() <= (e / cost_ratio).ln().abs() + 1e-9);
        }
    }
}
