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
    normalization, pilot, score, trial, work_cost,
};
use crate::estimator::Estimators;
use crate::film::{PixelSum, film_image};
use crate::image_io::Image;
use crate::render::{RenderOptions, RenderStats, render, render_after, render_film};
use crate::scene_data::RenderScene;
use std::ops::Range;
use std::time::Instant;

/// Samples of every pixel rendered by the confirmation pass in one
/// configuration (both halves), kept for the image.
pub struct Segment {
    pub samples: Range<u32>,
    /// `None`: plain PT; otherwise estimator `.0` alone, in configuration `.1`.
    pub only: Option<(usize, Choice)>,
    film: Vec<PixelSum>,
    stats: RenderStats,
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
    let base = ests.per_instance.clone();
    let (ests, decision) = pilot(rs, ests, opts);
    let mut plan = Plan {
        decision,
        estimators: Some(ests),
        base,
        segments: Vec::new(),
        pilot_seconds: t.elapsed().as_secs_f64(),
    };
    let h = opts.confirm_spp;
    let pixels = rs.camera.width as u64 * rs.camera.height as u64;
    let fits = if h == 0 || pixels > opts.confirm_max_pixels {
        0
    } else {
        (render.spp / 2 / (2 * h)).saturating_sub(1) as usize
    };
    let mut unsure: Vec<(usize, Choice)> = plan
        .decision
        .estimators
        .iter()
        .enumerate()
        .filter_map(|(k, d)| unsure_candidate(&plan.decision.pt, d, opts).map(|c| (k, c)))
        .collect();
    unsure.truncate(fits);
    if !unsure.is_empty() {
        plan.confirm(rs, &unsure, opts, render);
    }
    plan.install(rs, Config::Decided);
    plan
}

/// The candidate to confirm for one estimator, `None` where the pilot is
/// sure (see [`PilotOptions::confirm_sigmas`]): the configuration the pilot
/// chose, or, where it chose none, the one it would have chosen without
/// [`PilotOptions::margin`].
fn unsure_candidate(pt: &Trial, d: &EstimatorDecision, opts: &PilotOptions) -> Option<Choice> {
    let choice = d
        .choice
        .or_else(|| super::choose(&d.trials, &PilotOptions { margin: 0.0, ..*opts }))?;
    let t = d.trials.iter().find(|t| t.choice == Some(choice))?;
    let (low, high) = efficiency_bounds(pt, t, opts.confirm_sigmas);
    (high >= 1.0 && low < opts.margin).then_some(choice)
}

/// `t`'s efficiency over PT's with its variance ratio `sigmas` standard
/// errors above and below the measured one (unshrunk): (low, high). (0, 0)
/// for a trial that cannot be used.
fn efficiency_bounds(pt: &Trial, t: &Trial, sigmas: f64) -> (f64, f64) {
    let r = (t.rel_var / pt.rel_var).ln();
    let s = t.log_variance_ratio_var(pt).sqrt();
    let cost_ratio = pt.cost / t.cost;
    let (low, high) = (
        cost_ratio * (-r - sigmas * s).exp(),
        cost_ratio * (-r + sigmas * s).exp(),
    );
    if t.biased || t.skipped || !(low.is_finite() && high.is_finite()) {
        (0.0, 0.0)
    } else {
        (low, high)
    }
}

impl Plan {
    /// Renders PT's segment and one per `unsure` estimator (its position in
    /// the decision, its candidate), measures them as the pilot measures
    /// its renders, and decides those estimators.
    fn confirm(
        &mut self,
        rs: &mut RenderScene,
        unsure: &[(usize, Choice)],
        opts: &PilotOptions,
        render: &RenderOptions,
    ) {
        let h = opts.confirm_spp;
        let ropts = RenderOptions {
            progress: false,
            ..*render
        };
        let (width, height) = (rs.camera.width, rs.camera.height);
        // Each configuration's two halves, as images, and its cost per sample.
        let mut measured: Vec<(Image, Image, f64)> = Vec::new();
        let configs: Vec<Option<(usize, Choice)>> = std::iter::once(None)
            .chain(
                unsure
                    .iter()
                    .map(|&(k, c)| Some((self.decision.estimators[k].index, c))),
            )
            .collect();
        for (n, only) in configs.into_iter().enumerate() {
            let start = 2 * h * n as u32;
            self.install(rs, Config::Segment(only));
            let (mut film, a_stats) = render_film(rs, &ropts, start..start + h);
            let (second, b_stats) = render_film(rs, &ropts, start + h..start + 2 * h);
            let a = film_image(width, height, &film);
            let b = film_image(width, height, &second);
            for (f, p) in film.iter_mut().zip(&second) {
                f.merge(p);
            }
            let mut stats = a_stats;
            stats.merge(&b_stats);
            let cost =
                work_cost(&stats.work, &stats.estimators) / stats.samples.max(1) as f64;
            measured.push((a, b, cost));
            self.segments.push(Segment {
                samples: start..start + 2 * h,
                only,
                film,
                stats,
            });
        }
        let images: Vec<&Image> = measured.iter().flat_map(|(a, b, _)| [a, b]).collect();
        let norm = normalization(&images, width);
        let (pa, pb, pt_cost) = &measured[0];
        let pt = trial(&norm, None, pa, pb, *pt_cost);
        for (&(k, choice), (a, b, cost)) in unsure.iter().zip(&measured[1..]) {
            let mut t = trial(&norm, Some(choice), a, b, *cost);
            score(&pt, &mut t, opts);
            let d = &mut self.decision.estimators[k];
            d.choice = (t.efficiency >= opts.confirm_margin).then_some(choice);
            d.confirmed = Some(t);
        }
        self.decision.confirmation = Some(super::ConfirmationSummary {
            pt,
            samples: self.rest_start(),
        });
    }

    /// The first sample of every pixel rendered in the decided configuration.
    pub fn rest_start(&self) -> u32 {
        self.segments.last().map_or(0, |s| s.samples.end)
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
            for (b, p) in before.iter_mut().zip(&seg.film) {
                b.merge(p);
            }
        }
        let (img, mut stats) = render_after(rs, opts, self.rest_start()..opts.spp, &before);
        for seg in &self.segments {
            stats.merge(&seg.stats);
        }
        (img, stats)
    }

    /// The film of samples `range` (a render part, `--shard`/`--samples`):
    /// bit for bit the same samples [`Plan::render`] renders there. A
    /// confirmation segment inside the range is reused (its seconds are the
    /// plan's, not the part's); one the range cuts is rendered again for its
    /// share.
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
            for (f, p) in film.iter_mut().zip(part) {
                f.merge(p);
            }
            stats.merge(st);
        };
        for k in 0..self.segments.len() {
            let s = &self.segments[k].samples;
            let (a, b) = (s.start.max(range.start), s.end.min(range.end));
            if a >= b {
                continue;
            }
            if (a, b) == (s.start, s.end) {
                let seg = &self.segments[k];
                let st = RenderStats {
                    seconds: 0.0,
                    ..seg.stats.clone()
                };
                add(&mut film, &seg.film, &st);
            } else {
                self.install(rs, Config::Segment(self.segments[k].only));
                let (part, st) = render_film(rs, opts, a..b);
                add(&mut film, &part, &st);
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
