//! The confirmation pass of `--estimators auto`: where the pilot cannot
//! tell whether an estimator pays, plain PT and the estimator's candidate
//! render the first samples of the image itself, at its full resolution,
//! two halves each, and that measurement decides.
//!
//! Why: the pilot is a quarter of the resolution and a few thousand
//! samples, and on glass it measures another image than the render's. Its
//! pixels average over 16 of the render's, whose antialiasing variance both
//! configurations share (on the default scene the first-vertex-NEE
//! estimator's variance came out 0.98x PT's +-1% where the render has
//! 1.17x), and it sees PT's rare caustic paths a handful of times (on
//! `glass-front-lamp` P = 1's variance 1.3x-1.6x PT's where the render has
//! 0.81x). At the render's resolution, 4 spp per half, the same ratios
//! came out 0.76x-1.0x (+-10%) and on `glass-moved` 0.77x-0.86x (+-4%)
//! against the render's 0.80x (BENCHMARKS.md, "auto").
//!
//! What it costs: nothing beyond the image's own samples. Samples
//! `0..2h` of every pixel are PT's, the next `2h` each candidate's, the rest
//! the decided configuration's; every one of them is an estimate of the
//! same pixel, and films of disjoint sample ranges merge exactly, so the
//! image is their mean, bit for bit the same at any thread count and when
//! rendered in parts. The price of a wrong guess is that of `2h` samples of
//! the other configuration, which is small exactly where the pilot could
//! not tell the two apart; where it could (a loser measured precisely, the
//! jade knot at 4x PT's efficiency), nothing is confirmed.

use super::{
    Choice, Decision, EstimatorDecision, PilotOptions, Trial, configure_alone, configure_decided,
    normalization, pilot, score, work_cost,
};
use crate::estimator::Estimators;
use crate::film::{PixelSum, film_image};
use crate::image_io::Image;
use crate::render::{RenderOptions, RenderStats, render, render_after, render_film};
use crate::scene_data::RenderScene;
use rayon::prelude::*;
use std::ops::Range;
use std::time::Instant;

/// The samples of every pixel one configuration rendered in the confirmation
/// pass (all its rounds), kept for the image.
pub struct Segment {
    /// Its sample ranges, one per round it took part in.
    pub samples: Vec<Range<u32>>,
    /// `None`: plain PT; otherwise estimator `.0` alone, in configuration `.1`.
    pub only: Option<(usize, Choice)>,
    film: Vec<PixelSum>,
    stats: RenderStats,
}

impl Segment {
    /// Samples per pixel, all rounds.
    pub fn sample_count(&self) -> u32 {
        self.samples.iter().map(|r| r.end - r.start).sum()
    }
}

/// What `--estimators auto` renders: the decision, and the samples the
/// confirmation pass rendered for the image. The estimators move between
/// the plan and the scene as each range of samples needs them; after
/// [`plan`], [`Plan::render`] and [`Plan::render_part`] the scene holds the
/// decided configuration.
pub struct Plan {
    pub decision: Decision,
    /// The estimators while the scene does not hold them.
    estimators: Option<Estimators>,
    /// Every instance's estimator as loaded.
    base: Vec<Option<u32>>,
    /// PT's first, then each confirmed estimator's.
    pub segments: Vec<Segment>,
    /// Seconds of the pilot (the confirmation's renders are the image's
    /// and counted with it).
    pub pilot_seconds: f64,
}

/// Which estimators a range of samples is rendered with.
#[derive(Clone, Copy)]
enum Config {
    Segment(Option<(usize, Choice)>),
    Decided,
}

/// The pilot ([`super::decide`]), then the confirmation pass for the
/// estimators it was unsure of, as many as fit in half of the render's
/// samples (the others keep the pilot's decision). `render` is the render
/// the plan is for (its spp, seed and M); the confirmation renders its
/// samples. Leaves the decided configuration in `rs`.
pub fn plan(
    rs: &mut RenderScene,
    ests: Estimators,
    opts: &PilotOptions,
    render: &RenderOptions,
) -> Plan {
    let t = Instant::now();
    let base = ests.per_instance().to_vec();
    let (ests, decision) = pilot(rs, ests, opts);
    let mut plan = Plan {
        decision,
        estimators: Some(ests),
        base,
        segments: Vec::new(),
        pilot_seconds: t.elapsed().as_secs_f64(),
    };
    let unsure: Vec<(usize, Choice)> = plan
        .decision
        .estimators
        .iter()
        .enumerate()
        .filter_map(|(k, d)| unsure_candidate(&plan.decision.pt, d, opts).map(|c| (k, c)))
        .collect();
    let h = opts.confirm_spp;
    let pixels = rs.camera.width as u64 * rs.camera.height as u64;
    if h > 0 && pixels <= opts.confirm_max_pixels && !unsure.is_empty() {
        // Rounds of two halves per configuration, PT's and each unsure
        // estimator's, within half of the render's samples: as many
        // estimators as get at least one round.
        let per_round = |n: usize| 2 * h * (1 + n as u32);
        let n = (0..=unsure.len())
            .rev()
            .find(|&n| per_round(n) <= render.spp / 2)
            .unwrap_or(0);
        let rounds = (render.spp / 2 / per_round(n.max(1))).min(opts.confirm_rounds);
        if n > 0 && rounds > 0 {
            plan.confirm(rs, &unsure[..n], rounds, opts, render);
        }
    }
    plan.install(rs, Config::Decided);
    plan
}

/// The candidate to confirm for one estimator, `None` where the pilot is
/// sure (see [`PilotOptions::confirm_sigmas`]): the configuration the pilot
/// chose, or, where it chose none, the one it would have chosen without
/// [`PilotOptions::margin`]. Sure of off where even the optimistic bound
/// stays below the margin (at 1.0 instead, the default scene's and
/// cornell-gold's knots, 1.10x PT's work and a variance the
/// quarter-resolution pilot puts at 0.98x-1.0x +-5%, were confirmed at
/// half of the seeds, 4-8 samples per pixel of a loser each time).
fn unsure_candidate(pt: &Trial, d: &EstimatorDecision, opts: &PilotOptions) -> Option<Choice> {
    let choice = d.choice.or_else(|| {
        super::choose(
            &d.trials,
            &PilotOptions {
                margin: 0.0,
                ..*opts
            },
        )
    })?;
    let t = d.trials.iter().find(|t| t.choice == Some(choice))?;
    let (low, high) = efficiency_bounds(pt, t, opts.confirm_sigmas, opts.variance_ratio_prior);
    (high >= opts.margin && low < opts.margin).then_some(choice)
}

/// `t`'s efficiency over PT's with its log variance ratio `sigmas`
/// standard deviations above and below its posterior mean, under the prior
/// [`super::efficiency`] shrinks with ([`PilotOptions::variance_ratio_prior`]):
/// (low, high). (0, 0) for a trial that cannot be used.
///
/// The posterior, not the measurement alone: on cornell-jade the pilot
/// measures P = 0's variance at 0.5x-2.9x PT's, +-50-78%, for a quarter of
/// PT's work; unshrunk, that made it unsure, and confirming it spent 8
/// samples per pixel of PT, 4x the estimator's cost each (auto 8.9x PT's
/// efficiency where P = 0 alone is 11.2x).
pub(super) fn efficiency_bounds(pt: &Trial, t: &Trial, sigmas: f64, tau: f64) -> (f64, f64) {
    let r = (t.rel_var / pt.rel_var).ln();
    let s2 = t.log_variance_ratio_var(pt);
    let tau2 = tau * tau;
    let (mean, sd) = if s2.is_infinite() {
        // Unmeasured: the prior alone.
        (0.0, tau)
    } else if tau2 + s2 > 0.0 {
        (r * tau2 / (tau2 + s2), (tau2 * s2 / (tau2 + s2)).sqrt())
    } else {
        (0.0, 0.0)
    };
    let cost_ratio = pt.cost / t.cost;
    let (low, high) = (
        cost_ratio * (-mean - sigmas * sd).exp(),
        cost_ratio * (-mean + sigmas * sd).exp(),
    );
    if t.biased || t.skipped || !(low.is_finite() && high.is_finite()) {
        (0.0, 0.0)
    } else {
        (low, high)
    }
}

/// Per pixel, the sums of a configuration's half images (each of `spp`
/// samples) and of their squares: its variance per sample from all its
/// halves (`halves - 1` degrees of freedom per pixel, where the pilot's two
/// halves give one).
struct Halves {
    spp: u32,
    halves: u32,
    sum: Vec<[f64; 3]>,
    sum_sq: Vec<[f64; 3]>,
}

impl Halves {
    fn new(pixels: usize, spp: u32) -> Self {
        Self {
            spp,
            halves: 0,
            sum: vec![[0.0; 3]; pixels],
            sum_sq: vec![[0.0; 3]; pixels],
        }
    }

    fn add(&mut self, img: &Image) {
        self.halves += 1;
        self.sum
            .par_iter_mut()
            .zip(&mut self.sum_sq)
            .zip(&img.pixels)
            .for_each(|((s, q), p)| {
                for c in 0..3 {
                    let v = if p[c].is_finite() { p[c] as f64 } else { 0.0 };
                    s[c] += v;
                    q[c] += v * v;
                }
            });
    }

    /// The mean of the halves (for the normalization).
    fn mean(&self, width: u32, height: u32) -> Image {
        let mut img = Image::new(width, height);
        let k = self.halves.max(1) as f64;
        for (o, s) in img.pixels.iter_mut().zip(&self.sum) {
            *o = s.map(|v| (v / k) as f32);
        }
        img
    }

    /// Its trial against the normalization `norm`, as [`super::trial`]
    /// measures the pilot's two halves, but per sample: configurations that
    /// stopped after different rounds compare.
    fn trial(&self, norm: &[[f32; 3]], choice: Option<Choice>, cost: f64) -> Trial {
        let k = self.halves as f64;
        let n = self.sum.len().max(1) as f64;
        let (mut total, mut mean_var) = (0.0f64, 0.0f64);
        let pixel_rel_var: Vec<f64> = self
            .sum
            .iter()
            .zip(&self.sum_sq)
            .zip(norm)
            .map(|((s, q), r)| {
                let mut pixel = 0.0f64;
                for c in 0..3 {
                    // The variance of one half's mean, unbiased.
                    let var_half = ((q[c] - s[c] * s[c] / k) / (k - 1.0)).max(0.0);
                    let r = r[c] as f64;
                    pixel += var_half * self.spp as f64 / (r * r + 0.01) / 3.0;
                    total += s[c] / k;
                    mean_var += var_half / k;
                }
                pixel
            })
            .collect();
        let channels = 3.0 * n;
        Trial::measured(
            choice,
            pixel_rel_var,
            cost,
            total / channels,
            mean_var / (channels * channels),
        )
    }
}

/// Adds film `part` to `film`, pixel by pixel.
fn merge_into(film: &mut [PixelSum], part: &[PixelSum]) {
    film.par_iter_mut().zip(part).for_each(|(f, p)| f.merge(p));
}

impl Plan {
    /// Renders, in up to `rounds` rounds, two halves of PT and of each
    /// `unsure` estimator's candidate (its position in the decision, its
    /// candidate), measures them as the pilot measures its renders, and
    /// decides those estimators: on where even the variance ratio
    /// [`PilotOptions::confirm_stop_sigmas`] standard errors worse beats PT by
    /// [`PilotOptions::confirm_margin`], off where even that much better
    /// does not, and after the last round by the measured efficiency. An
    /// estimator decided early renders no more rounds (a loser measured at
    /// full resolution is off after one: its samples in the image are a
    /// loser's), and PT stops when all are decided.
    fn confirm(
        &mut self,
        rs: &mut RenderScene,
        unsure: &[(usize, Choice)],
        rounds: u32,
        opts: &PilotOptions,
        render: &RenderOptions,
    ) {
        let h = opts.confirm_spp;
        let ropts = RenderOptions {
            progress: false,
            ..*render
        };
        let (width, height) = (rs.camera.width, rs.camera.height);
        let pixels = width as usize * height as usize;
        let configs: Vec<Option<(usize, Choice)>> = std::iter::once(None)
            .chain(
                unsure
                    .iter()
                    .map(|&(k, c)| Some((self.decision.estimators[k].index, c))),
            )
            .collect();
        let mut halves: Vec<Halves> = configs.iter().map(|_| Halves::new(pixels, h)).collect();
        self.segments = configs
            .iter()
            .map(|&only| Segment {
                samples: Vec::new(),
                only,
                film: vec![PixelSum::default(); pixels],
                stats: RenderStats::default(),
            })
            .collect();
        // Per unsure estimator: decided yet?
        let mut decided = vec![false; unsure.len()];
        let mut next = 0u32;
        let mut pt = None;
        for round in 0..rounds {
            for (c, &only) in configs.iter().enumerate() {
                if c > 0 && decided[c - 1] {
                    continue;
                }
                self.install(rs, Config::Segment(only));
                let seg = &mut self.segments[c];
                seg.samples.push(next..next + 2 * h);
                for _ in 0..2 {
                    let (film, stats) = render_film(rs, &ropts, next..next + h);
                    halves[c].add(&film_image(width, height, &film));
                    merge_into(&mut seg.film, &film);
                    seg.stats.merge(&stats);
                    next += h;
                }
            }
            let means: Vec<Image> = halves.iter().map(|x| x.mean(width, height)).collect();
            let norm = normalization(&means.iter().collect::<Vec<_>>(), width);
            let cost = |seg: &Segment| {
                work_cost(&seg.stats.work, &seg.stats.estimators) / seg.stats.samples.max(1) as f64
            };
            let pt_trial = halves[0].trial(&norm, None, cost(&self.segments[0]));
            let last = round + 1 == rounds;
            for (u, &(k, choice)) in unsure.iter().enumerate() {
                if decided[u] {
                    continue;
                }
                let mut t = halves[u + 1].trial(&norm, Some(choice), cost(&self.segments[u + 1]));
                score(&pt_trial, &mut t, opts);
                let (low, high) = efficiency_bounds(
                    &pt_trial,
                    &t,
                    opts.confirm_stop_sigmas,
                    opts.variance_ratio_prior,
                );
                let on = if t.biased || high < opts.confirm_margin {
                    Some(false)
                } else if low >= opts.confirm_margin {
                    Some(true)
                } else if last {
                    Some(t.efficiency >= opts.confirm_margin)
                } else {
                    None
                };
                let d = &mut self.decision.estimators[k];
                if let Some(on) = on {
                    decided[u] = true;
                    d.choice = on.then_some(choice);
                }
                d.confirmed = Some(t);
            }
            pt = Some(pt_trial);
            if decided.iter().all(|&d| d) {
                break;
            }
        }
        self.decision.confirmation_pt = pt;
    }

    /// The first sample of every pixel rendered in the decided configuration.
    pub fn rest_start(&self) -> u32 {
        self.segments
            .iter()
            .flat_map(|s| &s.samples)
            .map(|r| r.end)
            .max()
            .unwrap_or(0)
    }

    /// Seconds the confirmation pass's renders took.
    pub fn confirmation_seconds(&self) -> f64 {
        self.segments.iter().map(|s| s.stats.seconds).sum()
    }

    /// Puts the estimators configured as `config` into `rs` (or none, for
    /// plain PT or where all are off).
    fn install(&mut self, rs: &mut RenderScene, config: Config) {
        if let Some(e) = rs.estimators.take() {
            self.estimators = Some(e);
        }
        let Some(mut e) = self.estimators.take() else {
            return;
        };
        let on = match config {
            Config::Segment(None) => false,
            Config::Segment(Some((index, choice))) => {
                configure_alone(&mut e, &self.base, index, choice);
                true
            }
            Config::Decided => {
                configure_decided(&mut e, &self.base, &self.decision);
                e.any_in_use()
            }
        };
        if on {
            rs.estimators = Some(e);
        } else {
            self.estimators = Some(e);
        }
    }

    /// The whole image: the confirmation's samples and the rest in the
    /// decided configuration. Its statistics count both (the pilot not).
    pub fn render(&mut self, rs: &mut RenderScene, opts: &RenderOptions) -> (Image, RenderStats) {
        self.install(rs, Config::Decided);
        if self.segments.is_empty() {
            return render(rs, opts);
        }
        let mut before = vec![PixelSum::default(); self.segments[0].film.len()];
        for seg in &self.segments {
            merge_into(&mut before, &seg.film);
        }
        let (img, mut stats) = render_after(rs, opts, self.rest_start()..opts.spp, &before);
        for seg in &self.segments {
            stats.merge(&seg.stats);
        }
        (img, stats)
    }

    /// The film of samples `range` (a render part, `--shard`/`--samples`):
    /// bit for bit the same samples [`Plan::render`] renders there. A
    /// configuration's confirmation samples all inside the range are reused
    /// (their seconds are the plan's, not the part's); those the range cuts
    /// are rendered again for its share.
    pub fn render_part(
        &mut self,
        rs: &mut RenderScene,
        opts: &RenderOptions,
        range: Range<u32>,
    ) -> (Vec<PixelSum>, RenderStats) {
        let pixels = rs.camera.width as usize * rs.camera.height as usize;
        let mut film = vec![PixelSum::default(); pixels];
        let mut stats = RenderStats::default();
        let mut add = |film: &mut Vec<PixelSum>, part: &[PixelSum], st: &RenderStats| {
            merge_into(film, part);
            stats.merge(st);
        };
        for k in 0..self.segments.len() {
            let inside = |r: &Range<u32>| range.start <= r.start && r.end <= range.end;
            if self.segments[k].samples.iter().all(inside) {
                let seg = &self.segments[k];
                let st = RenderStats {
                    seconds: 0.0,
                    ..seg.stats.clone()
                };
                add(&mut film, &seg.film, &st);
                continue;
            }
            self.install(rs, Config::Segment(self.segments[k].only));
            for r in self.segments[k].samples.clone() {
                let (a, b) = (r.start.max(range.start), r.end.min(range.end));
                if a < b {
                    let (part, st) = render_film(rs, opts, a..b);
                    add(&mut film, &part, &st);
                }
            }
        }
        self.install(rs, Config::Decided);
        let a = self.rest_start().max(range.start);
        if a < range.end {
            let (part, st) = render_film(rs, opts, a..range.end);
            add(&mut film, &part, &st);
        }
        (film, stats)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn image(values: &[f32]) -> Image {
        let mut img = Image::new(values.len() as u32, 1);
        for (p, v) in img.pixels.iter_mut().zip(values) {
            *p = [*v; 3];
        }
        img
    }

    #[test]
    fn two_halves_measure_per_sample_what_the_pilot_measures_per_pixel() {
        let (a, b) = (image(&[1.0, 2.0, 0.5, 4.0]), image(&[1.5, 1.0, 0.5, 0.0]));
        let norm = vec![[1.0f32; 3]; 4];
        let pilot = super::super::trial(&norm, None, &a, &b, 1.0);
        let mut halves = Halves::new(4, 3);
        halves.add(&a);
        halves.add(&b);
        let t = halves.trial(&norm, None, 1.0);
        // The pilot's: the variance of a pixel's mean of two halves of 3
        // samples; the confirmation's: of one sample.
        for (x, y) in t.pixel_rel_var.iter().zip(&pilot.pixel_rel_var) {
            assert!((x - 6.0 * y).abs() <= 1e-12, "{x} against 6 x {y}");
        }
        assert!((t.mean - pilot.mean).abs() < 1e-12);
        assert!((t.mean_var - pilot.mean_var).abs() < 1e-15);
    }

    use super::super::tests::trial;

    #[test]
    fn only_what_the_pilot_cannot_tell_is_confirmed() {
        let opts = PilotOptions::default();
        let pt = trial(1.0, 0.01, 1.0, None);
        let decided = |mut t: Trial| {
            super::super::score(&pt, &mut t, &opts);
            EstimatorDecision {
                index: 0,
                choice: super::super::choose(std::slice::from_ref(&t), &opts),
                trials: vec![t],
                confirmed: None,
            }
        };
        // A loser measured precisely, a winner by multiples: sure.
        let loser = decided(trial(1.2, 0.012, 1.1, Some(2)));
        assert_eq!(unsure_candidate(&pt, &loser, &opts), None);
        let winner = decided(trial(0.3, 0.03, 0.3, Some(0)));
        assert!(winner.choice.is_some());
        assert_eq!(unsure_candidate(&pt, &winner, &opts), None);
        // A variance ratio made by a few bright pixels: confirmed, whichever
        // way the pilot went.
        let coin = decided(trial(0.8, 0.3, 0.97, Some(1)));
        assert_eq!(
            unsure_candidate(&pt, &coin, &opts).map(|c| c.min_bounces),
            Some(1)
        );
        // Unusable (its image mean is wrong): never.
        let biased = decided(Trial {
            mean: 0.25,
            ..trial(0.8, 0.3, 0.97, Some(1))
        });
        assert!(biased.trials[0].biased);
        assert_eq!(unsure_candidate(&pt, &biased, &opts), None);
    }
}
