//! The time-vs-relMSE plots (log-log, one curve per configuration, SVG and
//! PNG per scene): drawn from a run's measurements (`plot_scene`) or redrawn
//! from an earlier results.csv (`plot_from_csv`, `--plot-csv`) with the same
//! styles. Kept apart because it is the only part that needs plotters and a
//! font, and a missing font must not cost a run its tables.

use super::analysis::cells;
use super::harness::SceneResult;
use super::plan::Kind;
use anyhow::{Context, Result, bail, ensure};
use std::path::Path;

struct Curve {
    label: String,
    color: plotters::style::RGBColor,
    width: u32,
    points: Vec<(f64, f64)>,
}

/// `--plot-csv`: one plot per scene of a results.csv, each configuration's
/// (seconds, relMSE) averaged over seeds at each spp, as `curves` draws them.
pub(super) fn plot_from_csv(csv: &Path, out: &Path) -> Result<()> {
    use std::collections::BTreeMap;
    let text = nppp_files::read_regular_to_string(csv)
        .with_context(|| format!("reading {}", csv.display()))?;
    let mut lines = text.lines();
    let header: Vec<&str> = lines
        .next()
        .with_context(|| format!("{}: empty file", csv.display()))?
        .split(',')
        .collect();
    let col = |name: &str| {
        header
            .iter()
            .position(|h| *h == name)
            .with_context(|| format!("{}: no column {name:?}", csv.display()))
    };
    let (c_scene, c_config, c_kind, c_m, c_p, c_spp, c_w, c_h, c_s, c_e) = (
        col("scene")?,
        col("config")?,
        col("kind")?,
        col("max_bounces")?,
        col("min_bounces")?,
        col("spp")?,
        col("width")?,
        col("height")?,
        col("seconds")?,
        col("rel_mse")?,
    );
    // scene -> (size, config -> (kind, m, p, spp -> (sum s, sum e, n)))
    type Cells = BTreeMap<u32, (f64, f64, u32)>;
    type Configs = BTreeMap<String, (Kind, u32, u32, Cells)>;
    let mut scenes: BTreeMap<String, ((String, String), Configs)> = BTreeMap::new();
    for (i, line) in lines.enumerate() {
        let f: Vec<&str> = line.split(',').collect();
        let bad = || format!("{}:{}: malformed row", csv.display(), i + 2);
        ensure!(f.len() == header.len(), "{}", bad());
        let num = |c: usize| f[c].parse::<f64>().with_context(bad);
        let (secs, err) = (num(c_s)?, num(c_e)?);
        let spp = f[c_spp].parse::<u32>().with_context(bad)?;
        // The plots are named after the scene, in --out: a name that is
        // not a plain file name would write elsewhere (or over a file).
        let name = f[c_scene];
        ensure!(
            !name.is_empty()
                && !name.starts_with('.')
                && !name.contains(['/', '\\', '\0'])
                && name.len() <= 200,
            "{}:{}: scene {:?} is not a plain file name (the plots are written as \
             --out/SCENE.svg and .png): empty, starting with a dot, holding a path \
             separator or over 200 bytes",
            csv.display(),
            i + 2,
            name
        );
        let entry = scenes
            .entry(f[c_scene].to_string())
            .or_insert_with(|| ((f[c_w].to_string(), f[c_h].to_string()), BTreeMap::new()));
        let kind = Kind::from_name(f[c_kind]).with_context(bad)?;
        let cfg = entry.1.entry(f[c_config].to_string()).or_insert_with(|| {
            (
                kind,
                f[c_m].parse().unwrap_or(0),
                f[c_p].parse().unwrap_or(0),
                BTreeMap::new(),
            )
        });
        let cell = cfg.3.entry(spp).or_insert((0.0, 0.0, 0));
        *cell = (cell.0 + secs, cell.1 + err, cell.2 + 1);
    }
    ensure!(!scenes.is_empty(), "{}: no rows", csv.display());
    crate::plot::register_font().map_err(|e| anyhow::anyhow!(e))?;
    nppp_files::create_output_dir(out).with_context(|| format!("creating {}", out.display()))?;
    for (name, ((w, h), configs)) in &scenes {
        let mmax = configs
            .values()
            .filter(|c| c.0 == Kind::Pt)
            .map(|c| c.1)
            .max()
            .unwrap_or(1);
        let curves: Vec<Curve> = configs
            .iter()
            .map(|(label, (kind, m, p, cells))| {
                let (color, width) = curve_style(*kind, *m, *p, mmax);
                let mut points: Vec<(f64, f64)> = cells
                    .values()
                    .map(|&(s, e, n)| (s / n as f64, e / n as f64))
                    .filter(drawable)
                    .collect();
                points.sort_by(|a, b| a.0.total_cmp(&b.0));
                Curve {
                    label: label.clone(),
                    color,
                    width,
                    points,
                }
            })
            .filter(|c| !c.points.is_empty())
            .collect();
        let title = format!("{name}: time vs relMSE ({w}x{h})");
        let (svg, png) = (
            out.join(format!("{name}.svg")),
            out.join(format!("{name}.png")),
        );
        for p in [&svg, &png] {
            nppp_files::ensure_not_input("--out", p, &[("the --plot-csv file", csv)])
                .map_err(anyhow::Error::msg)?;
        }
        // Drawn whole in memory, then put in place: a CSV with nothing to
        // draw left a blank page over the old plot.
        let svg_text = crate::plot::svg_of(PLOT_SIZE, |a| draw(a, &title, &curves))
            .with_context(|| format!("drawing {}", svg.display()))?;
        let png_bytes = crate::plot::png_of(PLOT_SIZE, |a| draw(a, &title, &curves))
            .with_context(|| format!("drawing {}", png.display()))?;
        crate::plot::write_plot(&svg, svg_text.as_bytes())?;
        crate::plot::write_plot(&png, &png_bytes)?;
        nppp_files::note!("{}, {}", svg.display(), png.display());
    }
    Ok(())
}

/// Colour and line width of a configuration's curve: PT M = max in thick
/// black, smaller M in lighter greys, NPPP one colour per P (thicker with
/// NEE through the estimator), the oracle purple.
fn curve_style(kind: Kind, m: u32, p: u32, mmax: u32) -> (plotters::style::RGBColor, u32) {
    use plotters::style::RGBColor;
    const NPPP_COLORS: [RGBColor; 4] = [
        RGBColor(214, 39, 40),
        RGBColor(255, 127, 14),
        RGBColor(31, 119, 180),
        RGBColor(44, 160, 44),
    ];
    match kind {
        Kind::Pt if m == mmax => (RGBColor(0, 0, 0), 3),
        Kind::Pt => {
            // Lighter grey for smaller M.
            let g = (200.0 - 150.0 * (m as f64 - 1.0) / (mmax.max(2) as f64 - 1.0)) as u8;
            (RGBColor(g, g, g), 1)
        }
        Kind::Nppp => (NPPP_COLORS[(p as usize).min(3)], 2),
        Kind::NpppNee => (NPPP_COLORS[(p as usize).min(3)], 4),
        Kind::Oracle => (RGBColor(148, 103, 189), 1),
    }
}

/// A (seconds, relMSE) point both log axes can show: positive, and within
/// [`crate::plot::plottable`] (a time of 1.7e308 in a results file hung
/// plotters on an axis padded to infinity).
fn drawable(&(s, e): &(f64, f64)) -> bool {
    s > 0.0 && e > 0.0 && crate::plot::plottable(s) && crate::plot::plottable(e)
}

fn curves(r: &SceneResult) -> Vec<Curve> {
    let ladder: Vec<u32> = {
        let mut v: Vec<u32> = r.measurements.iter().map(|m| m.spp).collect();
        v.sort_unstable();
        v.dedup();
        v
    };
    let mmax = r
        .configs
        .iter()
        .filter(|c| c.kind == Kind::Pt)
        .map(|c| c.m)
        .max()
        .unwrap_or(1);
    r.configs
        .iter()
        .enumerate()
        .map(|(ci, c)| {
            let (color, width) = curve_style(c.kind, c.m, c.p, mmax);
            let mut points: Vec<(f64, f64)> = cells(r, ci, &ladder)
                .iter()
                .map(|x| (x.seconds, x.rel_mse))
                .filter(drawable)
                .collect();
            points.sort_by(|a, b| a.0.total_cmp(&b.0));
            Curve {
                label: c.label(),
                color,
                width,
                points,
            }
        })
        .filter(|c| !c.points.is_empty())
        .collect()
}

fn draw<DB: plotters::prelude::DrawingBackend>(
    root: plotters::prelude::DrawingArea<DB, plotters::coord::Shift>,
    title: &str,
    curves: &[Curve],
) -> Result<()>
where
    DB::ErrorType: 'static,
{
    use plotters::prelude::*;
    let err = |e: &dyn std::fmt::Display| anyhow::anyhow!("plotting: {e}");
    root.fill(&WHITE).map_err(|e| err(&e))?;
    let (x0, x1, y0, y1) = crate::plot::bounds(curves.iter().flat_map(|c| c.points.iter()));
    if x0 > x1 {
        bail!("nothing to plot");
    }
    let (x0, x1, y0, y1) = (x0 / 1.5, x1 * 1.5, y0 / 1.5, y1 * 1.5);
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 22))
        .margin(12)
        .x_label_area_size(45)
        .y_label_area_size(75)
        .build_cartesian_2d((x0..x1).log_scale(), (y0..y1).log_scale())
        .map_err(|e| err(&e))?;
    chart
        .configure_mesh()
        .x_desc("render time (s)")
        .y_desc("relMSE")
        .x_label_formatter(&|x| format!("{x:.2}"))
        .y_label_formatter(&|y| format!("{y:.0e}"))
        .draw()
        .map_err(|e| err(&e))?;
    for c in curves {
        let style = ShapeStyle {
            color: c.color.to_rgba(),
            filled: true,
            stroke_width: c.width,
        };
        let color = c.color;
        let width = c.width;
        chart
            .draw_series(LineSeries::new(c.points.iter().copied(), style))
            .map_err(|e| err(&e))?
            .label(c.label.clone())
            .legend(move |(x, y)| {
                PathElement::new(
                    vec![(x, y), (x + 20, y)],
                    ShapeStyle {
                        color: color.to_rgba(),
                        filled: true,
                        stroke_width: width.max(2),
                    },
                )
            });
        chart
            .draw_series(c.points.iter().map(|&p| Circle::new(p, 3, style.filled())))
            .map_err(|e| err(&e))?;
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperRight)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()
        .map_err(|e| err(&e))?;
    root.present().map_err(|e| err(&e))?;
    Ok(())
}

/// Writes `<out>/<scene>.svg` and `.png`; returns what was written (or why not).
pub(super) fn plot_scene(r: &SceneResult, out: &Path) -> Result<Vec<String>> {
    let cs = curves(r);
    if cs.is_empty() {
        return Ok(vec![format!("{}: nothing to plot", r.name)]);
    }
    if let Err(e) = crate::plot::register_font() {
        return Ok(vec![format!("{}: plots skipped: {e}", r.name)]);
    }
    let title = format!("{}: time vs relMSE ({}x{})", r.name, r.width, r.height);
    let mut done = Vec::new();
    // In memory first, then put in place (a link at the path is replaced,
    // not followed, as every other output of bench).
    let svg = out.join(format!("{}.svg", r.name));
    let text = crate::plot::svg_of(PLOT_SIZE, |a| draw(a, &title, &cs))
        .with_context(|| format!("drawing {}", svg.display()))?;
    crate::plot::write_plot(&svg, text.as_bytes())?;
    done.push(svg.display().to_string());
    let png = out.join(format!("{}.png", r.name));
    match crate::plot::png_of(PLOT_SIZE, |a| draw(a, &title, &cs))
        .and_then(|bytes| crate::plot::write_plot(&png, &bytes))
    {
        Ok(()) => done.push(png.display().to_string()),
        Err(e) => done.push(format!("{} not written: {e:#}", png.display())),
    }
    Ok(done)
}

/// Pixels of a bench plot.
const PLOT_SIZE: (u32, u32) = (900, 640);

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn points_near_f64_limits_are_not_drawn() {
        assert!(drawable(&(0.5, 1e-3)));
        for p in [
            (1.7e308, 0.1),
            (1e-300, 0.1),
            (0.5, 1e200),
            (f64::INFINITY, 0.1),
            (0.5, f64::NAN),
            (0.0, 0.1),
            (0.5, -1.0),
        ] {
            assert!(!drawable(&p), "{p:?}");
        }
        // A results file with such a time plots (it hung in plotters).
        let dir = std::env::temp_dir().join(format!("nppp-bench-plot-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let csv = dir.join("results.csv");
        std::fs::write(
            &csv,
            "scene,config,kind,max_bounces,min_bounces,spp,width,height,seconds,rel_mse\n\
             s,PT M=1,pt,1,,1,8,8,1.7e308,0.1\n\
             s,PT M=3,pt,3,,1,8,8,1e-300,0.1\n\
             s,PT M=3,pt,3,,2,8,8,1e300,0.1\n\
             s,PT M=2,pt,2,,1,8,8,0.5,0.2\n\
             s,PT M=2,pt,2,,4,8,8,2.0,0.05\n",
        )
        .unwrap();
        if crate::plot::register_font().is_ok() {
            plot_from_csv(&csv, &dir.join("plots")).unwrap();
            assert!(dir.join("plots/s.svg").is_file());
        }
        let _ = std::fs::remove_dir_all(&dir);
    }
}
