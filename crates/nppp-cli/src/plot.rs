//! Plots shared by the subcommands: the font plotters draws text with, and
//! the training curves of a model directory's `log.csv` (`nppp plot-log`,
//! and `nppp train` at the end of a run).

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};

/// Registers a system TrueType font for the plots' text (plotters draws text
/// with ab_glyph, which needs the font's bytes). `NPPP_FONT` overrides.
pub fn register_font() -> Result<(), String> {
    static DONE: std::sync::OnceLock<Result<(), String>> = std::sync::OnceLock::new();
    DONE.get_or_init(|| {
        let mut candidates: Vec<PathBuf> = std::env::var_os("NPPP_FONT")
            .map(PathBuf::from)
            .into_iter()
            .collect();
        if let Some(p) = candidates.first() {
            // A named pipe waited for a writer forever, /dev/zero was read
            // until memory ran out.
            if let Err(e) = font_file_problem(p) {
                nppp_files::note!(
                    "warning: NPPP_FONT={}: {e}; using a system font",
                    p.display()
                );
                candidates.clear();
            }
        }
        for p in [
            "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
            "/usr/share/fonts/dejavu/DejaVuSans.ttf",
            "/usr/share/fonts/TTF/DejaVuSans.ttf",
            "/usr/share/fonts/truetype/liberation/LiberationSans-Regular.ttf",
            "/usr/share/fonts/liberation-sans/LiberationSans-Regular.ttf",
            "/System/Library/Fonts/Supplemental/Arial.ttf",
            "C:\\Windows\\Fonts\\arial.ttf",
        ] {
            candidates.push(PathBuf::from(p));
        }
        for p in candidates {
            if font_file_problem(&p).is_err() {
                continue;
            }
            if let Ok(bytes) = nppp_files::read_regular(&p) {
                let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
                if plotters::style::register_font(
                    "sans-serif",
                    plotters::style::FontStyle::Normal,
                    bytes,
                )
                .is_ok()
                {
                    return Ok(());
                }
            }
        }
        Err("no TrueType font found (set NPPP_FONT=/path/to/font.ttf)".into())
    })
    .clone()
}

/// Why `path` cannot be a font file: not a regular file, or larger than
/// any font (fonts are kilobytes to a few megabytes).
fn font_file_problem(path: &Path) -> Result<(), String> {
    const MAX_FONT_BYTES: u64 = 64 << 20;
    nppp_files::check_regular(path).map_err(|e| e.to_string())?;
    let len = std::fs::metadata(path).map_err(|e| e.to_string())?.len();
    if len > MAX_FONT_BYTES {
        return Err(format!(
            "{} is larger than any font file",
            nppp_files::format_bytes(len)
        ));
    }
    Ok(())
}

/// `nppp plot-log`: the training curves of a model directory.
#[derive(clap::Args)]
pub struct PlotLogArgs {
    /// A model directory (its log.csv) or a log.csv file.
    pub log: PathBuf,
    /// The plot to write, *.svg or *.png (default: log.svg and log.png beside
    /// the log).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Replace the default plots beside a log that is not in a model
    /// directory where they exist (files nppp did not name after the log
    /// may be anyone's, so they are kept otherwise). A model directory's
    /// plots, and a plot named with `--out`, are replaced as images are.
    #[arg(long)]
    pub overwrite: bool,
}

/// The columns of a training log, by name; empty cells are `None`.
pub struct TrainingLog {
    pub columns: Vec<String>,
    pub rows: Vec<Vec<Option<f64>>>,
}

impl TrainingLog {
    pub fn read(path: &Path) -> Result<Self> {
        let text = nppp_files::read_regular_to_string(path)
            .with_context(|| format!("reading {}", path.display()))?;
        let mut lines = text.lines();
        let header = lines
            .next()
            .with_context(|| format!("{}: empty file, not a training log", path.display()))?;
        let columns: Vec<String> = header.split(',').map(|s| s.trim().to_string()).collect();
        for need in ["step", "train_loss"] {
            if !columns.iter().any(|c| c == need) {
                bail!(
                    "{}: no column \"{need}\": not a training log of `nppp train`",
                    path.display()
                );
            }
        }
        let mut rows = Vec::new();
        for (i, line) in lines.enumerate() {
            let cells: Vec<&str> = line.split(',').collect();
            if cells.len() != columns.len() {
                bail!(
                    "{}: line {} has {} cells, the header {}",
                    path.display(),
                    i + 2,
                    cells.len(),
                    columns.len()
                );
            }
            let row = cells
                .iter()
                .map(|c| {
                    let c = c.trim();
                    if c.is_empty() {
                        Ok(None)
                    } else {
                        c.parse::<f64>().map(Some).map_err(|_| {
                            anyhow::anyhow!(
                                "{}: line {}: {c:?} is not a number",
                                path.display(),
                                i + 2
                            )
                        })
                    }
                })
                .collect::<Result<Vec<_>>>()?;
            rows.push(row);
        }
        Ok(Self { columns, rows })
    }

    /// (step, value) of every row where `column` has a finite value.
    pub fn series(&self, column: &str, scale: f64) -> Vec<(f64, f64)> {
        let (Some(s), Some(c)) = (self.index("step"), self.index(column)) else {
            return Vec::new();
        };
        self.rows
            .iter()
            .filter_map(|r| Some((r[s]?, r[c]? * scale)))
            .filter(|&(x, y)| plottable(x) && plottable(y))
            .collect()
    }

    fn index(&self, name: &str) -> Option<usize> {
        self.columns.iter().position(|c| c == name)
    }
}

/// Whether a value can be drawn: finite, and within 1e-150..1e150 in
/// magnitude (or 0), so that an axis padded around any two of them stays
/// finite and spans at most 300 decades. An axis that reached infinity made
/// plotters loop forever (a log with a loss of 1.7e308 hung `nppp
/// plot-log`), and so did a log axis over more than 308 decades (losses of
/// 1e-200 and 1e200).
pub(crate) fn plottable(v: f64) -> bool {
    v.is_finite() && (v == 0.0 || (1e-150..=1e150).contains(&v.abs()))
}

/// The smallest and largest x and y of `points`: (x0, x1, y0, y1), with
/// x0 > x1 when there are none.
pub(crate) fn bounds<'a>(points: impl Iterator<Item = &'a (f64, f64)>) -> (f64, f64, f64, f64) {
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for &(x, y) in points {
        x0 = x0.min(x);
        x1 = x1.max(x);
        y0 = y0.min(y);
        y1 = y1.max(y);
    }
    (x0, x1, y0, y1)
}

type Series = (&'static str, Vec<(f64, f64)>, plotters::style::RGBColor);

/// One panel: several series against the step, log-scaled y where all
/// values are positive.
fn panel<DB: plotters::prelude::DrawingBackend>(
    area: &plotters::prelude::DrawingArea<DB, plotters::coord::Shift>,
    title: &str,
    y_desc: &str,
    series: &[Series],
) -> Result<()>
where
    DB::ErrorType: 'static,
{
    use plotters::prelude::*;
    let err = |e: &dyn std::fmt::Display| anyhow::anyhow!("plotting: {e}");
    let (x0, x1, y0, y1) = bounds(series.iter().flat_map(|s| s.1.iter()));
    if x0 > x1 {
        area.titled(&format!("{title}: no rows yet"), ("sans-serif", 18))
            .map_err(|e| err(&e))?;
        return Ok(());
    }
    let x1 = if x1 > x0 { x1 } else { x0 + 1.0 };
    let positive = y0 > 0.0;
    let mut builder = ChartBuilder::on(area);
    builder
        .caption(title, ("sans-serif", 18))
        .margin(8)
        .margin_right(24)
        .x_label_area_size(35)
        .y_label_area_size(65);
    macro_rules! draw_into {
        ($chart:expr) => {{
            let mut chart = $chart;
            chart
                .configure_mesh()
                .x_desc("step")
                .x_label_formatter(&|x| format!("{x:.0}"))
                .y_desc(y_desc)
                .draw()
                .map_err(|e| err(&e))?;
            for (label, pts, color) in series {
                let color = *color;
                chart
                    .draw_series(LineSeries::new(pts.iter().copied(), color.stroke_width(2)))
                    .map_err(|e| err(&e))?
                    .label(*label)
                    .legend(move |(x, y)| {
                        PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(2))
                    });
            }
            chart
                .configure_series_labels()
                .position(SeriesLabelPosition::UpperRight)
                .background_style(WHITE.mix(0.85))
                .border_style(BLACK)
                .draw()
                .map_err(|e| err(&e))?;
        }};
    }
    if positive {
        let (lo, hi) = (y0 / 1.3, (y1 * 1.3).max(y0 * 1.5));
        draw_into!(
            builder
                .build_cartesian_2d(x0..x1, (lo..hi).log_scale())
                .map_err(|e| err(&e))?
        );
    } else {
        let pad = ((y1 - y0).abs() * 0.1).max(1e-6);
        draw_into!(
            builder
                .build_cartesian_2d(x0..x1, (y0 - pad)..(y1 + pad))
                .map_err(|e| err(&e))?
        );
    }
    Ok(())
}

fn draw_log<DB: plotters::prelude::DrawingBackend>(
    root: plotters::prelude::DrawingArea<DB, plotters::coord::Shift>,
    title: &str,
    log: &TrainingLog,
) -> Result<()>
where
    DB::ErrorType: 'static,
{
    use plotters::prelude::*;
    let err = |e: &dyn std::fmt::Display| anyhow::anyhow!("plotting: {e}");
    root.fill(&WHITE).map_err(|e| err(&e))?;
    let root = root
        .titled(title, ("sans-serif", 22))
        .map_err(|e| err(&e))?;
    let areas = root.split_evenly((3, 1));
    let train: Vec<Series> = vec![
        ("total", log.series("train_loss", 1.0), BLACK),
        ("chamfer", log.series("train_chamfer", 1.0), BLUE),
        ("energy", log.series("train_energy", 1.0), RED),
        ("mask BCE", log.series("train_bce", 1.0), GREEN),
    ];
    panel(
        &areas[0],
        "training losses (mean since the previous row)",
        "loss",
        &train,
    )?;
    let held: Vec<Series> = vec![
        ("chamfer", log.series("heldout_chamfer", 1.0), BLUE),
        ("energy", log.series("heldout_energy", 1.0), RED),
        ("mask BCE", log.series("heldout_bce", 1.0), GREEN),
    ];
    panel(&areas[1], "held-out losses", "loss", &held)?;
    let acc: Vec<Series> = vec![
        (
            "throughput RMS error %",
            log.series("throughput_rms_error", 100.0),
            BLUE,
        ),
        (
            "throughput bias %",
            log.series("throughput_bias", 100.0),
            RED,
        ),
        (
            "mask error %",
            log.series("mask_accuracy", 1.0)
                .into_iter()
                .map(|(x, a)| (x, 100.0 * (1.0 - a)))
                .collect(),
            GREEN,
        ),
    ];
    panel(&areas[2], "held-out accuracy", "%", &acc)?;
    root.present().map_err(|e| err(&e))?;
    Ok(())
}

/// Draws the training curves of `log` (a model directory or its log.csv) to
/// `out` (`.svg` or `.png`), or to log.svg and log.png beside the log.
/// Returns the files written. Those default plots replace existing files
/// only in a model directory (its own plots) or with `overwrite`: beside a
/// `results.csv` elsewhere, `results.svg` may be anyone's.
pub fn plot_training_log(log: &Path, out: Option<&Path>, overwrite: bool) -> Result<Vec<PathBuf>> {
    let csv = if log.is_dir() {
        log.join("log.csv")
    } else {
        log.to_path_buf()
    };
    let data = TrainingLog::read(&csv)?;
    register_font().map_err(|e| anyhow::anyhow!("{e}"))?;
    let title = format!("training: {}", csv.display());
    let outs: Vec<PathBuf> = match out {
        Some(o) => vec![o.to_path_buf()],
        None => vec![csv.with_extension("svg"), csv.with_extension("png")],
    };
    // A model directory, not its checkpoint folder (which holds a
    // train_config.json of its own, and only what its state.json lists).
    let in_model_dir = csv.parent().is_some_and(|d| {
        d.join("checkpoint").is_dir()
            || (d.join("train_config.json").is_file() && !d.join("state.json").exists())
    });
    if out.is_none()
        && !overwrite
        && !in_model_dir
        && let Some(o) = outs.iter().find(|o| std::fs::symlink_metadata(o).is_ok())
    {
        bail!(
            "{} exists, and {} is not in a model directory, so the plot beside it may be \
             anyone's: pass --overwrite to replace it, or name the plot with --out",
            o.display(),
            csv.display()
        );
    }
    for o in &outs {
        let ext = o
            .extension()
            .map(|e| e.to_string_lossy().to_ascii_lowercase())
            .unwrap_or_default();
        if nppp_files::same_file(o, &csv) {
            bail!("--out {} is the log itself", o.display());
        }
        if ext != "svg" && ext != "png" {
            bail!("--out {}: name the plot *.svg or *.png", o.display());
        }
        let size = (900u32, 1000u32);
        if ext == "svg" {
            let text = svg_of(size, |area| draw_log(area, &title, &data))?;
            write_plot(o, text.as_bytes())?;
        } else {
            let png = png_of(size, |area| draw_log(area, &title, &data))?;
            write_plot(o, &png)?;
        }
    }
    Ok(outs)
}

/// A plot drawn by `draw` as SVG text, in memory: written only once it is
/// whole ([`write_plot`]). Drawn straight into the file, a plot that
/// failed half-way replaced the old one with a blank page, and a link in
/// its place was followed.
pub fn svg_of(
    size: (u32, u32),
    draw: impl FnOnce(
        plotters::drawing::DrawingArea<plotters::prelude::SVGBackend, plotters::coord::Shift>,
    ) -> Result<()>,
) -> Result<String> {
    use plotters::prelude::*;
    let mut text = String::new();
    draw(SVGBackend::with_string(&mut text, size).into_drawing_area())?;
    Ok(text)
}

/// As [`svg_of`], a PNG file's bytes.
pub fn png_of(
    size: (u32, u32),
    draw: impl FnOnce(
        plotters::drawing::DrawingArea<plotters::prelude::BitMapBackend, plotters::coord::Shift>,
    ) -> Result<()>,
) -> Result<Vec<u8>> {
    use plotters::prelude::*;
    let mut rgb = vec![0u8; (size.0 * size.1 * 3) as usize];
    draw(BitMapBackend::with_buffer(&mut rgb, size).into_drawing_area())?;
    let mut png_bytes = Vec::new();
    let mut enc = png::Encoder::new(&mut png_bytes, size.0, size.1);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    let mut w = enc.write_header().context("encoding the PNG")?;
    w.write_image_data(&rgb).context("encoding the PNG")?;
    w.finish().context("encoding the PNG")?;
    Ok(png_bytes)
}

/// Puts a whole plot in place (a temporary file renamed over the target).
pub fn write_plot(path: &Path, bytes: &[u8]) -> Result<()> {
    nppp_files::create_parent(path)
        .and_then(|_| nppp_files::write_atomic(path, bytes))
        .with_context(|| format!("writing {}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn logs_parse_by_column_name_and_plot() {
        let dir = std::env::temp_dir().join(format!("nppp-plot-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let csv = dir.join("log.csv");
        std::fs::write(
            &csv,
            "epoch,step,train_loss,heldout_chamfer,mask_accuracy\n0.1,100,2.0,,\n0.2,200,1.0,0.5,0.9\n",
        )
        .unwrap();
        let log = TrainingLog::read(&csv).unwrap();
        assert_eq!(
            log.series("train_loss", 1.0),
            vec![(100.0, 2.0), (200.0, 1.0)]
        );
        assert_eq!(log.series("heldout_chamfer", 1.0), vec![(200.0, 0.5)]);
        assert!(log.series("missing", 1.0).is_empty());
        if register_font().is_ok() {
            let out = plot_training_log(&dir, None, false).unwrap();
            for o in out {
                assert!(
                    std::fs::metadata(&o).unwrap().len() > 1000,
                    "{}",
                    o.display()
                );
            }
        }
        // Values near f64's limits are left out: padding the axis around
        // 1.7e308 reached infinity and plotters never returned.
        std::fs::write(
            &csv,
            "epoch,step,train_loss\n0.1,100,1.7e308\n0.2,200,1.0\n0.3,300,1e-320\n0.4,400,inf\n\
             0.5,500,1e-200\n0.6,600,1e200\n",
        )
        .unwrap();
        let log = TrainingLog::read(&csv).unwrap();
        assert_eq!(log.series("train_loss", 1.0), vec![(200.0, 1.0)]);
        if register_font().is_ok() {
            // The plots of the first call are there, and this folder is
            // not a model directory: kept unless told.
            let e = plot_training_log(&dir, None, false)
                .unwrap_err()
                .to_string();
            assert!(
                e.contains("log.svg exists") && e.contains("--overwrite"),
                "{e}"
            );
            assert!(!plot_training_log(&dir, None, true).unwrap().is_empty());
            // A model directory's plots are its own.
            std::fs::write(dir.join("train_config.json"), "{}").unwrap();
            assert!(!plot_training_log(&dir, None, false).unwrap().is_empty());
        }
        std::fs::write(&csv, "a,b\n1,2\n").unwrap();
        let e = TrainingLog::read(&csv).err().unwrap().to_string();
        assert!(e.contains("no column \"step\""), "{e}");
        std::fs::write(&csv, "step,train_loss\n1,x\n").unwrap();
        let e = TrainingLog::read(&csv).err().unwrap().to_string();
        assert!(e.contains("line 2"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
