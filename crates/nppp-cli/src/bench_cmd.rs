//! `nppp bench`: time against error, for plain path tracing and for path
//! tracing with estimators, on the benchmark scenes.
//!
//! Per scene: a reference (plain path tracing at M, many samples, rendered
//! once and cached with its settings), then every configuration (PT at
//! M = 1..M, PT + NPPP at P = 0..3 with the full M, optionally PT + oracle)
//! at a ladder of sample counts and several seeds. Every figure in the
//! report is measured in the same run, on the same machine, against the same
//! reference; ratios are taken against PT at the full M.

use anyhow::{Context, Result, bail, ensure};
use clap::Args;
use nppp_render::estimator::{EstimatorMode, EstimatorStats, Estimators};
use nppp_render::metrics::{self, Errors};
use nppp_render::{Image, RenderOptions, RenderScene, image_io};
use serde::{Deserialize, Serialize};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// The M' at which plain path tracing is measured: every M' up to 16, then
/// about two per octave (1, 2, ..., 16, 24, 32, 48, 64, ...) and M itself,
/// so that a translucent scene at M = 256 costs 23 PT configurations, not 256.
fn pt_bounce_ladder(m: u32) -> Vec<u32> {
    let mut ladder: Vec<u32> = (1..=m.min(16)).collect();
    let mut step = 16u32;
    while step < m {
        for x in [step + step / 2, step * 2] {
            if x < m {
                ladder.push(x);
            }
        }
        step *= 2;
    }
    if m > 16 {
        ladder.push(m);
    }
    ladder
}

#[cfg(test)]
mod ladder_tests {
    #[test]
    fn ladder_is_every_m_to_16_then_two_per_octave_ending_at_m() {
        assert_eq!(super::pt_bounce_ladder(5), vec![1, 2, 3, 4, 5]);
        let l = super::pt_bounce_ladder(256);
        assert_eq!(&l[15..], &[16, 24, 32, 48, 64, 96, 128, 192, 256]);
        let l = super::pt_bounce_ladder(100);
        assert_eq!(&l[15..], &[16, 24, 32, 48, 64, 96, 100]);
    }
}

/// The benchmark scenes, in `--scenes-dir`.
const DEFAULT_SCENES: &[&str] = &[
    "cornell-box",
    "cornell-glass",
    "cornell-gold",
    "cornell-jade",
    "tube",
    "room",
];
/// Seeds of the reference's two halves: far from the seeds 1..N of the
/// measured renders, whose random streams must not overlap the reference's.
const REFERENCE_SEEDS: [u64; 2] = [0x5EED_0000_0001, 0x5EED_0000_0002];
/// Bump when the reference's meaning changes, so old caches are re-rendered.
const REFERENCE_FORMAT: u32 = 1;
/// The P values of the thesis' comparison.
const NPPP_P: [u32; 4] = [0, 1, 2, 3];

#[derive(Args, Debug)]
pub struct BenchArgs {
    /// A few minutes on 2 cores: half resolution, spp 4,16,64, a 512-spp
    /// reference, two seeds. Without it: full resolution, spp 4..1024, a
    /// 4096-spp reference, three seeds (hours on 2 cores).
    #[arg(long)]
    pub quick: bool,
    /// Scenes to run, comma-separated: names in --scenes-dir (without
    /// `.json`) or paths to scene files.
    #[arg(long, value_delimiter = ',')]
    pub scenes: Option<Vec<String>>,
    /// Where scene names are looked up.
    #[arg(long, default_value = "data/scenes")]
    pub scenes_dir: PathBuf,
    /// Output folder: results.md, results.csv, <scene>.svg/.png, and per
    /// scene the cached reference and previews.
    #[arg(long, default_value = "out/bench")]
    pub out: PathBuf,
    /// Seeds per measurement (seeds 1..=N); errors are reported as mean and
    /// standard deviation over them.
    #[arg(long)]
    pub seeds: Option<u32>,
    /// The spp ladder, comma-separated (overrides --quick's and the full default).
    #[arg(long, value_delimiter = ',')]
    pub spp: Option<Vec<u32>>,
    /// Samples per pixel of the reference.
    #[arg(long)]
    pub reference_spp: Option<u32>,
    /// Resolution factor applied to each scene's camera (quick: 0.5, full: 1).
    #[arg(long)]
    pub scale: Option<f64>,
    /// M: the reference's and the NPPP configurations' max bounces; plain
    /// path tracing runs at every M' = 1..M. Default: each scene's own
    /// `render.max_bounces` (cornell-glass renders at M = 10, cornell-jade at
    /// 256, the rest at 5). PT's M' ladder is every value to 16, then about
    /// two per octave.
    #[arg(long)]
    pub max_bounces: Option<u32>,
    /// Also run PT + oracle (the real object traced alone in place of the
    /// network) at each P: the error the estimator's integration allows.
    #[arg(long)]
    pub oracle: bool,
    /// Re-render the references even if cached ones match.
    #[arg(long)]
    pub fresh_reference: bool,
    /// Render nothing: redraw the time-vs-error plots of an earlier run
    /// from its results.csv into --out (for runs made on a machine without
    /// a TrueType font).
    #[arg(long, value_name = "RESULTS_CSV")]
    pub plot_csv: Option<PathBuf>,
}

struct Plan {
    mode: &'static str,
    ladder: Vec<u32>,
    reference_spp: u32,
    seeds: u32,
    scale: f64,
}

impl Plan {
    fn from_args(a: &BenchArgs) -> Result<Self> {
        let (mode, ladder, reference_spp, seeds, scale) = if a.quick {
            ("quick", vec![4, 16, 64], 512, 2, 0.5)
        } else {
            ("full", vec![4, 16, 64, 256, 1024], 4096, 3, 1.0)
        };
        let mut ladder = a.spp.clone().unwrap_or(ladder);
        ladder.sort_unstable();
        ladder.dedup();
        ensure!(
            !ladder.is_empty() && ladder[0] >= 1,
            "--spp needs at least one value, each at least 1"
        );
        let plan = Plan {
            mode,
            ladder,
            reference_spp: a.reference_spp.unwrap_or(reference_spp),
            seeds: a.seeds.unwrap_or(seeds),
            scale: a.scale.unwrap_or(scale),
        };
        ensure!(
            plan.reference_spp >= 2,
            "--reference-spp must be at least 2 (it is rendered as two halves)"
        );
        ensure!(plan.seeds >= 1, "--seeds must be at least 1");
        ensure!(
            plan.scale.is_finite() && plan.scale > 0.0 && plan.scale <= 4.0,
            "--scale must be in (0, 4]"
        );
        ensure!(
            a.max_bounces.is_none_or(|m| m >= 1),
            "--max-bounces must be at least 1"
        );
        Ok(plan)
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kind {
    Pt,
    Nppp,
    Oracle,
}

impl Kind {
    /// The `kind` column of results.csv.
    fn name(self) -> &'static str {
        match self {
            Kind::Pt => "pt",
            Kind::Nppp => "nppp",
            Kind::Oracle => "oracle",
        }
    }

    fn from_name(s: &str) -> Option<Self> {
        [Kind::Pt, Kind::Nppp, Kind::Oracle]
            .into_iter()
            .find(|k| k.name() == s)
    }
}

#[derive(Clone, Debug)]
struct Config {
    kind: Kind,
    m: u32,
    p: u32,
}

impl Config {
    fn label(&self) -> String {
        match self.kind {
            Kind::Pt => format!("PT M={}", self.m),
            Kind::Nppp => format!("NPPP P={}", self.p),
            Kind::Oracle => format!("oracle P={}", self.p),
        }
    }
    /// The scene layout this configuration renders: merged for PT,
    /// estimator instances kept apart otherwise (where that differs).
    fn scene<'a>(
        &self,
        pt: &'a RenderScene,
        with_estimators: Option<&'a RenderScene>,
    ) -> &'a RenderScene {
        match self.kind {
            Kind::Pt => pt,
            Kind::Nppp | Kind::Oracle => with_estimators.unwrap_or(pt),
        }
    }
    fn slug(&self) -> String {
        match self.kind {
            Kind::Pt => format!("pt-m{}", self.m),
            Kind::Nppp => format!("nppp-p{}", self.p),
            Kind::Oracle => format!("oracle-p{}", self.p),
        }
    }
}

/// One render, measured.
struct Measurement {
    config: usize,
    spp: u32,
    seed: u64,
    seconds: f64,
    samples: u64,
    errors: Errors,
    flip: Option<f64>,
    /// Mean of the image over the reference's mean (all channels): the bias
    /// an error number alone does not show.
    mean_ratio: f64,
    estimator_bytes: usize,
    stats: EstimatorStats,
}

/// The mean over seeds of one (config, spp) cell.
#[derive(Clone, Debug)]
struct Cell {
    spp: u32,
    seconds: f64,
    samples_per_second: f64,
    rel_mse: f64,
    rel_mse_sd: Option<f64>,
    rel_mse_trimmed: f64,
    mape: f64,
    rmse: f64,
    flip: Option<f64>,
    mean_ratio: f64,
    estimator_bytes: usize,
}

#[derive(Serialize, Deserialize, Debug, Clone, PartialEq)]
struct ReferenceMeta {
    format: u32,
    scene: String,
    scene_hash: String,
    width: u32,
    height: u32,
    spp: u32,
    max_bounces: u32,
    seeds: [u64; 2],
    renderer: String,
    /// Not part of the match: how long it took and how noisy it is.
    seconds: f64,
    noise_floor_rel_mse: f64,
}

impl ReferenceMeta {
    fn same_settings(&self, o: &ReferenceMeta) -> bool {
        self.format == o.format
            && self.scene_hash == o.scene_hash
            && self.width == o.width
            && self.height == o.height
            && self.spp == o.spp
            && self.max_bounces == o.max_bounces
            && self.seeds == o.seeds
            && self.renderer == o.renderer
    }
}

struct SceneResult {
    name: String,
    path: PathBuf,
    width: u32,
    height: u32,
    instances: usize,
    estimator_instances: usize,
    estimator_files: Vec<PathBuf>,
    triangles_unique: u64,
    triangles_instanced: u64,
    build_seconds: f64,
    reference: ReferenceMeta,
    reference_cached: bool,
    /// M of the reference and the NPPP configurations (PT runs at 1..=M).
    max_bounces: u32,
    configs: Vec<Config>,
    /// Configurations that could not run, with the reason.
    skipped: Vec<(String, String)>,
    measurements: Vec<Measurement>,
}

pub fn run(a: &BenchArgs) -> Result<()> {
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
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let machine = Machine::probe();
    eprintln!(
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
    for path in &paths {
        results.push(
            bench_scene(a, &plan, path)
                .with_context(|| format!("benchmarking {}", path.display()))?,
        );
    }
    let total = t0.elapsed().as_secs_f64();
    let md = report_markdown(a, &plan, &machine, &results, total);
    let md_path = a.out.join("results.md");
    image_io::write_text(&md_path, &md)
        .with_context(|| format!("writing {}", md_path.display()))?;
    let csv_path = a.out.join("results.csv");
    image_io::write_text(&csv_path, &report_csv(&results))
        .with_context(|| format!("writing {}", csv_path.display()))?;
    let mut plots = Vec::new();
    for r in &results {
        plots.extend(plot_scene(r, &a.out)?);
    }
    eprintln!(
        "bench done in {:.0} s: {} and {}",
        total,
        md_path.display(),
        csv_path.display()
    );
    for p in plots {
        eprintln!("  plot: {p}");
    }
    Ok(())
}

fn resolve_scene(dir: &Path, name: &str) -> Result<PathBuf> {
    let p = if name.ends_with(".json") || name.contains('/') {
        PathBuf::from(name)
    } else {
        dir.join(format!("{name}.json"))
    };
    ensure!(
        p.is_file(),
        "{}: scene not found (run nppp bench from the repository root, or pass --scenes-dir or a path in --scenes)",
        p.display()
    );
    Ok(p)
}

/// `data/scenes/../../models/x` -> `models/x`, lexically (for messages and
/// the report; the file system is not consulted).
fn tidy_path(p: &Path) -> PathBuf {
    use std::path::Component;
    let mut out: Vec<Component> = Vec::new();
    for c in p.components() {
        match c {
            Component::CurDir => {}
            Component::ParentDir if matches!(out.last(), Some(Component::Normal(_))) => {
                out.pop();
            }
            c => out.push(c),
        }
    }
    if out.is_empty() {
        PathBuf::from(".")
    } else {
        out.iter().collect()
    }
}

fn scene_name(path: &Path) -> String {
    path.file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "scene".into())
}

/// Hash of everything a plain path-traced reference depends on in the scene:
/// the file itself and the content of every mesh (OBJ files included).
fn scene_hash(path: &Path, scene: &nppp_scene::Scene) -> Result<String> {
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    let mut h = nppp_scene::hash::Fnv1a::new();
    h.bytes(&bytes);
    for m in &scene.meshes {
        h.u64(nppp_scene::mesh_content_hash(m));
    }
    for m in &scene.materials {
        h.u64(nppp_scene::material_content_hash(m));
    }
    Ok(format!("{:016x}", h.finish()))
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

fn render_with(
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

fn bench_scene(a: &BenchArgs, plan: &Plan, path: &Path) -> Result<SceneResult> {
    let name = scene_name(path);
    let dir = a.out.join(&name);
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let mut scene = nppp_scene::load_scene(path)?;
    let hash = scene_hash(path, &scene)?;
    scene
        .camera
        .resize(Some(plan.scale), None, None)
        .map_err(anyhow::Error::msg)?;
    let (width, height) = (scene.camera.width, scene.camera.height);
    let m = a.max_bounces.unwrap_or(scene.render.max_bounces);

    let t_build = Instant::now();
    // Plain path tracing gets its fastest layout (estimator instances merged
    // into the world BLAS); estimator runs get theirs.
    let mut rs = RenderScene::new(&scene);
    let build_seconds = t_build.elapsed().as_secs_f64();
    // A second layout only where the first merged an estimator instance
    // (a once-used mesh); otherwise both would be the same scene.
    let mut rs_est = scene
        .instances
        .iter()
        .enumerate()
        .any(|(i, inst)| inst.estimator.is_some() && rs.accel.is_merged(i))
        .then(|| RenderScene::for_estimators(&scene));
    let triangles_unique: u64 = scene.meshes.iter().map(|m| m.triangles.len() as u64).sum();
    let triangles_instanced: u64 = scene
        .instances
        .iter()
        .map(|i| scene.meshes[i.mesh].triangles.len() as u64)
        .sum();
    eprintln!(
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
        match Estimators::load(&scene, EstimatorMode::Neural, 0) {
            Ok(Some(e)) => {
                neural = Some(e);
                configs.extend(ps.iter().map(|&p| Config {
                    kind: Kind::Nppp,
                    m,
                    p,
                }));
            }
            Ok(None) => skipped.push(("NPPP (all P)".into(), "skipped: no estimator".into())),
            Err(e) => {
                eprintln!("[{name}] warning: the estimators do not load: {e}");
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
                eprintln!(
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
        Kind::Nppp => neural.take(),
        Kind::Oracle => oracle.take(),
    };
    rs.estimators = src.map(|mut e| {
        e.configure(c.p, nppp_render::estimator::EntryNee::Off);
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
        Kind::Nppp => *neural = e,
        Kind::Oracle => *oracle = e,
    }
}

fn load_or_render_reference(
    a: &BenchArgs,
    rs: &RenderScene,
    dir: &Path,
    name: &str,
    want: &ReferenceMeta,
) -> Result<(Image, ReferenceMeta, bool)> {
    let exr = dir.join("reference.exr");
    let json = dir.join("reference.json");
    if !a.fresh_reference && exr.is_file() && json.is_file() {
        let text = std::fs::read_to_string(&json)
            .with_context(|| format!("reading {}", json.display()))?;
        match serde_json::from_str::<ReferenceMeta>(&text) {
            Ok(have) if have.same_settings(want) => {
                let img = image_io::read_exr(&exr)
                    .with_context(|| format!("reading the cached reference {}", exr.display()))?;
                if img.width == want.width && img.height == want.height {
                    eprintln!(
                        "[{name}] reference: cached {} ({} spp, settings match)",
                        exr.display(),
                        have.spp
                    );
                    return Ok((img, have, true));
                }
                eprintln!(
                    "[{name}] reference: {} has the wrong size; re-rendering",
                    exr.display()
                );
            }
            Ok(_) => eprintln!(
                "[{name}] reference: {} was made with other settings; re-rendering",
                json.display()
            ),
            Err(e) => eprintln!(
                "[{name}] reference: {} is unreadable ({e}); re-rendering",
                json.display()
            ),
        }
    }
    // Two independent halves: their difference estimates the reference's own noise.
    let rs_ref = rs;
    let half = want.spp / 2;
    eprintln!(
        "[{name}] reference: rendering PT M={} at {} spp (two halves of {half})...",
        want.max_bounces, want.spp
    );
    let (ia, sa) = render_with(rs_ref, half, want.max_bounces, want.seeds[0]);
    let (ib, sb) = render_with(rs_ref, want.spp - half, want.max_bounces, want.seeds[1]);
    let wa = half as f64 / want.spp as f64;
    let mut img = Image::new(ia.width, ia.height);
    let mut floor = 0.0f64;
    for ((o, pa), pb) in img.pixels.iter_mut().zip(&ia.pixels).zip(&ib.pixels) {
        for c in 0..3 {
            let (x, y) = (pa[c] as f64, pb[c] as f64);
            let r = wa * x + (1.0 - wa) * y;
            o[c] = r as f32;
            // Var(mean of two halves) ~= (x - y)^2 / 4 for equal halves.
            floor += (x - y) * (x - y) / 4.0 / (r * r + metrics::REL_EPS);
        }
    }
    floor /= (3 * img.pixels.len().max(1)) as f64;
    let mut meta = want.clone();
    meta.seconds = sa.seconds + sb.seconds;
    meta.noise_floor_rel_mse = floor;
    image_io::write_exr(&img, &exr).with_context(|| format!("writing {}", exr.display()))?;
    let png = dir.join("reference.png");
    image_io::write_png(&img, &png).with_context(|| format!("writing {}", png.display()))?;
    let text = serde_json::to_string_pretty(&meta).context("serializing the reference settings")?;
    image_io::write_text(&json, &(text + "\n"))
        .with_context(|| format!("writing {}", json.display()))?;
    eprintln!(
        "[{name}] reference: {:.1} s, noise floor relMSE {:.3e}",
        meta.seconds, floor
    );
    Ok((img, meta, false))
}

#[cfg(feature = "flip")]
const FLIP_NOTE: &str = "LDR-FLIP (NVIDIA FLIP via nv-flip, 67 pixels per degree) of the sRGB-encoded, clamped images (exposure 1, as the PNG previews)";
#[cfg(not(feature = "flip"))]
const FLIP_NOTE: &str = "not available (nppp-cli built without the `flip` feature)";

#[cfg(feature = "flip")]
fn flip_mean(img: &Image, reference: &Image) -> Option<f64> {
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
fn flip_mean(_img: &Image, _reference: &Image) -> Option<f64> {
    None
}

// ---------------------------------------------------------------- analysis

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len().max(1) as f64
}

fn cells(r: &SceneResult, config: usize, ladder: &[u32]) -> Vec<Cell> {
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
fn interp_loglog(pts: &[(f64, f64)], x: f64) -> Option<f64> {
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
enum Speedup {
    /// Interpolated on the configuration's own curve.
    Exact(f64),
    /// The configuration's cheapest point is already below the error: at least this.
    AtLeast(f64),
    /// The configuration's curve never gets that low on the ladder.
    NotReached,
}

impl Speedup {
    fn show(&self) -> String {
        match self {
            Speedup::Exact(x) => format!("{x:.2}x"),
            Speedup::AtLeast(x) => format!(">= {x:.2}x"),
            Speedup::NotReached => "not reached".into(),
        }
    }
}

/// The time `cells` (in ladder order) need to reach `error`, against the
/// baseline's time `t_base` for it.
fn speedup_at_error(cells: &[Cell], error: f64, t_base: f64) -> Speedup {
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

fn baseline_index(r: &SceneResult, m: u32) -> Option<usize> {
    r.configs
        .iter()
        .position(|c| c.kind == Kind::Pt && c.m == m)
}

// ---------------------------------------------------------------- reports

struct Machine {
    cpu: String,
    nproc: usize,
    threads: usize,
    date: String,
    commit: String,
    os: String,
}

impl Machine {
    fn probe() -> Self {
        let cpu = std::fs::read_to_string("/proc/cpuinfo")
            .ok()
            .and_then(|s| {
                s.lines()
                    .find(|l| l.starts_with("model name"))
                    .and_then(|l| l.split_once(':'))
                    .map(|(_, v)| v.trim().to_string())
            })
            .unwrap_or_else(|| "unknown CPU".into());
        let nproc = std::thread::available_parallelism()
            .map(|n| n.get())
            .unwrap_or(1);
        let git = |args: &[&str]| {
            std::process::Command::new("git")
                .args(args)
                .output()
                .ok()
                .filter(|o| o.status.success())
                .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string())
        };
        let commit = match git(&["rev-parse", "--short=12", "HEAD"]) {
            Some(c) => {
                let dirty = git(&["status", "--porcelain", "--untracked-files=no"])
                    .is_some_and(|s| !s.is_empty());
                if dirty {
                    format!("{c} (with uncommitted changes)")
                } else {
                    c
                }
            }
            None => "unknown (not a git checkout)".into(),
        };
        let os = std::fs::read_to_string("/proc/sys/kernel/osrelease")
            .map(|s| format!("Linux {}", s.trim()))
            .unwrap_or_else(|_| std::env::consts::OS.into());
        Machine {
            cpu,
            nproc,
            threads: rayon::current_num_threads(),
            date: utc_now(),
            commit,
            os,
        }
    }
}

/// The current UTC date and time, without a date library.
fn utc_now() -> String {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs() as i64)
        .unwrap_or(0);
    let (days, rem) = (secs.div_euclid(86_400), secs.rem_euclid(86_400));
    // Howard Hinnant's civil_from_days.
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    format!(
        "{y:04}-{m:02}-{d:02} {:02}:{:02} UTC",
        rem / 3600,
        rem % 3600 / 60
    )
}

fn peak_rss_mib() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let l = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = l.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

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

fn report_markdown(
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

    // Equal spp.
    let _ = writeln!(
        s,
        "### Equal spp: time and relMSE as a multiple of PT M={}'s\n",
        r.max_bounces
    );
    let _ = writeln!(
        s,
        "| config | {} |",
        base.iter()
            .map(|b| format!("{} spp", b.spp))
            .collect::<Vec<_>>()
            .join(" | ")
    );
    let _ = writeln!(s, "|---|{}", "---|".repeat(base.len()));
    for (ci, c) in &others {
        let cc = cells(r, *ci, &plan.ladder);
        let cols: Vec<String> = base
            .iter()
            .map(|b| match cc.iter().find(|x| x.spp == b.spp) {
                Some(x) => format!(
                    "time x{:.2}, relMSE x{:.2}",
                    x.seconds / b.seconds.max(1e-9),
                    x.rel_mse / b.rel_mse.max(1e-300)
                ),
                None => "-".into(),
            })
            .collect();
        let _ = writeln!(s, "| {} | {} |", c.label(), cols.join(" | "));
    }
    let _ = writeln!(s);

    // Equal time.
    let _ = writeln!(
        s,
        "### Equal time: relMSE as a multiple of PT M={}'s, at PT's render times (interpolated; `-` outside the configuration's measured times)\n",
        r.max_bounces
    );
    let _ = writeln!(
        s,
        "| config | {} |",
        base.iter()
            .map(|b| format!("{:.3} s (PT {} spp)", b.seconds, b.spp))
            .collect::<Vec<_>>()
            .join(" | ")
    );
    let _ = writeln!(s, "|---|{}", "---|".repeat(base.len()));
    for (ci, c) in &others {
        let mut pts: Vec<(f64, f64)> = cells(r, *ci, &plan.ladder)
            .iter()
            .map(|x| (x.seconds, x.rel_mse))
            .collect();
        pts.sort_by(|p, q| p.0.total_cmp(&q.0));
        let cols: Vec<String> = base
            .iter()
            .map(|b| match interp_loglog(&pts, b.seconds) {
                Some(e) => format!("x{:.2}", e / b.rel_mse.max(1e-300)),
                None => "-".into(),
            })
            .collect();
        let _ = writeln!(s, "| {} | {} |", c.label(), cols.join(" | "));
    }
    let _ = writeln!(s);

    // Equal error.
    let _ = writeln!(
        s,
        "### Equal error: speed-up against PT M={} (PT's time / the configuration's time for PT's relMSE)\n",
        r.max_bounces
    );
    let _ = writeln!(
        s,
        "| config | {} |",
        base.iter()
            .map(|b| format!("relMSE {} (PT {} spp)", sci(b.rel_mse), b.spp))
            .collect::<Vec<_>>()
            .join(" | ")
    );
    let _ = writeln!(s, "|---|{}", "---|".repeat(base.len()));
    for (ci, c) in &others {
        let cc = cells(r, *ci, &plan.ladder);
        let cols: Vec<String> = base
            .iter()
            .map(|b| speedup_at_error(&cc, b.rel_mse, b.seconds).show())
            .collect();
        let _ = writeln!(s, "| {} | {} |", c.label(), cols.join(" | "));
    }
    let _ = writeln!(s);

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

fn report_csv(results: &[SceneResult]) -> String {
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

// ---------------------------------------------------------------- plots

struct Curve {
    label: String,
    color: plotters::style::RGBColor,
    width: u32,
    points: Vec<(f64, f64)>,
}

/// `--plot-csv`: one plot per scene of a results.csv, each configuration's
/// (seconds, relMSE) averaged over seeds at each spp, as `curves` draws them.
fn plot_from_csv(csv: &Path, out: &Path) -> Result<()> {
    use plotters::prelude::{BitMapBackend, IntoDrawingArea, SVGBackend};
    use std::collections::BTreeMap;
    let text =
        std::fs::read_to_string(csv).with_context(|| format!("reading {}", csv.display()))?;
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
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
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
                    .filter(|&(s, e)| s > 0.0 && e > 0.0)
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
        let svg = out.join(format!("{name}.svg"));
        draw(
            SVGBackend::new(&svg, (900, 640)).into_drawing_area(),
            &title,
            &curves,
        )
        .with_context(|| format!("writing {}", svg.display()))?;
        let png = out.join(format!("{name}.png"));
        draw(
            BitMapBackend::new(&png, (900, 640)).into_drawing_area(),
            &title,
            &curves,
        )
        .with_context(|| format!("writing {}", png.display()))?;
        eprintln!("{}, {}", svg.display(), png.display());
    }
    Ok(())
}

/// Colour and line width of a configuration's curve: PT M = max in thick
/// black, smaller M in lighter greys, NPPP one colour per P, the oracle purple.
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
        Kind::Oracle => (RGBColor(148, 103, 189), 1),
    }
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
                .filter(|x| x.seconds > 0.0 && x.rel_mse > 0.0)
                .map(|x| (x.seconds, x.rel_mse))
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
    let all = curves.iter().flat_map(|c| c.points.iter());
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for &(x, y) in all {
        x0 = x0.min(x);
        x1 = x1.max(x);
        y0 = y0.min(y);
        y1 = y1.max(y);
    }
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
fn plot_scene(r: &SceneResult, out: &Path) -> Result<Vec<String>> {
    use plotters::prelude::*;
    let cs = curves(r);
    if cs.is_empty() {
        return Ok(vec![format!("{}: nothing to plot", r.name)]);
    }
    if let Err(e) = crate::plot::register_font() {
        return Ok(vec![format!("{}: plots skipped: {e}", r.name)]);
    }
    let title = format!("{}: time vs relMSE ({}x{})", r.name, r.width, r.height);
    let mut done = Vec::new();
    let svg = out.join(format!("{}.svg", r.name));
    draw(
        SVGBackend::new(&svg, (900, 640)).into_drawing_area(),
        &title,
        &cs,
    )
    .with_context(|| format!("writing {}", svg.display()))?;
    done.push(svg.display().to_string());
    let png = out.join(format!("{}.png", r.name));
    match draw(
        BitMapBackend::new(&png, (900, 640)).into_drawing_area(),
        &title,
        &cs,
    ) {
        Ok(()) => done.push(png.display().to_string()),
        Err(e) => done.push(format!("{} not written: {e:#}", png.display())),
    }
    Ok(done)
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

    #[test]
    fn date_is_plausible() {
        let d = utc_now();
        assert!(d.starts_with("20") && d.ends_with("UTC"), "{d}");
    }
}
