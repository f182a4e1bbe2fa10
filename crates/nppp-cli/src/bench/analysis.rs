//! From measurements to the report's numbers: the mean (and spread) over
//! seeds of each (configuration, spp) cell, the FLIP score, log-log
//! interpolation and the speed-up at equal error against the PT baseline.
//! Pure functions (of the measurements, or for FLIP of two images), apart
//! from the harness and the reports, so the arithmetic behind every ratio is
//! in one place and tested.

use super::harness::{Measurement, SceneResult};
use super::plan::Kind;
use nppp_render::Image;
#[cfg(feature = "flip")]
use nppp_render::image_io;

/// The mean over seeds of one (config, spp) cell.
#[derive(Clone, Debug)]
pub(super) struct Cell {
    pub(super) spp: u32,
    pub(super) seconds: f64,
    pub(super) samples_per_second: f64,
    pub(super) rel_mse: f64,
    pub(super) rel_mse_sd: Option<f64>,
    pub(super) rel_mse_trimmed: f64,
    pub(super) mape: f64,
    pub(super) rmse: f64,
    pub(super) flip: Option<f64>,
    pub(super) mean_ratio: f64,
    pub(super) estimator_bytes: usize,
}

#[cfg(feature = "flip")]
pub(super) const FLIP_NOTE: &str = "LDR-FLIP (NVIDIA FLIP via nv-flip, 67 pixels per degree) of the sRGB-encoded, clamped images (exposure 1, as the PNG previews)";
#[cfg(not(feature = "flip"))]
pub(super) const FLIP_NOTE: &str = "not available (nppp-cli built without the `flip` feature)";

#[cfg(feature = "flip")]
pub(super) fn flip_mean(img: &Image, reference: &Image) -> Option<f64> {
    if img.width != reference.width || img.height != reference.height || img.pixels.is_empty() {
        return None;
    }
    fn srgb8(img: &Image) -> nv_flip::FlipImageRgb8 {
        let data: Vec<u8> = img
            .pixels
            .iter()
            .flat_map(|p| p.map(image_io::srgb_encode))
            .collect();
        nv_flip::FlipImageRgb8::with_data(img.width, img.height, &data)
    }
    let map = nv_flip::flip(
        srgb8(reference),
        srgb8(img),
        nv_flip::DEFAULT_PIXELS_PER_DEGREE,
    );
    let v = map.to_vec();
    Some(v.iter().map(|&x| x as f64).sum::<f64>() / v.len().max(1) as f64)
}

#[cfg(not(feature = "flip"))]
pub(super) fn flip_mean(_img: &Image, _reference: &Image) -> Option<f64> {
    None
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len().max(1) as f64
}

pub(super) fn cells(r: &SceneResult, config: usize, ladder: &[u32]) -> Vec<Cell> {
    ladder
        .iter()
        .filter_map(|&spp| {
            let ms: Vec<&Measurement> = r
                .measurements
                .iter()
                .filter(|m| m.config == config && m.spp == spp)
                .collect();
            if ms.is_empty() {
                return None;
            }
            let rel: Vec<f64> = ms.iter().map(|m| m.errors.rel_mse).collect();
            let mu = mean(&rel);
            let sd = (rel.len() > 1).then(|| {
                (rel.iter().map(|x| (x - mu) * (x - mu)).sum::<f64>() / (rel.len() - 1) as f64)
                    .sqrt()
            });
            let seconds = mean(&ms.iter().map(|m| m.seconds).collect::<Vec<_>>());
            let samples = mean(&ms.iter().map(|m| m.samples as f64).collect::<Vec<_>>());
            let flips: Vec<f64> = ms.iter().filter_map(|m| m.flip).collect();
            Some(Cell {
                spp,

                seconds,
                samples_per_second: samples / seconds.max(1e-9),
                rel_mse: mu,
                rel_mse_sd: sd,
                rel_mse_trimmed: mean(
                    &ms.iter()
                        .map(|m| m.errors.rel_mse_trimmed)
                        .collect::<Vec<_>>(),
                ),
                mape: mean(&ms.iter().map(|m| m.errors.mape).collect::<Vec<_>>()),
                rmse: mean(&ms.iter().map(|m| m.errors.rmse).collect::<Vec<_>>()),
                flip: (flips.len() == ms.len()).then(|| mean(&flips)),
                mean_ratio: mean(&ms.iter().map(|m| m.mean_ratio).collect::<Vec<_>>()),
                estimator_bytes: ms[0].estimator_bytes,
            })
        })
        .collect()
}

/// Log-log interpolation of y at x along points sorted by x; None outside.
pub(super) fn interp_loglog(pts: &[(f64, f64)], x: f64) -> Option<f64> {
    let lx = x.ln();
    for w in pts.windows(2) {
        let ((x0, y0), (x1, y1)) = (w[0], w[1]);
        if x0 <= 0.0 || x1 <= 0.0 || y0 <= 0.0 || y1 <= 0.0 {
            continue;
        }
        let (a, b) = (x0.min(x1), x0.max(x1));
        if x >= a && x <= b {
            if (x1 - x0).abs() < 1e-300 {
                return Some(y0);
            }
            let t = (lx - x0.ln()) / (x1.ln() - x0.ln());
            return Some((y0.ln() + t * (y1.ln() - y0.ln())).exp());
        }
    }
    None
}

/// How much faster a configuration reaches a given error than the baseline.
#[derive(Clone, Copy, Debug)]
pub(super) enum Speedup {
    /// Interpolated on the configuration's own curve.
    Exact(f64),
    /// The configuration's cheapest point is already below the error: at least this.
    AtLeast(f64),
    /// The configuration's curve never gets that low on the ladder.
    NotReached,
}

impl Speedup {
    pub(super) fn show(&self) -> String {
        match self {
            Speedup::Exact(x) => format!("{x:.2}x"),
            Speedup::AtLeast(x) => format!(">= {x:.2}x"),
            Speedup::NotReached => "not reached".into(),
        }
    }
}

/// The time `cells` (in ladder order) need to reach `error`, against the
/// baseline's time `t_base` for it.
pub(super) fn speedup_at_error(cells: &[Cell], error: f64, t_base: f64) -> Speedup {
    if cells.is_empty() || error.is_nan() || error <= 0.0 {
        return Speedup::NotReached;
    }
    let first = &cells[0];
    if first.rel_mse <= error {
        return Speedup::AtLeast(t_base / first.seconds.max(1e-9));
    }
    // Error against time, walking up the ladder.
    let pts: Vec<(f64, f64)> = cells.iter().map(|c| (c.rel_mse, c.seconds)).collect();
    for w in pts.windows(2) {
        let ((e0, t0), (e1, t1)) = (w[0], w[1]);
        if e0 >= error && e1 <= error && e0 > 0.0 && e1 > 0.0 && t0 > 0.0 && t1 > 0.0 {
            let t = if (e0 - e1).abs() < 1e-300 {
                t0
            } else {
                (t0.ln() + (error.ln() - e0.ln()) / (e1.ln() - e0.ln()) * (t1.ln() - t0.ln())).exp()
            };
            return Speedup::Exact(t_base / t.max(1e-9));
        }
    }
    Speedup::NotReached
}

pub(super) fn baseline_index(r: &SceneResult, m: u32) -> Option<usize> {
    r.configs
        .iter()
        .position(|c| c.kind == Kind::Pt && c.m == m)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cell(spp: u32, seconds: f64, rel_mse: f64) -> Cell {
        Cell {
            spp,
            seconds,
            samples_per_second: 1.0,
            rel_mse,
            rel_mse_sd: None,
            rel_mse_trimmed: rel_mse,
            mape: 0.0,
            rmse: 0.0,
            flip: None,
            mean_ratio: 1.0,
            estimator_bytes: 0,
        }
    }

    #[test]
    fn interpolation_is_log_log() {
        let pts = [(1.0, 1.0), (100.0, 0.01)];
        let y = interp_loglog(&pts, 10.0).unwrap();
        assert!((y - 0.1).abs() < 1e-12);
        assert!(interp_loglog(&pts, 1000.0).is_none());
    }

    #[test]
    fn speedup_cases() {
        // relMSE ~ 1/t: twice as fast as a baseline that needs 2 s for 0.5.
        let c = [cell(4, 0.25, 4.0), cell(16, 1.0, 1.0), cell(64, 4.0, 0.25)];
        match speedup_at_error(&c, 0.5, 4.0) {
            Speedup::Exact(x) => assert!((x - 2.0).abs() < 1e-9, "{x}"),
            s => panic!("{s:?}"),
        }
        assert!(
            matches!(speedup_at_error(&c, 10.0, 1.0), Speedup::AtLeast(x) if (x - 4.0).abs() < 1e-9)
        );
        assert!(matches!(
            speedup_at_error(&c, 0.01, 1.0),
            Speedup::NotReached
        ));
    }
}
