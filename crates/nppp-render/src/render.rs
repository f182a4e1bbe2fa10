//! The render driver: tiles in parallel with rayon, one wavefront per worker,
//! a progress bar on stderr, and the statistics a user needs to trust the image.

use crate::camera::jitter;
use crate::estimator::EstimatorStats;
use crate::film::PixelSum;
use crate::image_io::Image;
use crate::integrator::{IntegratorSettings, Wavefront, WorkCounts};
use crate::path::PathState;
use crate::scene_data::RenderScene;
use indicatif::{ProgressBar, ProgressDrawTarget};
use nppp_geom::SampleRng;
use rayon::prelude::*;
use std::ops::Range;
use std::time::{Duration, Instant};

pub const TILE: u32 = 16;
/// Paths per wavefront batch: large enough to amortize batched work, small
/// enough to stay in cache.
pub const BATCH_PATHS: usize = 4096;

#[derive(Clone, Copy, Debug)]
pub struct RenderOptions {
    pub spp: u32,
    pub max_bounces: u32,
    pub seed: u64,
    pub progress: bool,
}

#[derive(Clone, Debug, Default)]
pub struct RenderStats {
    pub seconds: f64,
    pub samples: u64,
    /// Samples dropped because their radiance was NaN or infinite.
    pub dropped_samples: u64,
    pub estimators: crate::estimator::EstimatorStats,
    /// Rays traced, counted (deterministic, unlike `seconds`).
    pub work: WorkCounts,
}

impl RenderStats {
    pub fn samples_per_second(&self) -> f64 {
        self.samples as f64 / self.seconds.max(1e-9)
    }

    /// Adds another render's statistics (its time included): a render made
    /// of several sample ranges counts all of them.
    pub fn merge(&mut self, o: &RenderStats) {
        self.seconds += o.seconds;
        self.samples += o.samples;
        self.dropped_samples += o.dropped_samples;
        self.estimators.merge(&o.estimators);
        self.work.merge(&o.work);
    }
}

/// Renders `scene` into a new image.
///
/// The image is split into bands of `TILE` rows; each band's tiles render in
/// parallel and their means go straight into the band, so the only
/// full-resolution buffer is the f32 image itself (12 bytes per pixel: 3.2 GB
/// at the largest allowed 16384 x 16384), never a full-resolution film of sums.
///
/// Panics if estimators are attached to a scene built by
/// [`RenderScene::new`]: their instances were merged into the world BLAS and
/// the estimators would silently never be used.
pub fn render(scene: &RenderScene, opts: &RenderOptions) -> (Image, RenderStats) {
    let mut img = Image::new(scene.camera.width, scene.camera.height);
    let stats = render_into(scene, opts, 0..opts.spp, &mut img.pixels, |_, p| p.mean());
    (img, stats)
}

/// Renders samples `samples` of every pixel on top of `before`, the film of
/// samples rendered already (by other configurations: `--estimators auto`'s
/// confirmation pass), into the image of all of them. The result is bit for
/// bit the mean of the merged films, without a second full-resolution film.
pub fn render_after(
    scene: &RenderScene,
    opts: &RenderOptions,
    samples: Range<u32>,
    before: &[PixelSum],
) -> (Image, RenderStats) {
    let mut img = Image::new(scene.camera.width, scene.camera.height);
    assert_eq!(before.len(), img.pixels.len(), "film size");
    let stats = render_into(scene, opts, samples, &mut img.pixels, |i, p| {
        let mut all = before[i];
        all.merge(p);
        all.mean()
    });
    (img, stats)
}

/// Renders samples `samples` (of `0..opts.spp`) of every pixel and returns
/// the film: each pixel's exact sums, row-major. Films of disjoint sample
/// ranges merge ([`PixelSum::merge`]) into exactly the film of their union,
/// so their means are bit for bit those of [`render`] (`nppp render
/// --shard`). The film takes 128 bytes per pixel.
pub fn render_film(
    scene: &RenderScene,
    opts: &RenderOptions,
    samples: Range<u32>,
) -> (Vec<PixelSum>, RenderStats) {
    let (w, h) = (scene.camera.width, scene.camera.height);
    let mut film = vec![PixelSum::default(); w as usize * h as usize];
    let stats = render_into(scene, opts, samples, &mut film, |_, p| *p);
    (film, stats)
}

/// Renders samples `samples` of every pixel into `out` (row-major), each
/// pixel's accumulated samples turned into an output value by `finish`
/// (given the pixel's row-major index).
fn render_into<T: Send>(
    scene: &RenderScene,
    opts: &RenderOptions,
    samples: Range<u32>,
    out: &mut [T],
    finish: impl Fn(usize, &PixelSum) -> T + Sync,
) -> RenderStats {
    if let Some(e) = &scene.estimators {
        let merged = e
            .per_instance()
            .iter()
            .enumerate()
            .find(|(i, est)| est.is_some() && scene.accel.is_merged(*i));
        assert!(
            merged.is_none(),
            "instance {:?} has an estimator but was merged: build the scene with RenderScene::for_estimators",
            merged.map(|m| m.0)
        );
    }
    let (w, h) = (scene.camera.width, scene.camera.height);
    assert_eq!(out.len(), w as usize * h as usize, "output size");
    let samples = samples.start.min(opts.spp)..samples.end.min(opts.spp);
    let total = w as u64 * h as u64 * samples.len() as u64;
    let bar = if opts.progress {
        ProgressBar::new(total)
    } else {
        ProgressBar::hidden()
    };
    bar.set_draw_target(if opts.progress {
        ProgressDrawTarget::stderr_with_hz(4)
    } else {
        ProgressDrawTarget::hidden()
    });
    bar.set_style(nppp_files::progress_style(
        "{spinner} [{elapsed_precise}] {wide_bar} {percent}% {rate} ETA {eta}",
        "samples",
    ));
    bar.enable_steady_tick(Duration::from_millis(250));
    let settings = IntegratorSettings {
        max_bounces: opts.max_bounces,
        seed: opts.seed,
    };
    let start = Instant::now();
    let band_len = (w * TILE) as usize;
    let (dropped, (est, work)) = out
        .par_chunks_mut(band_len)
        .enumerate()
        .map(|(band, band_pixels)| {
            let y0 = band as u32 * TILE;
            let th = TILE.min(h - y0);
            let tiles: Vec<(u32, Vec<PixelSum>, EstimatorStats, WorkCounts)> = (0..w
                .div_ceil(TILE))
                .into_par_iter()
                .map_init(Wavefront::default, |wf, tx| {
                    let x0 = tx * TILE;
                    let tw = TILE.min(w - x0);
                    let film = render_tile(
                        scene,
                        opts,
                        &settings,
                        samples.clone(),
                        wf,
                        (x0, y0),
                        (tw, th),
                        &bar,
                    );
                    (x0, film, wf.estimator_stats, wf.work)
                })
                .collect();
            let mut dropped = 0u64;
            let mut est = EstimatorStats::default();
            let mut work = WorkCounts::default();
            for (x0, film, st, wk) in tiles {
                est.merge(&st);
                work.merge(&wk);
                let tw = TILE.min(w - x0);
                for (i, p) in film.iter().enumerate() {
                    let (x, y) = (x0 + i as u32 % tw, i as u32 / tw);
                    let i = (y * w + x) as usize;
                    band_pixels[i] = finish(band * band_len + i, p);
                    dropped += p.dropped as u64;
                }
            }
            (dropped, (est, work))
        })
        .reduce(
            || (0, Default::default()),
            |(da, (mut ea, mut wa)), (db, (eb, wb))| {
                ea.merge(&eb);
                wa.merge(&wb);
                (da + db, (ea, wa))
            },
        );
    bar.finish_and_clear();
    RenderStats {
        seconds: start.elapsed().as_secs_f64(),
        samples: total,
        dropped_samples: dropped,
        estimators: est,
        work,
    }
}

/// Samples `samples` of one tile, in wavefront batches of about
/// `BATCH_PATHS` paths. Batches start at multiples of their sample count, so
/// a sample range that starts there (every shard of a render that is not cut
/// inside a batch) batches its paths exactly as the whole render does.
#[allow(clippy::too_many_arguments)]
fn render_tile(
    scene: &RenderScene,
    opts: &RenderOptions,
    settings: &IntegratorSettings,
    samples: Range<u32>,
    wf: &mut Wavefront,
    (x0, y0): (u32, u32),
    (tw, th): (u32, u32),
    bar: &ProgressBar,
) -> Vec<PixelSum> {
    let w = scene.camera.width;
    let mut film = vec![PixelSum::default(); (tw * th) as usize];
    wf.estimator_stats = Default::default();
    wf.work = WorkCounts::default();
    let px = (tw * th) as usize;
    let spp_per_batch = (BATCH_PATHS / px).max(1) as u32;
    let mut s0 = samples.start;
    while s0 < samples.end {
        // The batch grid's next line, in u64: near u32::MAX it would wrap
        // to 0 and start the range over.
        let next = (u64::from(s0 / spp_per_batch) + 1) * u64::from(spp_per_batch);
        let s1 = next.min(u64::from(samples.end)) as u32;
        wf.paths.clear();
        for y in 0..th {
            for x in 0..tw {
                let (gx, gy) = (x0 + x, y0 + y);
                let pixel = (gy as u64) * w as u64 + gx as u64;
                for s in s0..s1 {
                    let mut rng = SampleRng::new(opts.seed, pixel, s as u64);
                    let pos = jitter(&mut rng, gx, gy);
                    let dir = scene.camera.ray_dir(pos);
                    wf.paths
                        .push(PathState::camera(y * tw + x, rng, scene.camera.origin, dir));
                }
            }
        }
        wf.run(scene, settings, &mut film);
        bar.inc(px as u64 * (s1 - s0) as u64);
        s0 = s1;
    }
    film
}
