//! Writing images: linear float32 RGB OpenEXR (the contract's output) and an
//! sRGB PNG preview. Both go through a temporary file and a rename so an
//! interrupted run never leaves a half-written image in place of a good one.

use std::io::Write;
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

fn temp_path(path: &Path) -> PathBuf {
    let mut name = path
        .file_name()
        .map(|n| n.to_os_string())
        .unwrap_or_default();
    name.push(format!(".{}.tmp", std::process::id()));
    path.with_file_name(name)
}

/// Checks, before minutes of rendering, that an image can be written to
/// `path`: it is not a folder, and the nearest existing ancestor folder
/// accepts a new file (tried with the temporary file `write_atomically`
/// would use, removed at once). Creates nothing that stays behind.
pub fn check_writable(path: &Path) -> Result<(), ImageError> {
    let err = |msg: String| ImageError::Write {
        path: path.into(),
        msg,
    };
    if path.file_name().is_none() || path.as_os_str().to_string_lossy().ends_with('/') {
        return Err(err("names a folder, not a file".into()));
    }
    if path.is_dir() {
        return Err(err("is a folder".into()));
    }
    let parent = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let mut dir = parent.as_path();
    while !dir.exists() {
        match dir.parent() {
            Some(d) if !d.as_os_str().is_empty() => dir = d,
            _ => {
                dir = Path::new(".");
                break;
            }
        }
    }
    if !dir.is_dir() {
        return Err(err(format!(
            "{} is not a folder, so the file cannot be created",
            dir.display()
        )));
    }
    let probe = if dir == parent.as_path() {
        temp_path(path)
    } else {
        dir.join(format!(".nppp-write-check.{}.tmp", std::process::id()))
    };
    match std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(&probe)
    {
        Ok(_) => {
            let _ = std::fs::remove_file(&probe);
            Ok(())
        }
        Err(e) => Err(err(format!("cannot be written: {e}"))),
    }
}

/// Writes `bytes_fn` to a temp file next to `path`, then renames it into place.
pub fn write_atomically(
    path: &Path,
    write: impl FnOnce(&Path) -> Result<(), String>,
) -> Result<(), ImageError> {
    if let Some(dir) = path.parent()
        && !dir.as_os_str().is_empty()
    {
        std::fs::create_dir_all(dir).map_err(|e| ImageError::Write {
            path: path.into(),
            msg: e.to_string(),
        })?;
    }
    let tmp = temp_path(path);
    let res = write(&tmp).and_then(|_| std::fs::rename(&tmp, path).map_err(|e| e.to_string()));
    if let Err(msg) = res {
        let _ = std::fs::remove_file(&tmp);
        return Err(ImageError::Write {
            path: path.into(),
            msg,
        });
    }
    Ok(())
}

pub fn write_exr(img: &Image, path: &Path) -> Result<(), ImageError> {
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
    write_atomically(path, |tmp| {
        exr::prelude::Image::from_encoded_channels(
            (img.width as usize, img.height as usize),
            encoding,
            channels,
        )
        .write()
        .to_file(tmp)
        .map_err(|e| e.to_string())
    })
}

pub fn read_exr(path: &Path) -> Result<Image, ImageError> {
    let err = |e: exr::error::Error| ImageError::Read {
        path: path.into(),
        msg: e.to_string(),
    };
    let img = exr::prelude::read_first_rgba_layer_from_file(
        path,
        |res: exr::math::Vec2<usize>, _| Image::new(res.width() as u32, res.height() as u32),
        |img: &mut Image, pos: exr::math::Vec2<usize>, (r, g, b, _a): (f32, f32, f32, f32)| {
            let i = pos.y() * img.width as usize + pos.x();
            img.pixels[i] = [r, g, b];
        },
    )
    .map_err(err)?;
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

pub fn write_png(img: &Image, path: &Path) -> Result<(), ImageError> {
    write_atomically(path, |tmp| {
        let f = std::fs::File::create(tmp).map_err(|e| e.to_string())?;
        let mut enc = png::Encoder::new(std::io::BufWriter::new(f), img.width, img.height);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let mut w = enc.write_header().map_err(|e| e.to_string())?;
        let data: Vec<u8> = img.pixels.iter().flat_map(|p| p.map(srgb_encode)).collect();
        w.write_image_data(&data).map_err(|e| e.to_string())?;
        w.finish().map_err(|e| e.to_string())?;
        Ok(())
    })
}

/// Writes a small text file atomically (reports, CSV).
pub fn write_text(path: &Path, text: &str) -> Result<(), ImageError> {
    write_atomically(path, |tmp| {
        let mut f = std::fs::File::create(tmp).map_err(|e| e.to_string())?;
        f.write_all(text.as_bytes()).map_err(|e| e.to_string())
    })
}
