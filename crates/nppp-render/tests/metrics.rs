//! Error metrics with known values.

use nppp_render::Image;
use nppp_render::metrics::{self, MetricsError, REL_EPS};

fn constant(w: u32, h: u32, v: [f32; 3]) -> Image {
    Image {
        width: w,
        height: h,
        pixels: vec![v; (w * h) as usize],
    }
}

/// A smooth, non-constant image.
fn ramp(w: u32, h: u32) -> Image {
    let mut img = Image::new(w, h);
    for (i, p) in img.pixels.iter_mut().enumerate() {
        let t = i as f32 / (w * h) as f32;
        *p = [t, 0.5 * t + 0.1, 2.0 - t];
    }
    img
}

/// Relative agreement up to f32 rounding of the pixel values (0.6, 0.1, ...
/// are not exact in f32).
fn close(a: f64, b: f64) -> bool {
    (a - b).abs() <= 1e-6 * a.abs().max(b.abs()).max(1e-30)
}

#[test]
fn image_against_itself_is_zero() {
    let r = ramp(40, 30);
    let e = metrics::compare(&r, &r).unwrap();
    assert_eq!(e.rel_mse, 0.0);
    assert_eq!(e.rel_mse_trimmed, 0.0);
    assert_eq!(e.mape, 0.0);
    assert_eq!(e.rmse, 0.0);
}

#[test]
fn constant_offset_has_closed_form_values() {
    let (r, d) = (0.5f32, 0.25f32);
    let reference = constant(32, 32, [r; 3]);
    let img = constant(32, 32, [r + d; 3]);
    let (r, d) = (r as f64, d as f64);
    let e = metrics::compare(&img, &reference).unwrap();
    assert!(close(e.rel_mse, d * d / (r * r + REL_EPS)), "{e:?}");
    // Every pixel has the same error, so trimming changes nothing.
    assert!(close(e.rel_mse_trimmed, e.rel_mse), "{e:?}");
    assert!(close(e.mape, d / (r + REL_EPS)), "{e:?}");
    assert!(close(e.rmse, d), "{e:?}");
}

#[test]
fn per_channel_values_are_averaged() {
    let reference = constant(4, 4, [1.0, 0.0, 2.0]);
    let img = constant(4, 4, [1.5, 0.1, 2.0]);
    let want = (0.25 / (1.0 + REL_EPS) + 0.01 / REL_EPS + 0.0) / 3.0;
    assert!(close(metrics::rel_mse(&img, &reference).unwrap(), want));
    let want_mape = (0.5 / (1.0 + REL_EPS) + 0.1 / REL_EPS) / 3.0;
    assert!(close(metrics::mape(&img, &reference).unwrap(), want_mape));
}

#[test]
fn trimmed_variant_drops_a_single_firefly() {
    // 1000 pixels: 0.1 % is exactly one pixel.
    let reference = constant(50, 20, [0.5; 3]);
    let mut img = reference.clone();
    // A uniform small error everywhere, and one firefly.
    for p in &mut img.pixels {
        *p = [0.6; 3];
    }
    img.pixels[123] = [500.0; 3];
    let base = 0.1f64 * 0.1 / (0.25 + REL_EPS);
    let plain = metrics::rel_mse(&img, &reference).unwrap();
    let trimmed = metrics::rel_mse_trimmed(&img, &reference).unwrap();
    assert!(
        plain > 100.0 * base,
        "the firefly dominates the plain relMSE: {plain}"
    );
    assert!(close(trimmed, base), "trimmed {trimmed} vs {base}");
    assert_eq!(metrics::trimmed_pixels(1000), 1);
    assert_eq!(metrics::trimmed_pixels(999), 0);
}

#[test]
fn trimming_drops_by_error_not_by_brightness() {
    // A bright but exact pixel is kept; the worst-error pixel goes.
    let mut reference = constant(50, 20, [0.5; 3]);
    reference.pixels[7] = [100.0; 3];
    let mut img = reference.clone();
    img.pixels[900] = [0.7; 3];
    img.pixels[901] = [0.9; 3];
    let trimmed = metrics::rel_mse_trimmed(&img, &reference).unwrap();
    let want = 0.2f64.powi(2) / (0.25 + REL_EPS) / 999.0;
    assert!(close(trimmed, want), "{trimmed} vs {want}");
}

#[test]
fn mismatched_sizes_and_non_finite_values_are_errors() {
    let a = constant(4, 4, [1.0; 3]);
    let b = constant(4, 5, [1.0; 3]);
    assert_eq!(
        metrics::compare(&a, &b),
        Err(MetricsError::SizeMismatch {
            width: 4,
            height: 4,
            ref_width: 4,
            ref_height: 5
        })
    );
    let mut c = a.clone();
    c.pixels[6][1] = f32::NAN;
    assert_eq!(
        metrics::rel_mse(&c, &a),
        Err(MetricsError::NonFinite {
            which: "image",
            x: 2,
            y: 1
        })
    );
    assert_eq!(
        metrics::rmse(&a, &c),
        Err(MetricsError::NonFinite {
            which: "reference",
            x: 2,
            y: 1
        })
    );
    let e = constant(0, 0, [0.0; 3]);
    assert_eq!(metrics::mape(&e, &e), Err(MetricsError::Empty));
    let mut short = a.clone();
    short.pixels.pop();
    assert!(matches!(
        metrics::rel_mse(&short, &a),
        Err(MetricsError::BadBuffer { .. })
    ));
    // The message names both sizes.
    let msg = metrics::compare(&a, &b).unwrap_err().to_string();
    assert!(msg.contains("4x4") && msg.contains("4x5"), "{msg}");
}
