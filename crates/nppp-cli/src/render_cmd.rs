//! `nppp render`.

use anyhow::{Context, Result};
use clap::Args;
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
    /// Hide the progress bar.
    #[arg(long)]
    pub quiet: bool,
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
    let t0 = std::time::Instant::now();
    let rs = RenderScene::new(&scene);
    let build = t0.elapsed().as_secs_f64();
    let opts = RenderOptions { spp: settings.spp, max_bounces: settings.max_bounces, seed: settings.seed, progress: !a.quiet };
    let (img, stats) = nppp_render::render(&rs, &opts);
    image_io::write_exr(&img, &a.out).with_context(|| "writing the EXR")?;
    if let Some(p) = &a.png {
        image_io::write_png(&img, p)?;
    }
    let m = img.mean();
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
