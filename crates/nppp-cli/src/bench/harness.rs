//! Running the benchmark: `run` (scenes in turn, then the reports and
//! plots), and per scene `bench_scene`: build the scene, get the reference,
//! load the estimators, warm up, then render every configuration at every
//! spp and seed, timed (`robust_seconds`) and compared to the reference.
//! The only file that renders the measured configurations, so every time in
//! the tables comes from one place and one method.

use super::analysis::flip_mean;
use super::machine::Machine;
use super::plan::{
    Config, DEFAULT_SCENES, Kind, NPPP_P, Plan, REFERENCE_FORMAT, REFERENCE_SEEDS, pt_bounce_ladder,
};
use super::plots::{plot_from_csv, plot_scene};
use super::reference::{
    ReferenceMeta, load_or_render_reference, resolve_scene, scene_hash, scene_name, tidy_path,
};
use super::report::{report_csv, report_markdown};
use crate::bench_cmd::BenchArgs;
use anyhow::{Context, Result, bail, ensure};
use nppp_render::estimator::{EntryNee, EstimatorMode, EstimatorStats, Estimators};
use nppp_render::estimator_overlap::{Obstruction, describe_all, release};
use nppp_render::metrics::{self, Errors};
use nppp_render::{Image, RenderOptions, RenderScene, image_io};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// One render, measured.
pub(super) struct Measurement {
    pub(super) config: usize,
    pub(super) spp: u32,
    pub(super) seed: u64,
    pub(super) seconds: f64,
    pub(super) samples: u64,
    pub(super) errors: Errors,
    pub(super) flip: Option<f64>,
    /// Mean of the image over the reference's mean (all channels): the bias
    /// an error number alone does not show.
    pub(super) mean_ratio: f64,
    pub(super) estimator_bytes: usize,
    pub(super) stats: EstimatorStats,
}

pub(super) struct SceneResult {
    pub(super) name: String,
    pub(super) path: PathBuf,
    pub(super) width: u32,
    pub(super) height: u32,
    pub(super) instances: usize,
    pub(super) estimator_instances: usize,
    pub(super) estimator_files: Vec<PathBuf>,
    pub(super) triangles_unique: u64,
    pub(super) triangles_instanced: u64,
    pub(super) build_seconds: f64,
    pub(super) reference: ReferenceMeta,
    pub(super) reference_cached: bool,
    /// M of the reference and the NPPP configurations (PT runs at 1..=M).
    pub(super) max_bounces: u32,
    pub(super) configs: Vec<Config>,
    /// Configurations that could not run, with the reason.
    pub(super) skipped: Vec<(String, String)>,
    pub(super) measurements: Vec<Measurement>,
}

/// `nppp bench`: every scene of the plan, then results.md, results.csv
/// and the plots in `--out` (or, with `--plot-csv`, only the plots).
pub(crate) fn run(a: &BenchArgs) -> Result<()> {
    if let Some(csv) = &a.plot_csv {
        return plot_from_csv(csv, &a.out);
    }
    let plan = Plan::from_args(a)?;
    let names: Vec<String> = a
        .scenes
        .clone()
        .unwrap_or_else(|| DEFAULT_SCENES.iter().map(|s| s.to_string()).collect());
    ensure!(!names.is_empty(), "--scenes is empty");
    let paths: Vec<PathBuf> = names
        .iter()
        .map(|n| resolve_scene(&a.scenes_dir, n))
        .collect::<Result<_>>()?;
    // Each scene's reference, previews and plots go under its file name.
    for (i, p) in paths.iter().enumerate() {
        if let Some(q) = paths[..i].iter().find(|q| scene_name(q) == scene_name(p)) {
            bail!(
                "--scenes: {} and {} have the same file name, so their outputs in --out would \
                 overwrite each other; rename one (or run them separately)",
                q.display(),
                p.display()
            );
        }
    }
    if a.out.exists() && !a.out.is_dir() {
        bail!(
            "--out {}: is a file; bench writes a folder of results",
            a.out.display()
        );
    }
    // Every scene is read and checked (at the bench's resolution) before
    // any is benchmarked: a bad second scene used to end the run after the
    // first's hours of renders. Each is read again when its turn comes, so
    // that only one scene's meshes are in memory at a time.
    let mut inputs = Vec::new();
    for p in &paths {
        let scene =
            load_for_bench(p, &plan).with_context(|| format!("benchmarking {}", p.display()))?;
        inputs.extend(scene.input_files());
    }
    check_outputs_spare_inputs(&a.out, &paths, &inputs)?;
    nppp_files::create_output_dir(&a.out)
        .with_context(|| format!("creating {}", a.out.display()))?;
    let machine = Machine::probe();
    nppp_files::note!(
        "nppp bench ({}): {} scene(s), spp {:?}, reference {} spp, {} seed(s), resolution x{}, {} threads",
        plan.mode,
        paths.len(),
        plan.ladder,
        plan.reference_spp,
        plan.seeds,
        plan.scale,
        rayon::current_num_threads()
    );
    let t0 = Instant::now();
    let mut results = Vec::new();
    let write_reports = |results: &[SceneResult], stem: &str| -> Result<(PathBuf, PathBuf)> {
        let (md_path, csv_path) = (
            a.out.join(format!("{stem}.md")),
            a.out.join(format!("{stem}.csv")),
        );
        let md = report_markdown(a, &plan, &machine, results, t0.elapsed().as_secs_f64());
        image_io::write_text(&md_path, &md)
            .with_context(|| format!("writing {}", md_path.display()))?;
        image_io::write_text(&csv_path, &report_csv(results))
            .with_context(|| format!("writing {}", csv_path.display()))?;
        Ok((md_path, csv_path))
    };
    for path in &paths {
        match bench_scene(a, &plan, path) {
            Ok(r) => results.push(r),
            Err(e) => {
                // What finished is kept, beside (not over) the reports of
                // an earlier complete run in the same --out.
                if !results.is_empty()
                    && let Ok((md, csv)) = write_reports(&results, "results.partial")
                {
                    nppp_files::note!(
                        "bench stopped at {}; the {} scene(s) benchmarked before it are in {} and {}",
                        path.display(),
                        results.len(),
                        md.display(),
                        csv.display()
                    );
                }
                return Err(e.context(format!("benchmarking {}", path.display())));
            }
        }
    }
    let total = t0.elapsed().as_secs_f64();
    let (md_path, csv_path) = write_reports(&results, "results")?;
    let mut plots = Vec::new();
    for r in &results {
        plots.extend(plot_scene(r, &a.out)?);
    }
    nppp_files::note!(
        "bench done in {:.0} s: {} and {}",
        total,
        md_path.display(),
        csv_path.display()
    );
    for p in plots {
        nppp_files::note!("  plot: {p}");
    }
    Ok(())
}

/// Refuses a run whose outputs would replace one of its inputs (a scene, a
/// mesh, an estimator): the reports, each scene's plots beside them and
/// its folder of reference and previews, all named after its file.
fn check_outputs_spare_inputs(
    out: &Path,
    paths: &[PathBuf],
    inputs: &[(String, PathBuf)],
) -> Result<()> {
    let mut outputs: Vec<PathBuf> = ["results", "results.partial"]
        .iter()
        .flat_map(|s| ["md", "csv"].map(|e| out.join(format!("{s}.{e}"))))
        .collect();
    for p in paths {
        let name = scene_name(p);
        outputs.extend(["svg", "png"].map(|e| out.join(format!("{name}.{e}"))));
        let dir = out.join(&name);
        // Each scene's folder must be one that can hold files: a file of
        // that name ended the run at that scene, after the earlier ones'
        // hours of renders. So must be the cached files' names in it.
        let folder_problem = |d: &Path| -> Option<String> {
            match std::fs::metadata(d) {
                Ok(m) if !m.is_dir() => Some(format!("{} is a file, not a folder", d.display())),
                _ => nppp_files::check_writable(&d.join("reference.exr"))
                    .err()
                    .map(|e| format!("{}: {e}", d.join("reference.exr").display())),
            }
        };
        if let Some(problem) = folder_problem(&dir) {
            bail!(
                "--out {}: bench writes {}'s reference and previews into {}, and {problem}",
                out.display(),
                p.display(),
                dir.display()
            );
        }
        for f in ["reference.exr", "reference.png", "reference.json"] {
            let fp = dir.join(f);
            if fp.is_dir() {
                bail!(
                    "--out {}: {} is a folder where bench writes {}'s {f}",
                    out.display(),
                    fp.display(),
                    p.display()
                );
            }
        }
        if let Some((what, input)) = inputs.iter().find(|(_, i)| nppp_files::is_inside(i, &dir)) {
            bail!(
                "--out {}: bench writes {}'s reference and previews into {}, which holds \
                 {what} ({}); choose another --out",
                out.display(),
                p.display(),
                dir.display(),
                input.display()
            );
        }
    }
    // A scene named like a report or a plot (`results.md.json`,
    // `a.svg.json` beside `a.json`) ran every render, then its folder
    // stood where the report was to go: hours of measurements, no report.
    for p in paths {
        let dir = out.join(scene_name(p));
        if outputs.contains(&dir) {
            bail!(
                "--scenes {}: bench writes that scene's files into {}, where it also writes \
                 {}; rename the scene file",
                p.display(),
                dir.display(),
                if dir.extension().is_some_and(|e| e == "svg" || e == "png") {
                    "a scene's plot"
                } else {
                    "its report"
                }
            );
        }
    }
    for o in &outputs {
        if o.is_dir() {
            bail!(
                "--out {}: {} is a folder where bench writes a report or plot",
                out.display(),
                o.display()
            );
        }
        nppp_files::ensure_not_input("--out", o, inputs).map_err(anyhow::Error::msg)?;
    }
    Ok(())
}

/// Renders shorter than this are repeated (same seed, so the same image) and
/// timed by their median, so scheduler noise does not decide a ratio.
const SHORT_RENDER_S: f64 = 0.5;
const MAX_REPEATS: usize = 5;

/// The median time of a short render over up to [`MAX_REPEATS`] runs
/// (including the one already made, which took `first` seconds).
fn robust_seconds(rs: &RenderScene, spp: u32, m: u32, seed: u64, first: f64) -> f64 {
    let mut times = vec![first];
    let mut total = first;
    while times.len() < MAX_REPEATS && total < SHORT_RENDER_S {
        let (_, st) = render_with(rs, spp, m, seed);
        times.push(st.seconds);
        total += st.seconds;
    }
    times.sort_by(f64::total_cmp);
    times[times.len() / 2]
}

fn image_sum(img: &Image) -> f64 {
    img.pixels
        .iter()
        .map(|p| p.iter().map(|&c| c as f64).sum::<f64>())
        .sum()
}

pub(super) fn render_with(
    rs: &RenderScene,
    spp: u32,
    max_bounces: u32,
    seed: u64,
) -> (Image, nppp_render::RenderStats) {
    nppp_render::render(
        rs,
        &RenderOptions {
            spp,
            max_bounces,
            seed,
            progress: false,
        },
    )
}

/// The scene at `path` as the bench renders it: read, checked (its memory
/// too) and resized to the plan's resolution.
fn load_for_bench(path: &Path, plan: &Plan) -> Result<nppp_scene::Scene> {
    let mut scene = nppp_scene::load_scene(path)?;
    scene
        .camera
        .resize(Some(plan.scale), None, None)
        .map_err(anyhow::Error::msg)?;
    // At the resolution the bench renders (the image counts).
    if let Some(problem) = nppp_render::scene_data::render_memory_problem(
        &scene,
        nppp_render::scene_data::RENDER_BYTES_PER_PIXEL,
        EstimatorMode::Neural,
    ) {
        bail!("{}: {problem}", path.display());
    }
    Ok(scene)
}

fn bench_scene(a: &BenchArgs, plan: &Plan, path: &Path) -> Result<SceneResult> {
    let name = scene_name(path);
    let dir = a.out.join(&name);
    let scene = load_for_bench(path, plan)?;
    let hash = scene_hash(path, &scene)?;
    // Only once the scene is known good: a bad one left an empty folder.
    nppp_files::create_output_dir(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let (width, height) = (scene.camera.width, scene.camera.height);
    let m = a.max_bounces.unwrap_or(scene.render.max_bounces);

    let t_build = Instant::now();
    // Plain path tracing gets its fastest layout (estimator instances merged
    // into the world BLAS); estimator runs get theirs.
    let mut rs = RenderScene::new(&scene);
    let build_seconds = t_build.elapsed().as_secs_f64();
    // A second layout only where estimator renders need another one.
    let mut rs_est = RenderScene::estimator_layout(&scene);
    let triangles_unique: u64 = scene.meshes.iter().map(|m| m.triangles.len() as u64).sum();
    let triangles_instanced: u64 = scene
        .instances
        .iter()
        .map(|i| scene.meshes[i.mesh].triangles.len() as u64)
        .sum();
    nppp_files::note!(
        "[{name}] {width}x{height}, {} instances, {triangles_instanced} instanced triangles, scene built in {build_seconds:.2} s",
        scene.instances.len()
    );

    // The reference: cached when its settings match.
    let want = ReferenceMeta {
        format: REFERENCE_FORMAT,
        scene: path.display().to_string(),
        scene_hash: hash,
        width,
        height,
        spp: plan.reference_spp,
        max_bounces: m,
        seeds: REFERENCE_SEEDS,
        renderer: format!("nppp {}", env!("CARGO_PKG_VERSION")),
        seconds: 0.0,
        noise_floor_rel_mse: 0.0,
    };
    let (reference, reference_meta, reference_cached) =
        load_or_render_reference(a, &rs, &dir, &name, &want)?;
    // relMSE against a black image is 0 for every configuration: a perfect
    // score that measures nothing (a --scale that leaves one pixel, or a
    // scene without light).
    let lit = reference.pixels.iter().any(|p| p.iter().any(|&c| c > 0.0));
    ensure!(
        lit,
        "[{name}] the reference ({width}x{height}, {} spp) is black: relMSE would be 0 for every \
         configuration. Check the scene's lights, or give a --scale that leaves more pixels",
        reference_meta.spp
    );

    // Estimators: the scene's own files, checked before any configuration runs.
    let mut estimator_files: Vec<PathBuf> = scene
        .instances
        .iter()
        .filter_map(|i| i.estimator.as_deref().map(tidy_path))
        .collect();
    estimator_files.sort();
    estimator_files.dedup();
    let estimator_instances = scene
        .instances
        .iter()
        .filter(|i| i.estimator.is_some())
        .count();
    let mut configs: Vec<Config> = pt_bounce_ladder(m)
        .into_iter()
        .map(|mm| Config {
            kind: Kind::Pt,
            m: mm,
            p: 0,
        })
        .collect();
    let mut skipped = Vec::new();
    let ps: Vec<u32> = NPPP_P.iter().copied().filter(|&p| p < m).collect();
    let mut neural: Option<Estimators> = None;
    // The instances whose object's hull other geometry reaches into,
    // once found and named (both kinds of estimators bind the same ones).
    let mut obstructed: Option<Vec<Obstruction>> = None;
    if estimator_files.is_empty() {
        skipped.push((
            "NPPP (all P)".to_string(),
            "skipped: no estimator (no instance of the scene names one)".to_string(),
        ));
    } else if let Some(missing) = estimator_files.iter().find(|f| !f.is_file()) {
        skipped.push((
            "NPPP (all P)".to_string(),
            format!(
                "skipped: no estimator ({} does not exist; see BENCHMARKS.md for how to build it)",
                missing.display()
            ),
        ));
    } else {
        if let Some(line) = nppp_render::estimator::unused_on_emitters(&scene) {
            nppp_files::note!("[{name}] warning: {line}");
        }
        match Estimators::load(&scene, EstimatorMode::Neural, 0) {
            Ok(Some(mut e)) => {
                let found = rs_est
                    .as_ref()
                    .unwrap_or(&rs)
                    .release_obstructed(&scene, &mut e);
                for line in describe_all(&found, &scene) {
                    nppp_files::note!("[{name}] warning: {line}");
                }
                obstructed = Some(found);
                if !e.any_in_use() {
                    skipped.push((
                        "NPPP (all P)".into(),
                        "skipped: every estimator instance is obstructed or a lamp (see the warnings)".into(),
                    ));
                } else {
                    configs.extend(ps.iter().map(|&p| Config {
                        kind: Kind::Nppp,
                        m,
                        p,
                    }));
                    // NEE through the estimator where an object takes light samples.
                    if entry_nee_of(&e) != EntryNee::Off {
                        configs.extend(ps.iter().map(|&p| Config {
                            kind: Kind::NpppNee,
                            m,
                            p,
                        }));
                    }
                    neural = Some(e);
                }
            }
            Ok(None) => skipped.push(("NPPP (all P)".into(), "skipped: no estimator".into())),
            Err(e) => {
                nppp_files::note!("[{name}] warning: the estimators do not load: {e}");
                skipped.push((
                    "NPPP (all P)".into(),
                    format!("skipped: the estimator does not load: {e}"),
                ));
            }
        }
    }
    let mut oracle: Option<Estimators> = None;
    if a.oracle && !estimator_files.is_empty() {
        oracle = Estimators::load(&scene, EstimatorMode::Oracle, 0)
            .with_context(|| format!("{}: oracle estimators", path.display()))?;
        if let Some(e) = &mut oracle {
            match &obstructed {
                // Found and named above, where the network's estimators loaded.
                Some(found) => release(e, found),
                None => {
                    let found = rs_est.as_ref().unwrap_or(&rs).release_obstructed(&scene, e);
                    for line in describe_all(&found, &scene) {
                        nppp_files::note!("[{name}] warning: {line}");
                    }
                }
            }
            if !e.any_in_use() {
                skipped.push((
                    "oracle (all P)".into(),
                    "skipped: every estimator instance is obstructed or a lamp (see the warnings)"
                        .into(),
                ));
                oracle = None;
            }
        }
        if oracle.is_some() {
            configs.extend(ps.iter().map(|&p| Config {
                kind: Kind::Oracle,
                m,
                p,
            }));
        }
    }

    // Warm-up (caches, thread pool, first touch of the estimator grids), untimed.
    for c in &configs {
        attach(
            rs_est.as_mut().unwrap_or(&mut rs),
            c,
            &mut neural,
            &mut oracle,
        );
        let _ = render_with(c.scene(&rs, rs_est.as_ref()), 1, c.m, 0);
        detach(
            rs_est.as_mut().unwrap_or(&mut rs),
            c,
            &mut neural,
            &mut oracle,
        );
    }

    let mut measurements = Vec::new();
    let top = *plan.ladder.last().unwrap_or(&1);
    for seed in 1..=plan.seeds as u64 {
        for &spp in &plan.ladder {
            for (ci, c) in configs.iter().enumerate() {
                let estimator_bytes = attach(
                    rs_est.as_mut().unwrap_or(&mut rs),
                    c,
                    &mut neural,
                    &mut oracle,
                );
                let rs_c = c.scene(&rs, rs_est.as_ref());
                let (img, mut stats) = render_with(rs_c, spp, c.m, seed);
                stats.seconds = robust_seconds(rs_c, spp, c.m, seed, stats.seconds);
                detach(
                    rs_est.as_mut().unwrap_or(&mut rs),
                    c,
                    &mut neural,
                    &mut oracle,
                );
                let errors = metrics::compare(&img, &reference)
                    .with_context(|| format!("{name}: comparing {} to the reference", c.label()))?;
                let flip = flip_mean(&img, &reference);
                let mean_ratio = image_sum(&img) / image_sum(&reference).max(1e-300);
                nppp_files::note!(
                    "[{name}] seed {seed} {:>4} spp {:<12} {:>8.3} s {:>7.3} M samples/s  relMSE {:.4e} (trimmed {:.4e})",
                    spp,
                    c.label(),
                    stats.seconds,
                    stats.samples_per_second() / 1e6,
                    errors.rel_mse,
                    errors.rel_mse_trimmed
                );
                if seed == 1 && spp == top {
                    let p = dir.join(format!("{}-{spp}spp.png", c.slug()));
                    image_io::write_png(&img, &p)
                        .with_context(|| format!("writing {}", p.display()))?;
                }
                measurements.push(Measurement {
                    config: ci,
                    spp,
                    seed,
                    seconds: stats.seconds,
                    samples: stats.samples,
                    errors,
                    flip,
                    mean_ratio,
                    estimator_bytes,
                    stats: stats.estimators,
                });
            }
        }
    }
    Ok(SceneResult {
        name,
        path: path.to_path_buf(),
        width,
        height,
        instances: scene.instances.len(),
        estimator_instances,
        estimator_files,
        triangles_unique,
        triangles_instanced,
        build_seconds,
        reference: reference_meta,
        reference_cached,
        max_bounces: m,
        configs,
        skipped,
        measurements,
    })
}

/// Puts the configuration's estimators (with its P) into the scene; returns
/// their memory.
fn attach(
    rs: &mut RenderScene,
    c: &Config,
    neural: &mut Option<Estimators>,
    oracle: &mut Option<Estimators>,
) -> usize {
    let src = match c.kind {
        Kind::Pt => None,
        Kind::Nppp | Kind::NpppNee => neural.take(),
        Kind::Oracle => oracle.take(),
    };
    rs.estimators = src.map(|mut e| {
        let nee = match c.kind {
            Kind::NpppNee => entry_nee_of(&e),
            _ => EntryNee::Off,
        };
        e.configure(c.p, nee);
        e
    });
    rs.estimators
        .as_ref()
        .map(|e| e.memory_bytes())
        .unwrap_or(0)
}

fn detach(
    rs: &mut RenderScene,
    c: &Config,
    neural: &mut Option<Estimators>,
    oracle: &mut Option<Estimators>,
) {
    let e = rs.estimators.take();
    match c.kind {
        Kind::Pt => {}
        Kind::Nppp | Kind::NpppNee => *neural = e,
        Kind::Oracle => *oracle = e,
    }
}

/// The NEE through the estimator a `+NEE` configuration uses: at the
/// picked vertex when every estimator of an object that takes light
/// samples has a vertex head, else at the first vertex; off when no object
/// takes light samples (smooth glass, media).
fn entry_nee_of(e: &Estimators) -> EntryNee {
    let mut lit = e
        .list
        .iter()
        .map(|est| est.light_sampling_entry_nee())
        .filter(|&nee| nee != EntryNee::Off)
        .peekable();
    if lit.peek().is_none() {
        EntryNee::Off
    } else if lit.all(|nee| nee == EntryNee::PickedVertex) {
        EntryNee::PickedVertex
    } else {
        EntryNee::FirstVertex
    }
}
