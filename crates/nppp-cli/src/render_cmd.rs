//! `nppp render`.

use anyhow::{Context, Result};
use clap::Args;
use nppp_render::estimator::{EstimatorMode, Estimators};
use nppp_render::{RenderOptions, RenderScene, image_io};
use std::path::PathBuf;

#[derive(Args, Debug)]
pub struct RenderArgs {
    /// Scene file (SCENE_FORMAT.md).
    pub scene: PathBuf,
    /// Samples per pixel (overrides the scene's render.spp).
    #[arg(long)]
    pub spp: Option<u32>,
    /// Maximum number of scattering events M (overrides render.max_bounces).
    #[arg(long)]
    pub max_bounces: Option<u32>,
    /// Seed of the per-sample random streams (overrides render.seed).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Output EXR (linear float32 RGB).
    #[arg(long, default_value = "out/render.exr")]
    pub out: PathBuf,
    /// Also write an sRGB PNG preview here.
    #[arg(long)]
    pub png: Option<PathBuf>,
    /// P: use estimators once a path has made at least this many bounces
    /// (overrides render.estimator_min_bounces).
    #[arg(long)]
    pub min_bounces: Option<u32>,
    /// What answers an instance's `estimator`: the baked network, the oracle
    /// (traces the real object alone; for validating the integration), or
    /// nothing (plain path tracing).
    #[arg(long, value_enum, default_value_t = EstimatorChoice::Neural)]
    pub estimators: EstimatorChoice,
    /// Hide the progress bar.
    #[arg(long)]
    pub quiet: bool,
}

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum EstimatorChoice {
    Off,
    Neural,
    Oracle,
}

pub fn run(a: &RenderArgs) -> Result<()> {
    let scene = nppp_scene::load_scene(&a.scene)?;
    let mut settings = scene.render;
    if let Some(s) = a.spp {
        anyhow::ensure!(s >= 1, "--spp must be at least 1");
        settings.spp = s;
    }
    if let Some(m) = a.max_bounces {
        settings.max_bounces = m;
    }
    if let Some(s) = a.seed {
        settings.seed = s;
    }
    if let Some(p) = a.min_bounces {
        settings.estimator_min_bounces = p;
    }
    let t0 = std::time::Instant::now();
    let mut rs = RenderScene::new(&scene);
    let mode = match a.estimators {
        EstimatorChoice::Off => EstimatorMode::Off,
        EstimatorChoice::Neural => EstimatorMode::Neural,
        EstimatorChoice::Oracle => EstimatorMode::Oracle,
    };
    rs.estimators = Estimators::load(&scene, mode, settings.estimator_min_bounces)?;
    let build = t0.elapsed().as_secs_f64();
    let opts = RenderOptions { spp: settings.spp, max_bounces: settings.max_bounces, seed: settings.seed, progress: !a.quiet };
    let (img, stats) = nppp_render::render(&rs, &opts);
    image_io::write_exr(&img, &a.out).with_context(|| "writing the EXR")?;
    if let Some(p) = &a.png {
        image_io::write_png(&img, p)?;
    }
    let m = img.mean();
    if let Some(e) = &rs.estimators {
        let st = &stats.estimators;
        eprintln!(
            "estimators ({:?}, P = {}): {} entries, {} mask skips, {} ambiguous rays traced for real, {} exits past M, {:.2} MiB shared; repairs: {} degenerate, {} inward, {} clamped",
            a.estimators,
            settings.estimator_min_bounces,
            st.entries,
            st.mask_skips,
            st.ambiguous,
            st.over_max_bounces,
            e.memory_bytes() as f64 / (1024.0 * 1024.0),
            st.repairs.degenerate,
            st.repairs.inward,
            st.repairs.clamped
        );
    }
    eprintln!(
        "{}: {}x{} spp {} M {} in {:.2}s (scene build {:.2}s), {:.3} M samples/s, mean rgb [{:.4} {:.4} {:.4}]{}",
        a.out.display(),
        img.width,
        img.height,
        settings.spp,
        settings.max_bounces,
        stats.seconds,
        build,
        stats.samples_per_second() / 1e6,
        m[0],
        m[1],
        m[2],
        if stats.dropped_samples > 0 { format!(", {} non-finite samples dropped", stats.dropped_samples) } else { String::new() }
    );
    Ok(())
}
