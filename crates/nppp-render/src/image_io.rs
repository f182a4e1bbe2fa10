//! Writing images: linear float32 RGB OpenEXR (the contract's output) and an
//! sRGB PNG preview. Both go through a temporary file and a rename so an
//! interrupted run never leaves a half-written image in place of a good one.

use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    #[error("{path}: {msg}")]
    Write { path: PathBuf, msg: String },
    #[error("{path}: {msg}")]
    Read { path: PathBuf, msg: String },
}

/// A linear RGB image, row 0 at the top.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    pub width: u32,
    pub height: u32,
    pub pixels: Vec<[f32; 3]>,
}

impl Image {
    pub fn new(width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            pixels: vec![[0.0; 3]; (width as usize) * (height as usize)],
        }
    }

    pub fn get(&self, x: u32, y: u32) -> [f32; 3] {
        self.pixels[(y * self.width + x) as usize]
    }

    pub fn mean(&self) -> [f64; 3] {
        let mut s = [0.0f64; 3];
        for p in &self.pixels {
            for c in 0..3 {
                s[c] += p[c] as f64;
            }
        }
        let n = self.pixels.len().max(1) as f64;
        [s[0] / n, s[1] / n, s[2] / n]
    }
}

/// Checks, before minutes of rendering, that an image can be written to
/// `path` (see [`nppp_files::check_writable`]). Creates nothing that stays.
pub fn check_writable(path: &Path) -> Result<(), ImageError> {
    nppp_files::check_writable(path).map_err(|msg| ImageError::Write {
        path: path.into(),
        msg,
    })
}

/// Writes through `write` to a temporary file next to `path`, then renames
/// it into place ([`nppp_files::write_atomic_via_path`]).
pub fn write_atomically(
    path: &Path,
    write: impl FnOnce(&Path) -> Result<(), String>,
) -> Result<(), ImageError> {
    nppp_files::create_parent(path)
        .and_then(|_| nppp_files::write_atomic_via_path(path, write))
        .map_err(|e| ImageError::Write {
            path: path.into(),
            msg: e.to_string(),
        })
}

pub fn write_exr(img: &Image, path: &Path) -> Result<(), ImageError> {
    write_exr_and_preview(img, path, None)
}

/// Writes the EXR and, if asked, its PNG preview as a pair: the PNG is
/// encoded first and put in place before the EXR is, and if it cannot be
/// written the EXR is left as it was (a failed run must not leave a new
/// EXR beside an old preview).
pub fn write_exr_and_preview(
    img: &Image,
    path: &Path,
    preview: Option<(&Path, &Preview)>,
) -> Result<(), ImageError> {
    use exr::prelude::{Encoding, LineOrder, SpecificChannels, Vec2, WritableImage};
    // exr's default encoding leaves the line order unspecified, and its
    // parallel compressor then writes blocks as they finish: the same pixels
    // gave different bytes from run to run. Increasing order makes the file
    // itself deterministic (RLE tiles as before).
    let encoding = Encoding {
        line_order: LineOrder::Increasing,
        ..Encoding::FAST_LOSSLESS
    };
    let channels = SpecificChannels::rgb(|Vec2(x, y): Vec2<usize>| {
        let p = img.pixels[y * img.width as usize + x];
        (p[0], p[1], p[2])
    });
    let png = match preview {
        Some((png_path, p)) => Some((
            png_path,
            png_bytes(img, p).map_err(|msg| ImageError::Write {
                path: png_path.into(),
                msg,
            })?,
        )),
        None => None,
    };
    if let Some((png_path, _)) = &png {
        nppp_files::create_parent(png_path).map_err(|e| ImageError::Write {
            path: (*png_path).into(),
            msg: e.to_string(),
        })?;
    }
    let mut png_error = None;
    let written = write_atomically(path, |tmp| {
        exr::prelude::Image::from_encoded_channels(
            (img.width as usize, img.height as usize),
            encoding,
            channels,
        )
        .write()
        .to_file(tmp)
        .map_err(|e| e.to_string())?;
        if let Some((png_path, bytes)) = &png
            && let Err(e) = nppp_files::write_atomic(png_path, bytes)
        {
            let msg = format!("{e} (the EXR {} was left as it was)", path.display());
            png_error = Some(ImageError::Write {
                path: (*png_path).into(),
                msg: msg.clone(),
            });
            return Err(msg);
        }
        Ok(())
    });
    match png_error {
        Some(e) => Err(e),
        None => written,
    }
}

/// The PNG preview's bytes.
fn png_bytes(img: &Image, preview: &Preview) -> Result<Vec<u8>, String> {
    let mut out = Vec::new();
    let mut enc = png::Encoder::new(&mut out, img.width, img.height);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    let mut w = enc.write_header().map_err(|e| e.to_string())?;
    let data: Vec<u8> = img
        .pixels
        .iter()
        .flat_map(|p| p.map(|x| srgb_encode(preview.map(x))))
        .collect();
    w.write_image_data(&data).map_err(|e| e.to_string())?;
    w.finish().map_err(|e| e.to_string())?;
    Ok(out)
}

pub fn read_exr(path: &Path) -> Result<Image, ImageError> {
    let err = |e: &dyn std::fmt::Display| ImageError::Read {
        path: path.into(),
        msg: e.to_string(),
    };
    // The decoder opens the file itself: a pipe would block it, a device
    // feed it forever.
    nppp_files::check_regular(path).map_err(|e| err(&e))?;
    // The decoder allocates the image its header declares before reading a
    // pixel: a 441-byte file claiming 1e9 x 8 pixels aborted the process.
    // No image nppp renders or compares is larger than a scene's largest.
    let meta = exr::meta::MetaData::read_from_file(path, false).map_err(|e| err(&e))?;
    let max = nppp_scene::MAX_IMAGE_SIDE as usize;
    if let Some(h) = meta
        .headers
        .iter()
        .find(|h| h.layer_size.width() > max || h.layer_size.height() > max)
    {
        return Err(err(&format!(
            "its header declares a {} x {} pixel layer, larger than any image nppp renders ({max} x {max}); \
             the file is damaged or not an image of this scene",
            h.layer_size.width(),
            h.layer_size.height()
        )));
    }
    let img = exr::prelude::read_first_rgba_layer_from_file(
        path,
        |res: exr::math::Vec2<usize>, _| Image::new(res.width() as u32, res.height() as u32),
        |img: &mut Image, pos: exr::math::Vec2<usize>, (r, g, b, _a): (f32, f32, f32, f32)| {
            let i = pos.y() * img.width as usize + pos.x();
            img.pixels[i] = [r, g, b];
        },
    )
    .map_err(|e| err(&e))?;
    Ok(img.layer_data.channel_data.pixels)
}

/// Linear radiance to an 8-bit sRGB code, clamped to [0, 1] (non-finite
/// values to 0): the PNG previews' encoding, also what FLIP compares.
pub fn srgb_encode(x: f32) -> u8 {
    let x = if x.is_finite() {
        x.clamp(0.0, 1.0)
    } else {
        0.0
    };
    let y = if x <= 0.003_130_8 {
        12.92 * x
    } else {
        1.055 * x.powf(1.0 / 2.4) - 0.055
    };
    (y * 255.0 + 0.5) as u8
}

/// How a PNG preview maps linear radiance to display values. The EXR is
/// never touched by it: it stays linear.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Preview {
    /// Exposure in stops: radiance is multiplied by 2^EV first.
    pub exposure_ev: f32,
    pub tonemap: Tonemap,
}

impl Default for Preview {
    fn default() -> Self {
        Self {
            exposure_ev: 0.0,
            tonemap: Tonemap::Clamp,
        }
    }
}

/// The curve from exposed radiance to [0, 1] before sRGB encoding.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Tonemap {
    /// Values above 1 clip to white (what the EXR's values are, exactly).
    #[default]
    Clamp,
    /// Narkowicz' fit of the ACES filmic curve: highlights roll off instead
    /// of clipping, shadows gain a little contrast.
    Filmic,
}

impl Preview {
    /// Display value in [0, 1] of a linear radiance channel.
    pub fn map(&self, x: f32) -> f32 {
        let x = if x.is_finite() { x.max(0.0) } else { 0.0 } * self.exposure_ev.exp2();
        match self.tonemap {
            Tonemap::Clamp => x.min(1.0),
            Tonemap::Filmic => {
                let (a, b, c, d, e) = (2.51, 0.03, 2.43, 0.59, 0.14);
                ((x * (a * x + b)) / (x * (c * x + d) + e)).clamp(0.0, 1.0)
            }
        }
    }
}

/// Writes the sRGB PNG preview (clamped, exposure 0).
pub fn write_png(img: &Image, path: &Path) -> Result<(), ImageError> {
    write_png_with(img, path, &Preview::default())
}

/// Writes an sRGB PNG preview with an exposure and a tone curve.
pub fn write_png_with(img: &Image, path: &Path, preview: &Preview) -> Result<(), ImageError> {
    let bytes = png_bytes(img, preview).map_err(|msg| ImageError::Write {
        path: path.into(),
        msg,
    })?;
    write_atomically(path, |tmp| {
        std::fs::write(tmp, &bytes).map_err(|e| e.to_string())
    })
}

/// Writes a small text file atomically (reports, CSV).
pub fn write_text(path: &Path, text: &str) -> Result<(), ImageError> {
    nppp_files::create_parent(path)
        .and_then(|_| nppp_files::write_atomic(path, text.as_bytes()))
        .map_err(|e| ImageError::Write {
            path: path.into(),
            msg: e.to_string(),
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An uncompressed float RGB scanline EXR header declaring `w` x `h`
    /// pixels, its offset table, and no pixel data: what the decoder reads
    /// before it allocates the image.
    fn exr_header_only(w: i32, h: i32) -> Vec<u8> {
        fn attr(out: &mut Vec<u8>, name: &str, ty: &str, v: &[u8]) {
            for s in [name, ty] {
                out.extend_from_slice(s.as_bytes());
                out.push(0);
            }
            out.extend_from_slice(&(v.len() as i32).to_le_bytes());
            out.extend_from_slice(v);
        }
        let mut channels = Vec::new();
        for c in ["B", "G", "R"] {
            channels.extend_from_slice(c.as_bytes());
            channels.push(0);
            for v in [2i32, 0, 1, 1] {
                channels.extend_from_slice(&v.to_le_bytes());
            }
        }
        channels.push(0);
        let window: Vec<u8> = [0, 0, w - 1, h - 1]
            .iter()
            .flat_map(|v: &i32| v.to_le_bytes())
            .collect();
        let mut out = vec![0x76, 0x2f, 0x31, 0x01, 2, 0, 0, 0];
        attr(&mut out, "channels", "chlist", &channels);
        attr(&mut out, "compression", "compression", &[0]);
        attr(&mut out, "dataWindow", "box2i", &window);
        attr(&mut out, "displayWindow", "box2i", &window);
        attr(&mut out, "lineOrder", "lineOrder", &[0]);
        attr(&mut out, "pixelAspectRatio", "float", &1f32.to_le_bytes());
        attr(&mut out, "screenWindowCenter", "v2f", &[0; 8]);
        attr(&mut out, "screenWindowWidth", "float", &1f32.to_le_bytes());
        out.push(0);
        let table_end = (out.len() + 8 * h as usize) as u64;
        for _ in 0..h {
            out.extend_from_slice(&table_end.to_le_bytes());
        }
        out.extend_from_slice(&[0; 64]);
        out
    }

    /// A damaged or forged reference declaring a huge image is refused from
    /// its header: the decoder would allocate 120 GB for this one and abort
    /// the process before reading a pixel.
    #[test]
    fn an_exr_declaring_a_huge_image_is_refused_before_decoding() {
        let dir = std::env::temp_dir().join(format!("nppp-exr-huge-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("wide.exr");
        std::fs::write(&path, exr_header_only(1_000_000_000, 8)).unwrap();
        let e = read_exr(&path).unwrap_err().to_string();
        assert!(
            e.contains("wide.exr") && e.contains("1000000000 x 8 pixel layer"),
            "{e}"
        );
        // The same header at a size nppp renders gets past the check and
        // fails on its missing pixels instead.
        std::fs::write(&path, exr_header_only(16, 8)).unwrap();
        let e = read_exr(&path).unwrap_err().to_string();
        assert!(!e.contains("pixel layer"), "{e}");
        // And a real image still reads.
        let img = Image {
            width: 3,
            height: 2,
            pixels: vec![[0.5, 1.0, 2.0]; 6],
        };
        write_exr(&img, &path).unwrap();
        assert_eq!(read_exr(&path).unwrap(), img);
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn preview_exposure_and_curves() {
        let clamp = Preview::default();
        for x in [-1.0, 0.0, 0.25, 1.0, 7.0, f32::NAN, f32::INFINITY] {
            let old = if x.is_finite() {
                x.clamp(0.0, 1.0)
            } else {
                0.0
            };
            assert_eq!(clamp.map(x), old, "{x}");
        }
        let up = Preview {
            exposure_ev: 2.0,
            tonemap: Tonemap::Clamp,
        };
        assert_eq!(up.map(0.1), 0.4);
        let filmic = Preview {
            exposure_ev: 0.0,
            tonemap: Tonemap::Filmic,
        };
        let mut prev = -1.0;
        for i in 0..1000 {
            let y = filmic.map(i as f32 * 0.05);
            assert!((0.0..=1.0).contains(&y) && y >= prev, "{i}: {y}");
            prev = y;
        }
        assert!(filmic.map(50.0) > 0.99 && filmic.map(0.0) == 0.0);
    }
}
