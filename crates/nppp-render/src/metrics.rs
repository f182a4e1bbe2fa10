//! Image error metrics against a reference, as used by `nppp bench`.
//!
//! All sums are in f64 over every pixel and every RGB channel. With `x` the
//! test value and `r` the reference value of one channel of one pixel:
//!
//! - **relMSE**: mean of `(x - r)^2 / (r^2 + eps)`, with [`REL_EPS`]
//!   `eps = 1e-2` (the customary choice in the rendering literature, e.g.
//!   Rousselle et al., Müller et al.): it keeps black reference pixels from
//!   dividing by zero and down-weights errors in near-black regions.
//! - **relMSE, trimmed**: the same, after dropping the
//!   `floor(n_pixels * TRIM_FRACTION)` pixels ([`TRIM_FRACTION`] = 0.1 %)
//!   with the **largest per-pixel error** (the pixel's relMSE term averaged
//!   over its three channels). Dropping by error, not by reference
//!   luminance, is what removes rare fireflies (the outliers that dominate a
//!   plain relMSE at low sample counts) while keeping bright but converged
//!   regions such as the light source. It is biased low by construction, the
//!   same way for every configuration; read it beside the plain value. An
//!   image with fewer than 1000 pixels drops nothing.
//! - **MAPE**: mean of `|x - r| / (r + eps)`, same `eps`.
//! - **RMSE**: `sqrt(mean((x - r)^2))`, in absolute radiance units.
//!
//! Sizes must match and every value must be finite; anything else is an
//! error rather than a silently meaningless number.

use crate::image_io::Image;

/// The `eps` of relMSE and MAPE.
pub const REL_EPS: f64 = 1e-2;

/// The fraction of pixels (largest per-pixel relMSE first) that the trimmed
/// relMSE drops.
pub const TRIM_FRACTION: f64 = 0.001;

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum MetricsError {
    #[error("image is {width}x{height} but the reference is {ref_width}x{ref_height}")]
    SizeMismatch {
        width: u32,
        height: u32,
        ref_width: u32,
        ref_height: u32,
    },
    #[error("the images have no pixels")]
    Empty,
    #[error("the {which} has a non-finite value at pixel ({x}, {y})")]
    NonFinite { which: &'static str, x: u32, y: u32 },
    #[error("the {which} has {len} pixels, but its size {width}x{height} needs {expected}")]
    BadBuffer {
        which: &'static str,
        len: usize,
        width: u32,
        height: u32,
        expected: usize,
    },
}

/// Every metric of one image against its reference.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Errors {
    pub rel_mse: f64,
    pub rel_mse_trimmed: f64,
    pub mape: f64,
    pub rmse: f64,
}

fn check(img: &Image, reference: &Image) -> Result<(), MetricsError> {
    if img.width != reference.width || img.height != reference.height {
        return Err(MetricsError::SizeMismatch {
            width: img.width,
            height: img.height,
            ref_width: reference.width,
            ref_height: reference.height,
        });
    }
    for (which, im) in [("image", img), ("reference", reference)] {
        let expected = im.width as usize * im.height as usize;
        if im.pixels.len() != expected {
            return Err(MetricsError::BadBuffer {
                which,
                len: im.pixels.len(),
                width: im.width,
                height: im.height,
                expected,
            });
        }
    }
    if img.pixels.is_empty() {
        return Err(MetricsError::Empty);
    }
    for (which, im) in [("image", img), ("reference", reference)] {
        if let Some(i) = im
            .pixels
            .iter()
            .position(|p| p.iter().any(|c| !c.is_finite()))
        {
            let w = im.width.max(1) as usize;
            return Err(MetricsError::NonFinite {
                which,
                x: (i % w) as u32,
                y: (i / w) as u32,
            });
        }
    }
    Ok(())
}

/// Per pixel: the relMSE term averaged over the three channels.
fn rel_sq_per_pixel(img: &Image, reference: &Image) -> Vec<f64> {
    img.pixels
        .iter()
        .zip(&reference.pixels)
        .map(|(x, r)| {
            (0..3)
                .map(|c| {
                    let (x, r) = (x[c] as f64, r[c] as f64);
                    (x - r) * (x - r) / (r * r + REL_EPS)
                })
                .sum::<f64>()
                / 3.0
        })
        .collect()
}

/// Relative mean squared error (see the module docs).
pub fn rel_mse(img: &Image, reference: &Image) -> Result<f64, MetricsError> {
    check(img, reference)?;
    let v = rel_sq_per_pixel(img, reference);
    Ok(v.iter().sum::<f64>() / v.len() as f64)
}

/// Pixels the trimmed relMSE drops from an image of `n` pixels.
pub fn trimmed_pixels(n: usize) -> usize {
    (n as f64 * TRIM_FRACTION).floor() as usize
}

/// relMSE without the 0.1 % of pixels with the largest per-pixel error.
pub fn rel_mse_trimmed(img: &Image, reference: &Image) -> Result<f64, MetricsError> {
    check(img, reference)?;
    let mut v = rel_sq_per_pixel(img, reference);
    let drop = trimmed_pixels(v.len());
    let keep = v.len() - drop;
    if drop > 0 {
        // Partition so the `keep` smallest come first; their order is irrelevant.
        v.select_nth_unstable_by(keep - 1, |a, b| a.total_cmp(b));
    }
    Ok(v[..keep].iter().sum::<f64>() / keep as f64)
}

/// Mean absolute percentage error, `|x - r| / (r + eps)`.
pub fn mape(img: &Image, reference: &Image) -> Result<f64, MetricsError> {
    check(img, reference)?;
    let s: f64 = img
        .pixels
        .iter()
        .zip(&reference.pixels)
        .map(|(x, r)| {
            (0..3)
                .map(|c| ((x[c] as f64) - (r[c] as f64)).abs() / ((r[c] as f64) + REL_EPS))
                .sum::<f64>()
        })
        .sum();
    Ok(s / (3 * img.pixels.len()) as f64)
}

/// Root mean squared error.
pub fn rmse(img: &Image, reference: &Image) -> Result<f64, MetricsError> {
    check(img, reference)?;
    let s: f64 = img
        .pixels
        .iter()
        .zip(&reference.pixels)
        .map(|(x, r)| {
            (0..3)
                .map(|c| {
                    let d = (x[c] as f64) - (r[c] as f64);
                    d * d
                })
                .sum::<f64>()
        })
        .sum();
    Ok((s / (3 * img.pixels.len()) as f64).sqrt())
}

/// Every metric at once.
pub fn compare(img: &Image, reference: &Image) -> Result<Errors, MetricsError> {
    Ok(Errors {
        rel_mse: rel_mse(img, reference)?,
        rel_mse_trimmed: rel_mse_trimmed(img, reference)?,
        mape: mape(img, reference)?,
        rmse: rmse(img, reference)?,
    })
}
