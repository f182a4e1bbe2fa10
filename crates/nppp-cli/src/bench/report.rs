//! The bench's written results: results.md (the header on method and
//! machine, the summary across scenes, then per scene every measurement and
//! the equal-spp, equal-time, equal-error and per-P tables, and where NPPP
//! loses) and results.csv (one row per render, the raw numbers the plots and
//! any later analysis start from). Tables and wording only: the cells,
//! interpolation and speed-ups come from `analysis`, the report takes
//! ratios of them and prints.

use super::analysis::{
    Cell, FLIP_NOTE, Speedup, baseline_index, cells, interp_loglog, speedup_at_error,
};
use super::harness::{Measurement, SceneResult};
use super::machine::{Machine, peak_rss_mib};
use super::plan::{Config, Kind, Plan};
use crate::bench_cmd::BenchArgs;
use std::fmt::Write as _;

fn sci(x: f64) -> String {
    if x == 0.0 {
        "0".into()
    } else {
        format!("{x:.3e}")
    }
}

fn mib(b: usize) -> String {
    if b == 0 {
        "0".into()
    } else {
        format!("{:.2} MiB", b as f64 / (1024.0 * 1024.0))
    }
}

pub(super) fn report_markdown(
    a: &BenchArgs,
    plan: &Plan,
    m: &Machine,
    results: &[SceneResult],
    total: f64,
) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "# nppp bench: time against error\n");
    let _ = writeln!(
        s,
        "- mode: **{}** (`nppp bench{}`), finished {}, total {:.0} s",
        plan.mode,
        if a.quick { " --quick" } else { "" },
        m.date,
        total
    );
    let _ = writeln!(
        s,
        "- machine: {}, {} logical CPUs, {} render threads, {}",
        m.cpu, m.nproc, m.threads, m.os
    );
    let _ = writeln!(
        s,
        "- commit: {}, nppp {}",
        m.commit,
        env!("CARGO_PKG_VERSION")
    );
    let _ = writeln!(
        s,
        "- ladder: {:?} spp, {} seed(s) (1..={}), resolution x{} of each scene's camera, M = {}",
        plan.ladder,
        plan.seeds,
        plan.seeds,
        plan.scale,
        match a.max_bounces {
            Some(m) => m.to_string(),
            None => "each scene's render.max_bounces".to_string(),
        }
    );
    if let Some(rss) = peak_rss_mib() {
        let _ = writeln!(s, "- peak memory of the bench process: {rss:.0} MiB");
    }
    let _ = writeln!(
        s,
        "- time = render time only (scene and BVH build and estimator loading excluded; a render under 0.5 s is repeated and timed by the median of up to 5 runs), mean over seeds; \
         samples/s = camera samples per second. mean / reference = the image's mean over the reference's (bias shows here, not in an error number). relMSE = mean of (x-r)^2/(r^2+0.01) over pixels and channels; \
         trimmed = the same without the 0.1 % of pixels with the largest error; MAPE = mean |x-r|/(r+0.01); \
         RMSE absolute. FLIP: {FLIP_NOTE}. Estimator memory is the baked grids and decoder, shared by all instances."
    );
    let _ = writeln!(
        s,
        "- Ratios are against **PT at the scene's M** (plain path tracing with the same M, the unbiased baseline), measured in this run. \
         PT with a smaller M is cheaper and biased (darker); NPPP is biased by its network. \
         *Speed-up at equal error* = PT's time at a ladder point / the time the configuration needs for PT's error there \
         (log-log interpolation on the configuration's own curve; `>=` when its cheapest point is already better, \
         `not reached` when no point of its ladder gets that low).\n"
    );

    // Summary across scenes.
    let _ = writeln!(
        s,
        "## Summary: speed-up of NPPP at equal error, against PT at the scene's M\n"
    );
    let _ = writeln!(
        s,
        "Per scene and P: the speed-up at PT's error at each ladder point (lowest spp first). Above 1 NPPP is faster at equal error.\n"
    );
    let _ = writeln!(
        s,
        "| scene | config | {} | mean / reference at {} spp |",
        plan.ladder
            .iter()
            .map(|spp| format!("at PT's error with {spp} spp"))
            .collect::<Vec<_>>()
            .join(" | "),
        plan.ladder.last().copied().unwrap_or(0)
    );
    let _ = writeln!(s, "|---|---|{}---:|", "---|".repeat(plan.ladder.len()));
    for r in results {
        let Some(bi) = baseline_index(r, r.max_bounces) else {
            continue;
        };
        let base = cells(r, bi, &plan.ladder);
        let mut any = false;
        for (ci, c) in r.configs.iter().enumerate() {
            if c.kind == Kind::Pt {
                continue;
            }
            any = true;
            let cc = cells(r, ci, &plan.ladder);
            let cols: Vec<String> = base
                .iter()
                .map(|b| speedup_at_error(&cc, b.rel_mse, b.seconds).show())
                .collect();
            let bias = cc
                .last()
                .map(|x| bias_note(x.mean_ratio))
                .unwrap_or_default();
            let _ = writeln!(
                s,
                "| {} | {} | {} | {} |",
                r.name,
                c.label(),
                cols.join(" | "),
                bias
            );
        }
        if !any {
            for (label, why) in &r.skipped {
                let _ = writeln!(
                    s,
                    "| {} | {} | {} | |",
                    r.name,
                    label,
                    vec![why.as_str(); plan.ladder.len()].join(" | ")
                );
            }
        }
    }
    let _ = writeln!(s);

    for r in results {
        scene_markdown(&mut s, plan, r);
    }
    s
}

/// Beyond this relative deviation of the image mean from the reference's, a
/// configuration is called biased in the report.
const BIAS_TOLERANCE: f64 = 0.05;

fn bias_note(mean_ratio: f64) -> String {
    if (mean_ratio - 1.0).abs() > BIAS_TOLERANCE {
        format!("**{mean_ratio:.3}** (biased)")
    } else {
        format!("{mean_ratio:.3}")
    }
}

fn scene_markdown(s: &mut String, plan: &Plan, r: &SceneResult) {
    let _ = writeln!(s, "## {}\n", r.name);
    let est = if r.estimator_files.is_empty() {
        "no estimators".to_string()
    } else {
        format!(
            "{} with an estimator ({})",
            r.estimator_instances,
            r.estimator_files
                .iter()
                .map(|p| p.display().to_string())
                .collect::<Vec<_>>()
                .join(", ")
        )
    };
    let _ = writeln!(
        s,
        "`{}`: {}x{} pixels, {} instances ({est}), {} triangles ({} unique), scene build {:.2} s.\n",
        r.path.display(),
        r.width,
        r.height,
        r.instances,
        r.triangles_instanced,
        r.triangles_unique,
        r.build_seconds
    );
    let _ = writeln!(
        s,
        "Reference: PT M={} at {} spp ({}; {:.1} s to render), `{}/reference.exr`. Its own noise, estimated from its two halves, \
         adds about **{}** to every relMSE below (the floor no configuration can go under).\n",
        r.reference.max_bounces,
        r.reference.spp,
        if r.reference_cached {
            "cached, settings and scene hash match"
        } else {
            "rendered in this run"
        },
        r.reference.seconds,
        r.name,
        sci(r.reference.noise_floor_rel_mse)
    );
    let _ = writeln!(s, "![time vs relMSE]({}.svg)\n", r.name);

    // Every measurement.
    let seeds = plan.seeds > 1;
    let _ = writeln!(
        s,
        "### All measurements (mean over {} seed(s))\n",
        plan.seeds
    );
    let _ = writeln!(
        s,
        "| config | spp | time (s) | samples/s | relMSE{} | relMSE trimmed | MAPE | RMSE | FLIP | mean / reference | estimator memory |",
        if seeds { " (± sd over seeds)" } else { "" }
    );
    let _ = writeln!(s, "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for (ci, c) in r.configs.iter().enumerate() {
        for cell in cells(r, ci, &plan.ladder) {
            let rel = match cell.rel_mse_sd {
                Some(sd) => format!("{} ± {}", sci(cell.rel_mse), sci(sd)),
                None => sci(cell.rel_mse),
            };
            let _ = writeln!(
                s,
                "| {} | {} | {:.3} | {:.3} M | {} | {} | {:.4} | {} | {} | {:.3} | {} |",
                c.label(),
                cell.spp,
                cell.seconds,
                cell.samples_per_second / 1e6,
                rel,
                sci(cell.rel_mse_trimmed),
                cell.mape,
                sci(cell.rmse),
                cell.flip
                    .map(|f| format!("{f:.4}"))
                    .unwrap_or_else(|| "n/a".into()),
                cell.mean_ratio,
                mib(cell.estimator_bytes)
            );
        }
    }
    for (label, why) in &r.skipped {
        let _ = writeln!(s, "| {label} | | {why} | | | | | | | | |");
    }
    let _ = writeln!(s);

    let Some(bi) = baseline_index(r, r.max_bounces) else {
        return;
    };
    let base = cells(r, bi, &plan.ladder);
    let others: Vec<(usize, &Config)> = r
        .configs
        .iter()
        .enumerate()
        .filter(|(i, _)| *i != bi)
        .collect();

    // One row per configuration, one column per PT cell of the ladder.
    let others: Vec<(&Config, Vec<Cell>)> = others
        .iter()
        .map(|(ci, c)| (*c, cells(r, *ci, &plan.ladder)))
        .collect();
    let mut table = |title: String,
                     column: &dyn Fn(&Cell) -> String,
                     entry: &dyn Fn(&[Cell], &Cell) -> String| {
        let _ = writeln!(s, "{title}\n");
        let header: Vec<String> = base.iter().map(column).collect();
        let _ = writeln!(s, "| config | {} |", header.join(" | "));
        let _ = writeln!(s, "|---|{}", "---|".repeat(base.len()));
        for (c, cc) in &others {
            let cols: Vec<String> = base.iter().map(|b| entry(cc, b)).collect();
            let _ = writeln!(s, "| {} | {} |", c.label(), cols.join(" | "));
        }
        let _ = writeln!(s);
    };
    table(
        format!(
            "### Equal spp: time and relMSE as a multiple of PT M={}'s",
            r.max_bounces
        ),
        &|b| format!("{} spp", b.spp),
        &|cc, b| match cc.iter().find(|x| x.spp == b.spp) {
            Some(x) => format!(
                "time x{:.2}, relMSE x{:.2}",
                x.seconds / b.seconds.max(1e-9),
                x.rel_mse / b.rel_mse.max(1e-300)
            ),
            None => "-".into(),
        },
    );
    table(
        format!(
            "### Equal time: relMSE as a multiple of PT M={}'s, at PT's render times (interpolated; `-` outside the configuration's measured times)",
            r.max_bounces
        ),
        &|b| format!("{:.3} s (PT {} spp)", b.seconds, b.spp),
        &|cc, b| {
            let mut pts: Vec<(f64, f64)> = cc.iter().map(|x| (x.seconds, x.rel_mse)).collect();
            pts.sort_by(|p, q| p.0.total_cmp(&q.0));
            match interp_loglog(&pts, b.seconds) {
                Some(e) => format!("x{:.2}", e / b.rel_mse.max(1e-300)),
                None => "-".into(),
            }
        },
    );
    table(
        format!(
            "### Equal error: speed-up against PT M={} (PT's time / the configuration's time for PT's relMSE)",
            r.max_bounces
        ),
        &|b| format!("relMSE {} (PT {} spp)", sci(b.rel_mse), b.spp),
        &|cc, b| speedup_at_error(cc, b.rel_mse, b.seconds).show(),
    );

    // Speed-up as a function of P.
    let nppp: Vec<(usize, &Config)> = r
        .configs
        .iter()
        .enumerate()
        .filter(|(_, c)| c.kind == Kind::Nppp)
        .collect();
    if nppp.is_empty() {
        for (label, why) in &r.skipped {
            let _ = writeln!(s, "{label}: {why}.\n");
        }
        return;
    }
    let top = base.last();
    let _ = writeln!(
        s,
        "### NPPP as a function of P (at the top of the ladder unless said otherwise)\n"
    );
    let _ = writeln!(
        s,
        "| P | samples/s vs PT | relMSE vs PT at equal spp | trimmed relMSE vs PT | speed-up at PT's top-spp error | estimator entries per sample | mask skips per sample |"
    );
    let _ = writeln!(s, "|---:|---:|---:|---:|---:|---:|---:|");
    for (ci, c) in &nppp {
        let cc = cells(r, *ci, &plan.ladder);
        let (Some(b), Some(x)) = (top, cc.last()) else {
            continue;
        };
        let ms: Vec<&Measurement> = r
            .measurements
            .iter()
            .filter(|m| m.config == *ci && m.spp == x.spp)
            .collect();
        let samples: f64 = ms.iter().map(|m| m.samples as f64).sum::<f64>().max(1.0);
        let entries: f64 = ms.iter().map(|m| m.stats.entries as f64).sum();
        let skips: f64 = ms.iter().map(|m| m.stats.mask_skips as f64).sum();
        let _ = writeln!(
            s,
            "| {} | x{:.2} | x{:.2} | x{:.2} | {} | {:.3} | {:.3} |",
            c.p,
            x.samples_per_second / b.samples_per_second.max(1e-9),
            x.rel_mse / b.rel_mse.max(1e-300),
            x.rel_mse_trimmed / b.rel_mse_trimmed.max(1e-300),
            speedup_at_error(&cc, b.rel_mse, b.seconds).show(),
            entries / samples,
            skips / samples
        );
    }
    let _ = writeln!(s);

    // Where NPPP loses, stated by the numbers.
    let _ = writeln!(s, "### Where NPPP loses here\n");
    let mut lines = Vec::new();
    for (ci, c) in &nppp {
        let cc = cells(r, *ci, &plan.ladder);
        let mut slower = Vec::new();
        let mut unreached = Vec::new();
        for b in &base {
            match speedup_at_error(&cc, b.rel_mse, b.seconds) {
                Speedup::Exact(x) if x < 1.0 => slower.push(format!("{} spp ({x:.2}x)", b.spp)),
                Speedup::NotReached => unreached.push(format!("{} spp", b.spp)),
                _ => {}
            }
        }
        if !slower.is_empty() {
            lines.push(format!(
                "- {}: slower than PT at equal error at PT's error for {}.",
                c.label(),
                slower.join(", ")
            ));
        }
        if !unreached.is_empty() {
            lines.push(format!(
                "- {}: does not get down to PT's error for {} at any spp measured (more samples may, unless its bias stops it first); PT wins there at every budget measured.",
                c.label(),
                unreached.join(", ")
            ));
        }
        if let Some(x) = cc.last()
            && (x.mean_ratio - 1.0).abs() > BIAS_TOLERANCE
        {
            lines.push(format!(
                "- {}: biased: its image's mean is {:.3} of the reference's at {} spp. Its error numbers mix that bias with noise; where it \"wins\", it wins only because PT's noise at that budget costs more relMSE than the missing (or extra) light does.",
                c.label(),
                x.mean_ratio,
                x.spp
            ));
        }
        if let (Some(b), Some(x)) = (top, cc.last())
            && x.rel_mse > b.rel_mse
        {
            lines.push(format!(
                "- {}: at {} spp its relMSE is {:.2}x PT's (equal spp).",
                c.label(),
                x.spp,
                x.rel_mse / b.rel_mse.max(1e-300)
            ));
        }
    }
    if lines.is_empty() {
        lines.push("- Nowhere on this ladder: every NPPP configuration reached every PT error level faster.".into());
    }
    for l in lines {
        let _ = writeln!(s, "{l}");
    }
    let _ = writeln!(s);
}

pub(super) fn report_csv(results: &[SceneResult]) -> String {
    let mut s = String::from(
        "scene,config,kind,max_bounces,min_bounces,spp,seed,width,height,seconds,samples,samples_per_second,rel_mse,rel_mse_trimmed,mape,rmse,flip,mean_ratio,estimator_bytes,estimator_entries,mask_skips,ambiguous\n",
    );
    for r in results {
        for m in &r.measurements {
            let c = &r.configs[m.config];
            let _ = writeln!(
                s,
                "{},{},{},{},{},{},{},{},{},{:.6},{},{:.1},{:.6e},{:.6e},{:.6e},{:.6e},{},{:.6},{},{},{},{}",
                r.name,
                c.label(),
                c.kind.name(),
                c.m,
                if c.kind == Kind::Pt {
                    String::new()
                } else {
                    c.p.to_string()
                },
                m.spp,
                m.seed,
                r.width,
                r.height,
                m.seconds,
                m.samples,
                m.samples as f64 / m.seconds.max(1e-9),
                m.errors.rel_mse,
                m.errors.rel_mse_trimmed,
                m.errors.mape,
                m.errors.rmse,
                m.flip.map(|f| format!("{f:.6}")).unwrap_or_default(),
                m.mean_ratio,
                m.estimator_bytes,
                m.stats.entries,
                m.stats.mask_skips,
                m.stats.ambiguous
            );
        }
    }
    s
}
