//! `nppp render`.

use anyhow::{Context, Result, bail};
use clap::Args;
use nppp_render::estimator::{
    EntryMask, EntryNee, EstimatorMode, EstimatorModel, Estimators, LatentLookup,
};
use nppp_render::{RenderOptions, RenderScene, image_io};
use std::path::{Path, PathBuf};

#[derive(Args, Debug)]
pub struct RenderArgs {
    /// Scene file (docs/scene-format.md).
    pub scene: PathBuf,
    /// Samples per pixel (overrides the scene's render.spp).
    #[arg(long, value_parser = crate::at_least_one::<u32>)]
    pub spp: Option<u32>,
    /// Maximum number of scattering events M (overrides render.max_bounces).
    #[arg(long)]
    pub max_bounces: Option<u32>,
    /// Seed of the per-sample random streams (overrides render.seed).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Output EXR (linear float32 RGB); with --shard, the render part (*.nppr).
    #[arg(long, default_value = "out/render.exr")]
    pub out: PathBuf,
    /// Render only shard I of K (I from 0): every pixel's I-th of K sample
    /// ranges (contiguous, lengths within one of spp / K), written as a
    /// render part (--out PART.nppr) of exact per-pixel sums. `nppp merge`
    /// puts the K parts back together into the EXR this render without
    /// --shard writes, byte for byte (tools/slurm runs it as a job array).
    #[arg(long, value_parser = crate::merge_cmd::parse_shard, conflicts_with_all = ["png", "reference"])]
    pub shard: Option<crate::merge_cmd::Shard>,
    /// Render only samples START..END of every pixel (START included, END
    /// not, of 0..spp) into a render part, as --shard does with ranges of
    /// your choice: more samples to faster machines.
    #[arg(long, value_parser = parse_samples, conflicts_with_all = ["shard", "png", "reference"])]
    pub samples: Option<std::ops::Range<u32>>,
    /// Also write an sRGB PNG preview here.
    #[arg(long)]
    pub png: Option<PathBuf>,
    /// Exposure of the PNG preview in stops (radiance x 2^EV); the EXR
    /// stays linear.
    #[arg(
        long,
        default_value_t = 0.0,
        allow_negative_numbers = true,
        requires = "png"
    )]
    pub exposure: f64,
    /// Tone curve of the PNG preview: clamp (values above 1 clip) or filmic
    /// (ACES fit: highlights roll off).
    #[arg(long, value_enum, default_value_t = TonemapChoice::Clamp, requires = "png")]
    pub tonemap: TonemapChoice,
    /// Multiply the scene's image size by this (as `nppp bench --scale`).
    #[arg(long, conflicts_with_all = ["width", "height"])]
    pub scale: Option<f64>,
    /// Image width in pixels (alone: the height follows the aspect ratio).
    #[arg(long, value_parser = crate::at_least_one::<u32>)]
    pub width: Option<u32>,
    /// Image height in pixels (alone: the width follows the aspect ratio).
    #[arg(long, value_parser = crate::at_least_one::<u32>)]
    pub height: Option<u32>,
    /// P: use estimators once a path has made at least this many bounces
    /// (overrides render.estimator_min_bounces).
    #[arg(long)]
    pub min_bounces: Option<u32>,
    /// What answers an instance's `estimator`: the baked network, the oracle
    /// (traces the real object alone; for validating the integration), or
    /// nothing (plain path tracing). `cost-floor` is a timing instrument,
    /// not a render: the baked masks decide entries and every entry ends its
    /// path for free, so its time is a lower bound for any estimator using
    /// those masks (the image is biased dark by design). `free-exits`, the
    /// other timing instrument: every entry goes on for free, straight
    /// through the sphere with the training data's typical exit throughput
    /// and bounce count, so its time is a neural render's with decoding
    /// free (the gap between them is what the entries cost). The oracle and
    /// `off` read no estimator file: a missing or mismatched one is
    /// reported only by the modes that load it.
    #[arg(long, value_enum, default_value_t = EstimatorChoice::Auto)]
    pub estimators: EstimatorChoice,
    /// Next-event estimation through the estimator. `first`: sample the
    /// lights at the entry's first vertex (found by tracing the entry ray
    /// against the real mesh) and weight an emitter hit by a one-bounce exit
    /// by MIS; works with any estimator. `picked`: at one vertex of the
    /// skipped path picked by throughput; needs an estimator that returns
    /// vertices: `--estimators oracle` (MIS against the exit), or an
    /// estimator file with a vertex head (the light sample alone, the exit's
    /// emitter hit counted 0). `picked-light`: `picked` without MIS for the
    /// oracle too, to measure the network's scheme. `off`: the thesis.
    #[arg(long, value_enum, default_value_t = EntryNeeChoice::Off)]
    pub entry_nee: EntryNeeChoice,
    /// With --estimators auto: where the pilot cannot tell whether an
    /// estimator pays, decide by a confirmation pass at the render's own
    /// resolution whose samples are the image's first ones (up to two rounds
    /// of two halves of spp / 32 per configuration). Surer decisions, at a
    /// price: at 64 spp it cost the glass scenes' winners 5-8% of their
    /// time and the losers up to 6% (BENCHMARKS.md, "auto"), so it is off
    /// by default.
    #[arg(long)]
    pub auto_confirm: bool,
    /// With --estimators auto: the efficiency over PT's (1 / (work x
    /// variance), measured by the pilot) an estimator needs to be turned
    /// on; 1.05 by default. Higher is more cautious; it covers the pilot's
    /// noise and the cost model's error (BENCHMARKS.md, "auto's margin").
    #[arg(long, value_name = "FACTOR")]
    pub auto_margin: Option<f64>,
    /// How an estimator entry reads the latent grid: quadrilinear
    /// interpolation of 16 corners, or one corner picked with the
    /// probability of its weight (stochastic filtering, one memory access).
    #[arg(long, value_enum, default_value_t = LatentLookupChoice::Interpolate)]
    pub latent_lookup: LatentLookupChoice,
    /// Who decides whether a ray entering an estimator's sphere hits the
    /// object: `auto` (the real mesh for translucent objects, whose entries
    /// replace ~100 internal bounces; the learned mask otherwise), `learned`
    /// (the baked mask grid), `exact` (one query of the object's own BVH).
    #[arg(long, value_enum, default_value_t = EntryMaskChoice::Auto)]
    pub entry_mask: EntryMaskChoice,
    /// Which decoder answers batched estimator queries: the plain-Rust CPU
    /// decoder, or the Burn module on a backend (burn-wgpu needs the `wgpu` feature).
    #[arg(long, value_enum, default_value_t = DecoderChoice::Cpu)]
    pub decoder: DecoderChoice,
    /// Compare the result with this reference EXR (same size) and print relMSE,
    /// relMSE without the brightest 0.1% errors, MAPE and RMSE.
    #[arg(long)]
    pub reference: Option<PathBuf>,
    /// Hide the progress bar.
    #[arg(long)]
    pub quiet: bool,
}

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum EntryNeeChoice {
    Off,
    First,
    Picked,
    PickedLight,
}

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum LatentLookupChoice {
    Interpolate,
    Stochastic,
}

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum EntryMaskChoice {
    Auto,
    Learned,
    Exact,
}

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum TonemapChoice {
    Clamp,
    Filmic,
}

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum EstimatorChoice {
    Off,
    /// A short pilot decides, per estimator, whether and how to use it
    /// (nppp_render::auto).
    Auto,
    Neural,
    Oracle,
    CostFloor,
    FreeExits,
}

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum DecoderChoice {
    Cpu,
    BurnNdarray,
    BurnFlex,
    BurnWgpu,
}

/// `--entry-nee picked` with neural estimators: every estimator of an object
/// whose surface takes light samples must have a vertex head.
fn check_vertex_heads(e: &Estimators) -> Result<()> {
    for est in &e.list {
        let EstimatorModel::Neural { sampler } = &est.model else {
            continue;
        };
        if est.takes_light_samples() && !est.has_vertex_head() {
            let m = sampler.meta();
            bail!(
                "--entry-nee picked: the estimator of mesh '{}' ({}) has no vertex head, so it \
                 returns no vertex of the skipped path. Rebuild it from data made by this \
                 version (`nppp gen`, `nppp train`, `nppp bake`; `make bake OBJECT=...` for the \
                 committed ones), use --estimators oracle, or --entry-nee first, which works \
                 with any estimator",
                m.mesh_name,
                m.material_name
            );
        }
    }
    Ok(())
}

fn attach_decoders(ests: &mut Estimators, choice: DecoderChoice) -> Result<()> {
    let backend = match choice {
        DecoderChoice::Cpu => return Ok(()),
        DecoderChoice::BurnNdarray => nppp_nn::BackendKind::Ndarray,
        DecoderChoice::BurnFlex => nppp_nn::BackendKind::Flex,
        DecoderChoice::BurnWgpu => nppp_nn::BackendKind::Wgpu,
    };
    for e in &mut ests.list {
        if let EstimatorModel::Neural { sampler } = &mut e.model {
            let burn = nppp_nn::decoder::BurnDecoder::new(&sampler.baked().decoder, backend)?;
            sampler.set_decoder(Box::new(burn));
        }
    }
    Ok(())
}

/// "N decoder batches of K entries on average (cpu)": how the render's
/// entries reached the decoder (a GPU decoder pays only on large batches,
/// BENCHMARKS.md), and which decoder answered them.
fn decoder_batches(st: &nppp_render::estimator::EstimatorStats, ests: &Estimators) -> String {
    if st.decoder_batches == 0 {
        return "no decoder batches".into();
    }
    let mut names: Vec<&str> = ests
        .list
        .iter()
        .filter_map(|e| match &e.model {
            EstimatorModel::Neural { sampler } => Some(sampler.decoder_name()),
            _ => None,
        })
        .collect();
    names.dedup();
    format!(
        "{} decoder batches of {:.0} entries on average ({})",
        st.decoder_batches,
        st.entries as f64 / st.decoder_batches as f64,
        names.join(", ")
    )
}

/// Per estimator of `ests`: "mesh/material" of the first instance using it.
fn estimator_names(scene: &nppp_scene::Scene, ests: &Estimators) -> Vec<String> {
    (0..ests.list.len())
        .map(|i| {
            ests.per_instance()
                .iter()
                .position(|e| *e == Some(i as u32))
                .map(|ii| {
                    let inst = &scene.instances[ii];
                    format!(
                        "{}/{}",
                        scene.mesh_names[inst.mesh], scene.material_names[inst.material]
                    )
                })
                .unwrap_or_else(|| format!("estimator {i} (its instances obstructed)"))
        })
        .collect()
}

/// The output paths are checked before rendering: a typo in `--out` must not
/// cost the render, and an EXR must not be written under a `.png` name.
/// Neither output may name an input (the reference, the scene, its meshes
/// or estimators): the render would replace it.
fn check_outputs(a: &RenderArgs, scene: &nppp_scene::Scene) -> Result<()> {
    let mut inputs = scene.input_files();
    if let Some(r) = &a.reference {
        inputs.push(("the --reference image".to_string(), r.clone()));
    }
    nppp_files::ensure_not_input("--out", &a.out, &inputs).map_err(anyhow::Error::msg)?;
    if let Some(p) = &a.png {
        nppp_files::ensure_not_input("--png", p, &inputs).map_err(anyhow::Error::msg)?;
    }
    let has_ext = crate::has_extension;
    if a.shard.is_some() || a.samples.is_some() {
        // clap's `requires = "png"` does not hold beside --shard, which
        // conflicts with --png: the flags were accepted and did nothing.
        anyhow::ensure!(
            a.exposure == 0.0 && a.tonemap == TonemapChoice::Clamp,
            "--exposure and --tonemap shape the PNG preview, which a render part does not \
             write (`nppp merge --png` writes the merged image's, at exposure 0 with the clamp \
             curve)"
        );
        anyhow::ensure!(
            has_ext(&a.out, "nppr"),
            "--out {}: with --shard or --samples the output is a render part for `nppp merge`; name it *.nppr",
            a.out.display()
        );
    } else {
        anyhow::ensure!(
            has_ext(&a.out, "exr"),
            "--out {}: the output is an OpenEXR image; name it *.exr",
            a.out.display()
        );
    }
    image_io::check_writable(&a.out).context("--out")?;
    if let Some(p) = &a.png {
        anyhow::ensure!(
            has_ext(p, "png"),
            "--png {}: the preview is a PNG image; name it *.png",
            p.display()
        );
        anyhow::ensure!(
            !nppp_files::same_file(p, &a.out),
            "--png and --out are the same file ({})",
            p.display()
        );
        image_io::check_writable(p).context("--png")?;
    }
    Ok(())
}

/// A flag's number as a message shows it: in e-notation when huge or tiny
/// (`--exposure 1e30` printed 31 digits), else as given (an f32 is printed
/// as an f32: widened to f64, 70.3 printed 70.30000305175781).
fn shown<T>(v: T) -> String
where
    T: Copy + Into<f64> + std::fmt::Display + std::fmt::LowerExp,
{
    let x: f64 = v.into();
    if x.is_finite() && x != 0.0 && !(1e-3..1e6).contains(&x.abs()) {
        format!("{v:.3e}")
    } else {
        format!("{v}")
    }
}

pub fn run(a: &RenderArgs) -> Result<()> {
    let mut scene = nppp_scene::load_scene(&a.scene)?;
    let scene_size = (scene.camera.width, scene.camera.height);
    scene
        .camera
        .resize(a.scale, a.width, a.height)
        .map_err(anyhow::Error::msg)?;
    // A side below half a pixel is rendered 1 pixel: said, not silent.
    if let Some(s) = a.scale
        && (f64::from(scene_size.0) * s < 0.5 || f64::from(scene_size.1) * s < 0.5)
    {
        nppp_files::note!(
            "note: --scale {}: the image would be under a pixel on a side ({}x{} in the scene); \
             rendering {}x{}",
            shown(s),
            scene_size.0,
            scene_size.1,
            scene.camera.width,
            scene.camera.height
        );
    }
    anyhow::ensure!(
        a.exposure.is_finite() && a.exposure.abs() <= 64.0,
        "--exposure {}: give stops between -64 and 64",
        shown(a.exposure)
    );
    // Read the reference first: a bad reference should fail before minutes of rendering.
    let reference = match &a.reference {
        Some(p) => {
            let r = image_io::read_exr(p).with_context(|| {
                format!(
                    "--reference {}: cannot be read as an RGB OpenEXR image",
                    p.display()
                )
            })?;
            // Checked now, not after the render: every error metric would be NaN.
            if let Some(i) = r
                .pixels
                .iter()
                .position(|px| px.iter().any(|c| !c.is_finite() || *c < 0.0))
            {
                anyhow::bail!(
                    "--reference {}: pixel ({}, {}) is {:?}; a reference must be finite and non-negative radiance",
                    p.display(),
                    i as u32 % r.width,
                    i as u32 / r.width,
                    r.pixels[i]
                );
            }
            Some(r)
        }
        None => None,
    };
    if let Some(r) = &reference
        && (r.width, r.height) != (scene.camera.width, scene.camera.height)
    {
        anyhow::bail!(
            "--reference {}: the reference is {}x{}, the scene renders {}x{}",
            a.reference.as_deref().unwrap_or(Path::new("")).display(),
            r.width,
            r.height,
            scene.camera.width,
            scene.camera.height
        );
    }
    check_outputs(a, &scene)?;
    let mut settings = scene.render;
    if let Some(s) = a.spp {
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
    // The samples of this render part (`--shard`, `--samples`), if it is one.
    let part_samples = match (a.shard, &a.samples) {
        (Some(sh), _) => {
            anyhow::ensure!(
                sh.count <= settings.spp,
                "--shard {sh}: {} shards of a {}-spp render would leave some without a sample; use at most {} shards (or more --spp)",
                sh.count,
                settings.spp,
                settings.spp
            );
            Some(nppp_render::render_part::shard_samples(
                sh.index,
                sh.count,
                settings.spp,
            ))
        }
        (None, Some(r)) => {
            anyhow::ensure!(
                r.end <= settings.spp,
                "--samples {}..{}: the render has {} samples per pixel (0..{})",
                r.start,
                r.end,
                settings.spp,
                settings.spp
            );
            Some(r.clone())
        }
        (None, None) => None,
    };
    if part_samples.is_some() {
        check_film_memory(scene.camera.width, scene.camera.height)?;
    }
    let has_estimators = scene.instances.iter().any(|i| i.estimator.is_some());
    if has_estimators
        && !matches!(a.estimators, EstimatorChoice::Off | EstimatorChoice::Auto)
        && settings.estimator_min_bounces >= settings.max_bounces
    {
        nppp_files::note!(
            "warning: P = {} >= M = {}: no path can reach an estimator after P bounces, so this \
             render is plain path tracing (lower --min-bounces to use the estimators)",
            settings.estimator_min_bounces,
            settings.max_bounces
        );
    }
    let t0 = std::time::Instant::now();
    let mode = match a.estimators {
        EstimatorChoice::Off => EstimatorMode::Off,
        EstimatorChoice::Neural | EstimatorChoice::Auto => EstimatorMode::Neural,
        EstimatorChoice::Oracle => EstimatorMode::Oracle,
        EstimatorChoice::CostFloor => {
            nppp_files::note!(
                "warning: --estimators cost-floor ends every path at its first estimator entry: the image is not an estimate of the scene (timing only)"
            );
            EstimatorMode::CostFloor
        }
        EstimatorChoice::FreeExits => {
            nppp_files::note!(
                "warning: --estimators free-exits answers every estimator entry with a free exit straight through the object: the image is not an estimate of the scene (timing only)"
            );
            EstimatorMode::FreeExits
        }
    };
    if a.entry_nee != EntryNeeChoice::Off && (!has_estimators || mode == EstimatorMode::Off) {
        nppp_files::note!(
            "warning: --entry-nee does nothing here: {}",
            if has_estimators {
                "--estimators off renders plain path tracing"
            } else {
                "no instance of the scene has an estimator"
            }
        );
    }
    let picked = matches!(
        a.entry_nee,
        EntryNeeChoice::Picked | EntryNeeChoice::PickedLight
    );
    let instrument = matches!(mode, EstimatorMode::CostFloor | EstimatorMode::FreeExits);
    if instrument && a.entry_nee != EntryNeeChoice::Off {
        // They trace and decode nothing at an entry: no vertex to light,
        // and a timing with the flag would leave out what it costs.
        bail!(
            "--entry-nee {} needs an estimator that answers its entries (--estimators neural \
             or oracle): the cost floor and free exits trace and decode nothing at an entry, \
             so they take no next-event estimation through it (give --entry-nee off)",
            flag_spelling(&a.entry_nee)
        );
    }
    if a.decoder != DecoderChoice::Cpu {
        let why = match mode {
            _ if !has_estimators => Some("no instance of the scene has an estimator"),
            EstimatorMode::Off => Some("--estimators off renders plain path tracing"),
            EstimatorMode::Oracle => Some("the oracle traces the real object and decodes nothing"),
            EstimatorMode::CostFloor | EstimatorMode::FreeExits => {
                Some("the cost floor and free exits decode nothing")
            }
            EstimatorMode::Neural => None,
        };
        if let Some(why) = why {
            nppp_files::note!("warning: --decoder does nothing here: {why}");
        }
    }
    let auto = a.estimators == EstimatorChoice::Auto;
    if a.auto_margin.is_some() && !auto {
        bail!(
            "--auto-margin is the margin of --estimators auto: give --estimators auto (the default)"
        );
    }
    if let Some(m) = a.auto_margin
        && !(m.is_finite() && (1.0..=10.0).contains(&m))
    {
        bail!(
            "--auto-margin {}: give a factor from 1 to 10 (the default is {})",
            shown(m),
            nppp_render::auto::PilotOptions::default().margin
        );
    }
    if a.auto_confirm && !auto {
        bail!(
            "--auto-confirm confirms what --estimators auto decides: give --estimators auto (the default)"
        );
    }
    if auto && (a.min_bounces.is_some() || a.entry_nee != EntryNeeChoice::Off) {
        bail!(
            "--estimators auto chooses P and the entry NEE itself; give --estimators neural \
             with --min-bounces / --entry-nee to set them"
        );
    }
    let confirms = a.auto_confirm
        && u64::from(scene.camera.width) * u64::from(scene.camera.height)
            <= nppp_render::auto::PilotOptions::default().confirm_max_pixels;
    let pixel_bytes = nppp_render::scene_data::RENDER_BYTES_PER_PIXEL
        + if confirms {
            nppp_render::scene_data::AUTO_CONFIRM_BYTES_PER_PIXEL
        } else {
            0
        };
    if let Some(problem) = nppp_render::scene_data::render_memory_problem(&scene, pixel_bytes, mode)
    {
        bail!("{}: {problem}", a.scene.display());
    }
    let mut rs = RenderScene::with_estimators(&scene, mode, settings.estimator_min_bounces)
        .with_context(|| a.scene.display().to_string())?;
    if mode != EstimatorMode::Off
        && let Some(line) = nppp_render::estimator::unused_on_emitters(&scene)
    {
        nppp_files::note!("warning: {}: {line}", a.scene.display());
    }
    for line in nppp_render::estimator_overlap::describe_all(&rs.obstructed, &scene) {
        nppp_files::note!("warning: {}: {line}", a.scene.display());
    }
    if let Some(e) = &mut rs.estimators {
        let nee = match a.entry_nee {
            EntryNeeChoice::Off => EntryNee::Off,
            EntryNeeChoice::First => EntryNee::FirstVertex,
            EntryNeeChoice::Picked => EntryNee::PickedVertex,
            EntryNeeChoice::PickedLight => EntryNee::PickedVertexLightOnly,
        };
        if picked {
            check_vertex_heads(e)?;
        }
        if nee != EntryNee::Off && !e.list.iter().any(|est| est.takes_light_samples()) {
            nppp_files::note!(
                "warning: --entry-nee does nothing here: no estimator's object takes light \
                 samples (smooth glass, smooth mirrors and translucent objects scatter only in \
                 delta directions)"
            );
        }
        e.configure(settings.estimator_min_bounces, nee);
        // P = 0 gives the camera's own rays to the network: what a camera
        // sees of a dense medium is subsurface transport, which a network
        // reproduces; a surface is seen through its blur (an unseen scene's
        // glass knot filling the frame rendered 5% bright, relMSE 5.5
        // against the oracle's 0.0015). auto never tries it for them.
        if mode == EstimatorMode::Neural
            && !auto
            && settings.estimator_min_bounces == 0
            && e.list.iter().any(|est| est.medium.is_none())
        {
            nppp_files::note!(
                "warning: P = 0: camera rays enter the estimators, so the objects they answer \
                 for (other than translucent ones) are seen through the network's blur: sharp \
                 reflections and refractions smeared, light spilled past their edges. \
                 Measured on unseen scenes, 0.3% to 5% off in the image mean; P >= 1 keeps \
                 what the camera sees exact (--estimators auto never tries P = 0 for them)"
            );
        }
        e.latent_lookup = match a.latent_lookup {
            LatentLookupChoice::Interpolate => LatentLookup::Interpolate,
            LatentLookupChoice::Stochastic => LatentLookup::Stochastic,
        };
        e.entry_mask = match a.entry_mask {
            EntryMaskChoice::Auto => EntryMask::Auto,
            EntryMaskChoice::Learned => EntryMask::Learned,
            EntryMaskChoice::Exact => EntryMask::Exact,
        };
        attach_decoders(e, a.decoder)?;
        if mode == EstimatorMode::FreeExits {
            // What every entry continues with: a user timing the instrument
            // sees what it stands for (and a file whose mean exit had to be
            // clamped shows it).
            for (name, est) in estimator_names(&scene, e).iter().zip(&e.list) {
                if let EstimatorModel::CostFloor {
                    continue_with: Some(x),
                    ..
                } = &est.model
                {
                    nppp_files::note!(
                        "free exits: {name} continues with throughput [{:.3} {:.3} {:.3}] after {} internal bounces",
                        x.throughput.x,
                        x.throughput.y,
                        x.throughput.z,
                        x.bounces
                    );
                }
            }
        }
    }
    let build = t0.elapsed().as_secs_f64();
    let opts = RenderOptions {
        spp: settings.spp,
        max_bounces: settings.max_bounces,
        seed: settings.seed,
        progress: !a.quiet,
    };
    // auto's pilot and confirmation pass (wall clock, both), and the plan
    // the render follows.
    let mut plan_seconds = 0.0;
    let mut plan = None;
    let mut auto_choices = None;
    if auto && let Some(ests) = rs.estimators.take() {
        let names = estimator_names(&scene, &ests);
        let released: Vec<bool> = (0..ests.list.len())
            .map(|i| !ests.per_instance().contains(&Some(i as u32)))
            .collect();
        let t = std::time::Instant::now();
        // A pilot of a few percent of the render, sized to its budget: two
        // halves of spp / 16 at a quarter of the resolution (4 spp per half
        // for a 64-spp render), at least 1 and at most 16 per half. The
        // pilot's variance ratios are heavy-tailed (a caustic or a long
        // medium walk caught or missed) and tighten only with more samples:
        // a longer render can afford a pilot that sees more of them.
        // With --auto-confirm, where it cannot tell, the confirmation pass
        // renders up to two rounds of two halves of spp / 32 (1 to 8) of the
        // image itself per configuration: 8 samples each for a 64-spp
        // render, at most 32.
        // The scene's P is the contract's "used only once the path has made
        // at least P bounces": auto may choose a larger P, or none, never a
        // smaller one (and never 0 but for translucent objects, see
        // PilotOptions::min_p and min_p_medium).
        let defaults = nppp_render::auto::PilotOptions::default();
        let min_p = settings.estimator_min_bounces.max(defaults.min_p);
        let min_p_medium = settings.estimator_min_bounces.max(defaults.min_p_medium);
        let confirm_spp = (settings.spp / 32).clamp(1, 8);
        if a.auto_confirm {
            // Said, as --entry-nee and --decoder say where they do nothing:
            // the flag was ignored without a word.
            let pixels = u64::from(rs.camera.width) * u64::from(rs.camera.height);
            let most = defaults.confirm_max_pixels;
            if pixels > most {
                nppp_files::note!(
                    "warning: --auto-confirm does nothing here: the image has {pixels} pixels, \
                     more than the {most} its confirmation pass renders at full resolution"
                );
            } else if 2 * confirm_spp * 2 > settings.spp / 2 {
                nppp_files::note!(
                    "warning: --auto-confirm does nothing at {} spp: one round of its \
                     confirmation pass (two halves of PT and of a candidate, {confirm_spp} spp \
                     each) must fit in half the samples; give --spp {} or more",
                    settings.spp,
                    8 * confirm_spp
                );
            }
        }
        let pilot = nppp_render::auto::PilotOptions {
            max_bounces: settings.max_bounces,
            seed: settings.seed,
            spp: (settings.spp / 16).clamp(1, 16),
            confirm_spp: if a.auto_confirm { confirm_spp } else { 0 },
            min_p,
            min_p_medium,
            max_p: defaults.max_p.max(min_p),
            margin: a.auto_margin.unwrap_or(defaults.margin),
            ..defaults
        };
        let p = nppp_render::auto::plan(&mut rs, ests, &pilot, &opts);
        let decision = &p.decision;
        auto_choices = Some(
            decision
                .estimators
                .iter()
                .map(|d| format!("{}: {}", names[d.index], nppp_render::auto::label(d.choice)))
                .collect::<Vec<_>>()
                .join("; "),
        );
        plan_seconds = t.elapsed().as_secs_f64();
        for (line, d) in decision.describe(&names).iter().zip(&decision.estimators) {
            if released[d.index] {
                // No instance left to try it on (each obstructed): it said
                // "no P that auto tries is below M" (at M 256).
                nppp_files::note!(
                    "auto: {}: not used: every instance of it is traced for real (see the \
                     warning above)",
                    names[d.index]
                );
            } else {
                nppp_files::note!("auto: {line}");
            }
        }
        nppp_files::note!(
            "auto: pilot {:.2} s ({} samples at {}x{})",
            p.pilot_seconds,
            decision.samples,
            decision.width,
            decision.height
        );
        if !p.segments.is_empty() {
            let parts: Vec<String> = p
                .segments
                .iter()
                .map(|s| {
                    let what = match s.only {
                        None => "PT".to_string(),
                        Some((i, c)) => {
                            format!("{} {}", names[i], nppp_render::auto::label(Some(c)))
                        }
                    };
                    format!("{what} {} spp", s.sample_count())
                })
                .collect();
            nppp_files::note!(
                "auto: confirmed at full resolution with samples 0..{} of {} ({}), {:.2} s, kept in the image",
                p.rest_start(),
                settings.spp,
                parts.join(", "),
                p.confirmation_seconds()
            );
        }
        plan = Some(p);
    }
    if let Some(samples) = part_samples {
        // Read (the estimator files' hashes) before the render, not after it.
        let part_settings = part_settings(a, &scene, &rs, auto_choices)?;
        let (film, stats) = match &mut plan {
            Some(p) => p.render_part(&mut rs, &opts, samples.clone()),
            None => nppp_render::render_film(&rs, &opts, samples.clone()),
        };
        let header = nppp_render::render_part::RenderPartHeader {
            renderer: nppp_render::render_part::renderer_id(),
            scene: a.scene.display().to_string(),
            scene_hash: format!("{:016x}", nppp_scene::scene_content_hash(&scene)),
            width: scene.camera.width,
            height: scene.camera.height,
            spp: settings.spp,
            seed: settings.seed,
            max_bounces: settings.max_bounces,
            samples: [samples.start, samples.end],
            settings: part_settings,
            seconds: stats.seconds + plan_seconds,
        };
        nppp_render::render_part::write_part(&a.out, &header, &film)?;
        nppp_files::note!(
            "{}: render part (samples {}..{} of {}) of {}x{} M {} in {:.2}s (scene build {:.2}s){}",
            a.out.display(),
            samples.start,
            samples.end,
            settings.spp,
            header.width,
            header.height,
            settings.max_bounces,
            header.seconds,
            build,
            if stats.dropped_samples > 0 {
                format!(", {} non-finite samples dropped", stats.dropped_samples)
            } else {
                String::new()
            }
        );
        return Ok(());
    }
    let (img, mut stats) = match &mut plan {
        Some(p) => p.render(&mut rs, &opts),
        None => nppp_render::render(&rs, &opts),
    };
    // The pilot is part of the render's time (the confirmation's renders
    // are counted in `stats`, as the image's samples they are).
    if let Some(p) = &plan {
        stats.seconds += plan_seconds - p.confirmation_seconds();
    }
    let preview = image_io::Preview {
        exposure_ev: a.exposure as f32,
        tonemap: match a.tonemap {
            TonemapChoice::Clamp => image_io::Tonemap::Clamp,
            TonemapChoice::Filmic => image_io::Tonemap::Filmic,
        },
    };
    match &a.png {
        Some(p) => image_io::write_exr_and_preview(&img, &a.out, Some((p, &preview)))
            // The error names the file that failed (the EXR or the PNG).
            .with_context(|| "writing the EXR (--out) and its preview (--png)")?,
        None => image_io::write_exr(&img, &a.out).with_context(|| "writing the EXR")?,
    }
    let m = img.mean();
    if let Some(e) = &rs.estimators {
        let st = &stats.estimators;
        nppp_files::note!(
            "estimators ({}): {} entries, {} mask skips, {} ambiguous rays traced for real, {} exits past M, {} exits from the object (other geometry in its sphere), {}, {} decoder fallbacks, {} shared; repairs: {} degenerate, {} inward, {} clamped{}",
            // As the flag spells it (it printed `Auto`), and P where one P
            // holds for all (auto chooses per estimator, said above).
            match a.estimators {
                EstimatorChoice::Auto => "auto, P per estimator as chosen".to_string(),
                other => format!("{}, P = {}", flag_spelling(&other), e.min_bounces),
            },
            st.entries,
            st.mask_skips,
            st.ambiguous,
            st.over_max_bounces,
            st.exits_from_object,
            decoder_batches(st, e),
            st.decoder_fallbacks,
            nppp_files::format_bytes(e.memory_bytes() as u64),
            st.repairs.degenerate,
            st.repairs.inward,
            st.repairs.clamped,
            if st.repairs.vertices > 0 {
                format!(", {} picked vertices", st.repairs.vertices)
            } else {
                String::new()
            }
        );
        for w in estimator_warnings(st) {
            nppp_files::note!("warning: {w}");
        }
    }
    nppp_files::note!(
        "traced: {:.3} M rays, {:.3} M shadow rays, {:.3} M BVH node visits ({:.3} M by camera rays, {:.3} M leaves by later rays)",
        stats.work.rays as f64 / 1e6,
        stats.work.shadow_rays as f64 / 1e6,
        stats.work.node_visits as f64 / 1e6,
        stats.work.camera_node_visits as f64 / 1e6,
        stats.work.leaf_visits as f64 / 1e6
    );
    nppp_files::note!(
        "work: {}",
        nppp_render::auto::describe_work(&stats.work, &stats.estimators)
    );
    // Four decimals; a huge or tiny mean (a lamp of 1e30, or of 1e-30) in
    // e-notation, not forty digits or zeros.
    let mean = |x: f64| {
        if x != 0.0 && !(1e-4..1e6).contains(&x.abs()) {
            format!("{x:.4e}")
        } else {
            format!("{x:.4}")
        }
    };
    nppp_files::note!(
        "{}: {}x{} spp {} M {} in {:.2}s (scene build {:.2}s), {:.3} M samples/s, mean rgb [{} {} {}]{}",
        a.out.display(),
        img.width,
        img.height,
        settings.spp,
        settings.max_bounces,
        stats.seconds,
        build,
        stats.samples_per_second() / 1e6,
        mean(m[0]),
        mean(m[1]),
        mean(m[2]),
        if stats.dropped_samples > 0 {
            format!(", {} non-finite samples dropped", stats.dropped_samples)
        } else {
            String::new()
        }
    );
    if let Some(r) = &reference {
        let e = nppp_render::metrics::compare(&img, r).with_context(|| {
            format!(
                "comparing with {}",
                a.reference
                    .as_ref()
                    .map(|p| p.display().to_string())
                    .unwrap_or_default()
            )
        })?;
        // Fixed decimals; a huge error (a reference of another scene) in
        // e-notation, not forty digits.
        let m = |x: f64, decimals: usize| {
            if x.abs() >= 1e6 {
                format!("{x:.4e}")
            } else {
                format!("{x:.decimals$}")
            }
        };
        nppp_files::note!(
            "error vs {}: relMSE {}, relMSE (brightest 0.1% dropped) {}, MAPE {}, RMSE {}; {:.2}s",
            a.reference
                .as_ref()
                .map(|p| p.display().to_string())
                .unwrap_or_default(),
            m(e.rel_mse, 5),
            m(e.rel_mse_trimmed, 5),
            m(e.mape, 4),
            m(e.rmse, 5),
            stats.seconds
        );
    }
    Ok(())
}

/// `START..END` (`--samples`): a non-empty range of sample indices.
fn parse_samples(s: &str) -> Result<std::ops::Range<u32>, String> {
    let (a, b) = s
        .split_once("..")
        .ok_or_else(|| format!("\"{s}\": give START..END, e.g. 0..48 (END not included)"))?;
    let num = |t: &str| {
        t.trim()
            .parse::<u32>()
            .map_err(|_| match t.trim().parse::<u128>() {
                Ok(_) => format!(
                    "\"{s}\": {} is too large (samples are numbered below 2^32)",
                    t.trim()
                ),
                Err(_) => format!("\"{s}\": \"{t}\" is not a whole number"),
            })
    };
    let (a, b) = (num(a)?, num(b)?);
    if a >= b {
        return Err(format!(
            "\"{s}\": START must be below END (the range holds no sample)"
        ));
    }
    Ok(a..b)
}

/// A render part holds its film in memory twice over while it is written
/// (the sums and their serialized columns): refused before rendering when
/// that cannot fit, instead of failing at the end of the render.
pub fn check_film_memory(width: u32, height: u32) -> Result<()> {
    let per_pixel = 2 * nppp_render::render_part::PART_BYTES_PER_PIXEL + 12;
    check_pixels_memory(width, height, per_pixel, "a render part")
}

/// Refuses `what` of `width` x `height` pixels at `per_pixel` bytes each
/// when that is more than the memory available.
pub fn check_pixels_memory(width: u32, height: u32, per_pixel: u64, what: &str) -> Result<()> {
    let need = u64::from(width)
        .saturating_mul(u64::from(height))
        .saturating_mul(per_pixel);
    if let Some(avail) = nppp_files::available_memory()
        && need > avail
    {
        bail!(
            "{what} of {width}x{height} needs about {} of memory for its film ({per_pixel} bytes \
             per pixel), {} is available: use a smaller image or a machine with more memory",
            nppp_files::format_bytes(need),
            nppp_files::format_bytes(avail)
        );
    }
    Ok(())
}

/// A flag's value as the command line spells it (`picked`, not Rust's
/// `PickedVertex`), for messages and render parts' settings.
fn flag_spelling<T: clap::ValueEnum>(v: &T) -> String {
    v.to_possible_value()
        .map_or_else(String::new, |p| p.get_name().to_string())
}

/// What a render part's image depends on beyond the scene's content and the
/// numbers in its header: the estimator options as used, each estimator
/// file's content, and `auto`'s decision. Parts must agree on all of it.
fn part_settings(
    a: &RenderArgs,
    scene: &nppp_scene::Scene,
    rs: &RenderScene,
    auto_choices: Option<String>,
) -> Result<std::collections::BTreeMap<String, String>> {
    // Values as their flags spell them (a mismatch is reported with them).
    let mut m = std::collections::BTreeMap::new();
    m.insert("estimators".into(), flag_spelling(&a.estimators));
    if let Some(e) = &rs.estimators {
        m.insert("P".into(), e.min_bounces.to_string());
        m.insert("entry_nee".into(), flag_spelling(&a.entry_nee));
        m.insert("latent_lookup".into(), flag_spelling(&a.latent_lookup));
        m.insert("entry_mask".into(), flag_spelling(&a.entry_mask));
        m.insert("decoder".into(), flag_spelling(&a.decoder));
    }
    if let Some(c) = auto_choices {
        m.insert("auto".into(), c);
    }
    if a.estimators == EstimatorChoice::Auto {
        // Its confirmation pass renders the first samples its own way: a
        // part with it and one without merged into neither render's image.
        m.insert("auto_confirm".into(), a.auto_confirm.to_string());
    }
    // The oracle and `off` read no estimator file, so their parts do not
    // depend on one (and render without them, as the full image does).
    let reads_files = !matches!(a.estimators, EstimatorChoice::Off | EstimatorChoice::Oracle);
    // Each file read and hashed once, however many instances name it (the
    // room's 2,025 knots hashed their one 16.8 MB file 2,025 times: 47 s a
    // shard), and which instance has which content as one hash: by content,
    // not by path, so that parts rendered from other folders still merge.
    if reads_files {
        let mut by_path: std::collections::HashMap<&std::path::Path, u64> = Default::default();
        let mut all = nppp_scene::hash::Fnv1a::new();
        for (i, inst) in scene.instances.iter().enumerate() {
            let Some(path) = &inst.estimator else {
                continue;
            };
            let content = match by_path.get(path.as_path()) {
                Some(&c) => c,
                None => {
                    let bytes = nppp_files::read_regular(path).with_context(|| {
                        format!(
                            "{}: instances[{i}].estimator {}",
                            a.scene.display(),
                            path.display()
                        )
                    })?;
                    let mut h = nppp_scene::hash::Fnv1a::new();
                    h.bytes(&bytes);
                    *by_path.entry(path.as_path()).or_insert(h.finish())
                }
            };
            all.u64(i as u64);
            all.u64(content);
        }
        m.insert(
            "estimator files of the instances (hash)".into(),
            format!("{:016x}", all.finish()),
        );
    }
    Ok(m)
}

/// Share of entries above which a repair count means the estimator is
/// probably wrong for this object (a well-trained one repairs well under 1%).
const SUSPICIOUS_REPAIR_SHARE: f64 = 0.05;

/// Rays that crossed estimator spheres and were all turned away, above
/// which a render with no entry at all says so: the objects vanished for
/// paths past P (a rare legitimate case: rays through a sphere that all miss
/// a thin object's bounds).
const SUSPICIOUS_SKIPS_WITHOUT_ENTRY: u64 = 1000;

/// What a render's estimator counts say about the result, when it is
/// probably wrong, with what to do.
fn estimator_warnings(st: &nppp_render::estimator::EstimatorStats) -> Vec<String> {
    let mut w = Vec::new();
    if st.entries == 0 {
        if st.mask_skips >= SUSPICIOUS_SKIPS_WITHOUT_ENTRY {
            w.push(format!(
                "no path entered an estimator, though {} rays crossed their spheres and were \
                 turned away: their objects are invisible to paths past P. If they should be \
                 seen there, the estimator's entry mask refuses every ray (a damaged file, or \
                 one made for another object): check it with `nppp info FILE`, or compare with \
                 --estimators oracle",
                st.mask_skips
            ));
        }
        return w;
    }
    let share = |n: u64| n as f64 / st.entries as f64;
    if share(u64::from(st.repairs.clamped)) > SUSPICIOUS_REPAIR_SHARE {
        w.push(format!(
            "{} of {} estimator exits ({:.0}%) had a throughput or radiance beyond what the object \
             can return and were clamped: the estimator is undertrained or was not made for this \
             object; the image is probably too bright or too dark there. Train longer, or check \
             it with `nppp info FILE`",
            st.repairs.clamped,
            st.entries,
            100.0 * share(u64::from(st.repairs.clamped))
        ));
    }
    let bad = u64::from(st.repairs.degenerate) + u64::from(st.repairs.inward);
    if share(bad) > SUSPICIOUS_REPAIR_SHARE {
        w.push(format!(
            "{bad} of {} estimator exits ({:.0}%) were degenerate or pointed inward and were \
             repaired: the decoder is poorly trained",
            st.entries,
            100.0 * share(bad)
        ));
    }
    if share(u64::from(st.repairs.vertices)) > SUSPICIOUS_REPAIR_SHARE {
        w.push(format!(
            "{} of {} picked vertices ({:.0}%) were outside the object's sphere, degenerate or \
             beyond the throughput the object can return, and were repaired: the vertex head is \
             poorly trained or was not made for this object; the light at its vertices is \
             probably wrong. Train longer, or render with --entry-nee off",
            st.repairs.vertices,
            st.entries,
            100.0 * share(u64::from(st.repairs.vertices))
        ));
    }
    w
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn warnings_follow_the_repair_share() {
        let mut st = nppp_render::estimator::EstimatorStats {
            entries: 25_551,
            ..Default::default()
        };
        assert!(estimator_warnings(&st).is_empty());
        st.repairs.clamped = 100;
        assert!(estimator_warnings(&st).is_empty(), "0.4% is normal");
        st.repairs.clamped = 21_736;
        let w = estimator_warnings(&st);
        assert_eq!(w.len(), 1);
        assert!(
            w[0].contains("85%") && w[0].contains("Train longer"),
            "{}",
            w[0]
        );
        st.repairs.inward = 5_000;
        assert_eq!(estimator_warnings(&st).len(), 2);
        st.repairs.vertices = 150;
        assert_eq!(
            estimator_warnings(&st).len(),
            2,
            "0.6% of vertices is normal"
        );
        st.repairs.vertices = 25_000;
        let w = estimator_warnings(&st);
        assert!(
            w.len() == 3 && w[2].contains("picked vertices (98%)"),
            "{w:?}"
        );
        st.entries = 0;
        assert!(estimator_warnings(&st).is_empty());
        // Rays turned away and none let in: the objects vanished.
        st.mask_skips = 999;
        assert!(
            estimator_warnings(&st).is_empty(),
            "a few misses say nothing"
        );
        st.mask_skips = 41_300;
        let w = estimator_warnings(&st);
        assert!(
            w.len() == 1 && w[0].contains("41300 rays") && w[0].contains("oracle"),
            "{w:?}"
        );
    }
}
