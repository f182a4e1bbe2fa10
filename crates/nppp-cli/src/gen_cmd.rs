//! `nppp gen`: training data for one (mesh, material) estimator.
//!
//! The object is named the way users attach estimators (an instance of a
//! scene), or directly by mesh and material for objects that are in no scene
//! yet. Either way the estimator lives in mesh space, so an instance's
//! transform is ignored: one data set serves every instance of the object.

use anyhow::{Context, Result, anyhow, bail, ensure};
use clap::Args;
use indicatif::{ProgressBar, ProgressDrawTarget};
use nppp_estimator::WriterOptions;
use nppp_estimator::dataset::MAX_K;
use nppp_render::datagen::{
    GenConfig, GenObject, GenStats, default_max_internal_bounces, generate_shard, measure_bvh,
};
use nppp_scene::procedural::Procedural;
use nppp_scene::{Material, Mesh};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// The thesis' data set, for the size projection printed after a run.
const THESIS_RAYS: u64 = 200_000;
const THESIS_K: u64 = 512;

/// Material presets for `--material NAME`: the scene format's examples.
const PRESETS: &[(&str, &str)] = &[
    (
        "white",
        r#"{"type": "diffuse", "albedo": [0.73, 0.73, 0.73]}"#,
    ),
    (
        "gold",
        r#"{"type": "conductor", "reflectance": [1.0, 0.78, 0.34], "roughness": 0.2}"#,
    ),
    (
        "mirror",
        r#"{"type": "conductor", "reflectance": [1.0, 1.0, 1.0], "roughness": 0.0}"#,
    ),
    ("glass", r#"{"type": "dielectric", "ior": 1.5}"#),
];

#[derive(Args, Debug)]
pub struct GenArgs {
    /// Take the object from this scene file (with --instance): the mesh and
    /// material of one instance, without its transform.
    #[arg(long, requires = "instance", conflicts_with_all = ["mesh", "material"])]
    pub scene: Option<PathBuf>,
    /// Instance of --scene, counted from 0 in the order of its "instances" list.
    #[arg(long, requires = "scene")]
    pub instance: Option<usize>,
    /// The mesh, instead of --scene: an OBJ file; `builtin` (the project's
    /// torus knot, as in data/scenes/cornell-box.json);
    /// `procedural:torus_knot|displaced_sphere|menger_sponge` (standard
    /// parameters); or a scene-format mesh object in JSON, e.g.
    /// '{"procedural": {"type": "menger_sponge", "level": 2}}'.
    #[arg(long, requires = "material")]
    pub mesh: Option<String>,
    /// Shade an OBJ --mesh with its vertex normals (the scene format's "smooth": true).
    #[arg(long, requires = "mesh", conflicts_with = "scene")]
    pub smooth: bool,
    /// The material for --mesh: scene-format JSON, e.g.
    /// '{"type": "diffuse", "albedo": [0.8, 0.6, 0.35]}', or a preset: white, gold, mirror, glass.
    #[arg(long, requires = "mesh")]
    pub material: Option<String>,
    /// Input rays, uniform in the 4D sphere-pair parameterization (the
    /// default is the recipe of the committed estimators).
    #[arg(long, default_value_t = nppp_estimator::recipe::DEFAULT_RAYS, value_parser = crate::at_least_one::<u64>)]
    pub rays: u64,
    /// Exits traced per input ray that hits the object (`nppp train` uses
    /// this many per step by default).
    #[arg(long, default_value_t = nppp_estimator::recipe::DEFAULT_K, value_parser = crate::at_least_one::<u32>)]
    pub k: u32,
    /// Seed of every random stream: the file is a function of the object,
    /// the flags and this seed, whatever the thread count.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Paths still inside after this many scattering events are recorded as
    /// zero-throughput exits [default: 64; 2048 for translucent objects,
    /// whose media scatter hundreds of times].
    #[arg(long, value_parser = crate::at_least_one::<u32>)]
    pub max_internal_bounces: Option<u32>,
    /// Output data file (written to a temporary file, renamed when complete).
    #[arg(long)]
    pub out: PathBuf,
    /// Replace --out if it exists. Without it gen refuses an existing file:
    /// training data can be hours of tracing, and a model's bake reads its
    /// held-out rays from it.
    #[arg(long)]
    pub overwrite: bool,
    /// Trace only shard I of K (I from 0) of the --rays input rays, in whole
    /// chunks of 4096 rays: a file of its own that `nppp merge` joins with the
    /// other shards into the file one run writes, byte for byte (tools/slurm
    /// runs it as a job array). A shard is also a valid data set of its rays.
    #[arg(long, value_parser = crate::merge_cmd::parse_shard)]
    pub shard: Option<crate::merge_cmd::Shard>,
    /// Also measure the bare BVH's closest-hit rate on this mesh and compare.
    #[arg(long)]
    pub measure_bvh: bool,
    /// Store chunks uncompressed (faster to write, several times larger).
    #[arg(long)]
    pub no_compress: bool,
    /// Hide the progress bar.
    #[arg(long)]
    pub quiet: bool,
}

/// The most exits (`--rays` x `--k`, hits or not) one run may plan: 2^38,
/// about 2.7 TB at the 10 bytes an exit takes compressed; 4,000 times the
/// default recipe. More cannot be written anywhere, and was accepted and
/// traced until the disk filled.
const MAX_PLANNED_EXITS: u64 = 1 << 38;

/// The fewest input rays a run projects the full recipe's size and time
/// from.
const MIN_RAYS_TO_PROJECT: u64 = 1000;

pub fn run(a: &GenArgs) -> Result<()> {
    ensure!(
        (1..=MAX_K).contains(&a.k),
        "--k must be 1 to {MAX_K} (got {})",
        a.k
    );
    ensure!(
        a.max_internal_bounces
            .is_none_or(|m| m <= nppp_render::estimator::ORACLE_MAX_INTERNAL_BOUNCES),
        "--max-internal-bounces must be at most {} (the oracle's cap; got {}): a walk \
         still inside after that many scattering events is recorded as absorbed anyway",
        nppp_render::estimator::ORACLE_MAX_INTERNAL_BOUNCES,
        a.max_internal_bounces.unwrap_or(0)
    );
    ensure!(
        a.rays.saturating_mul(a.k as u64) <= MAX_PLANNED_EXITS,
        "--rays {} x --k {} plans {:.3e} exits, more than any disk holds (about 10 bytes each); \
         at most {MAX_PLANNED_EXITS:.3e} (the default recipe plans 6.4e7)",
        a.rays,
        a.k,
        a.rays as f64 * a.k as f64
    );
    ensure!(
        !a.out.is_dir(),
        "--out {}: is a directory; give a file name",
        a.out.display()
    );
    ensure!(
        crate::has_extension(&a.out, "nppd"),
        "--out {}: training data is named *.nppd (gen never writes under another extension, so \
         a slip cannot overwrite a scene, a mesh or an estimator)",
        a.out.display()
    );
    nppp_files::check_writable(&a.out).map_err(|e| anyhow!("--out {}: {e}", a.out.display()))?;
    let shard_rays = match a.shard {
        Some(sh) => Some(
            nppp_estimator::shard::shard_rays(
                sh.index,
                sh.count,
                a.rays,
                WriterOptions::default().chunk_rays,
            )
            .map_err(|e| anyhow!("--shard {sh}: {e}"))?,
        ),
        None => None,
    };
    let t0 = Instant::now();
    let (obj, inputs) = load_object(a)?;
    let build = t0.elapsed().as_secs_f64();
    nppp_files::ensure_not_input("--out", &a.out, &inputs).map_err(anyhow::Error::msg)?;
    // After that check, whose message says more when --out is an input.
    crate::keep_existing_data(&a.out, a.overwrite, "gen")?;
    if let Some(dir) = a.out.parent().filter(|d| !d.as_os_str().is_empty()) {
        nppp_files::create_output_dir(dir)
            .with_context(|| format!("--out {}: cannot create its folder", a.out.display()))?;
    }
    let max_internal_bounces = a
        .max_internal_bounces
        .unwrap_or_else(|| default_max_internal_bounces(&obj.material));
    let cfg = GenConfig {
        rays: a.rays,
        k: a.k,
        seed: a.seed,
        max_internal_bounces,
    };
    let threads = rayon::current_num_threads();
    let s = obj.sphere;
    nppp_files::note!(
        "gen: mesh \"{}\" ({} triangles, {:016x}), material \"{}\" ({:016x}), BVH built in {build:.2}s",
        obj.mesh_name,
        obj.triangles,
        obj.mesh_hash,
        obj.material_name,
        obj.material_hash
    );
    nppp_files::note!(
        "gen: sphere centre [{} {} {}] radius {}; {} rays x k = {}, seed {}, cap {} bounces, {threads} threads",
        s.center.x,
        s.center.y,
        s.center.z,
        s.radius,
        a.rays,
        a.k,
        a.seed,
        max_internal_bounces
    );
    if let (Some(sh), Some(r)) = (a.shard, &shard_rays) {
        nppp_files::note!(
            "gen: shard {sh}: rays {}..{} (merge the shards with `nppp merge`)",
            r.start,
            r.end
        );
    }

    let bar = progress_bar(
        shard_rays.as_ref().map_or(a.rays, |r| r.end - r.start),
        a.quiet,
    );
    let mut progress = |st: &GenStats| {
        bar.set_position(st.rays);
        bar.set_message(format!(
            "{}, {:.1}% hit",
            nppp_files::format_rate(st.exits_per_second(), "exits"),
            100.0 * st.hit_fraction()
        ));
    };
    // Checked free above unless --overwrite; a file that appears there while
    // the rays are traced (another run finishing first) is not replaced.
    let options = WriterOptions {
        compress: !a.no_compress,
        replace: a.overwrite,
        ..WriterOptions::default()
    };
    let cpu0 = process_cpu_seconds();
    let report = generate_shard(&obj, &cfg, shard_rays, &a.out, options, &mut progress);
    let gen_cpu = cpu_since(cpu0);
    bar.finish_and_clear();
    let report = report?;
    let (st, sum) = (&report.stats, &report.summary);
    let t = st.mean_throughput();
    crate::print_summary(&sum.path.display())?;
    crate::print_summary(&format_args!(
        "  rays        {} ({:.1}% hit the mesh)",
        st.rays,
        100.0 * st.hit_fraction()
    ))?;
    crate::print_summary(&format_args!(
        "  exits       {} ({} zero-throughput, {} of them at the bounce cap), mean bounces {:.3}",
        st.exits,
        st.zero_exits,
        st.capped_exits,
        st.mean_bounces()
    ))?;
    crate::print_summary(&format_args!(
        "  mean exit throughput [{:.4} {:.4} {:.4}]",
        t[0], t[1], t[2]
    ))?;
    crate::print_summary(&format_args!(
        "  vertices    {}",
        if obj.header(&cfg).vertices {
            "each exit carries its walk's picked vertex (next-event estimation through the estimator: `nppp train` adds a vertex head)"
        } else {
            "none (a smooth dielectric or a medium takes no light sample inside)"
        }
    ))?;
    let rate = nppp_files::format_rate;
    crate::print_summary(&format_args!(
        "  time        {:.2}s: {}, {}, {} in the walks ({threads} threads)",
        st.seconds,
        rate(st.exits_per_second(), "exits"),
        rate(st.rays_per_second(), "rays"),
        rate(st.bvh_queries_per_second(), "BVH queries")
    ))?;
    // A run shorter than the clock's tick has no CPU rate to speak of.
    if let Some(cpu) = gen_cpu.filter(|c| *c > 0.0) {
        crate::print_summary(&format_args!(
            "  CPU time    {cpu:.2}s: {} per CPU-second ({:.2} of {threads} threads busy on average)",
            rate(st.exits as f64 / cpu, "exits").trim_end_matches("/s"),
            cpu / st.seconds.max(1e-9)
        ))?;
    }
    crate::print_summary(&format_args!(
        "  file        {} in {} chunks, {:.2} bytes/exit ({:.2} before compression)",
        nppp_files::format_bytes(sum.file_bytes),
        sum.chunks,
        sum.bytes_per_exit(),
        sum.raw_bytes as f64 / st.exits.max(1) as f64
    ))?;
    if st.exits > 0 && st.zero_exits == st.exits {
        nppp_files::note!(
            "warning: every one of the {} exits has zero throughput: the material absorbs all \
             light. An estimator trained on this data renders the object black; pick a \
             reflecting instance",
            st.exits
        );
    } else if st.exits > 0 && st.capped_exits as f64 > 0.05 * st.exits as f64 {
        nppp_files::note!(
            "warning: {:.0}% of the exits stopped at the cap of {} internal bounces and count as \
             absorbed: raise --max-internal-bounces",
            100.0 * st.capped_exits as f64 / st.exits as f64,
            max_internal_bounces
        );
    }
    if st.repaired_exits > 0 {
        nppp_files::note!(
            "warning: {} exits had a non-finite throughput or radiance and were stored as zero (a BSDF bug)",
            st.repaired_exits
        );
    }
    // From a few hundred rays the hit fraction and the rate are noise (a
    // one-ray shard projected 11,459 minutes): no projection then.
    if st.rays < MIN_RAYS_TO_PROJECT {
        crate::print_summary(&format_args!(
            "  projection  none: {} rays are too few to project from (at least {MIN_RAYS_TO_PROJECT})",
            st.rays
        ))?;
    } else if st.exits > 0 {
        let exits = THESIS_RAYS as f64 * st.hit_fraction() * THESIS_K as f64;
        crate::print_summary(&format_args!(
            "  projection  {THESIS_RAYS} rays x k = {THESIS_K}: {:.1} M exits, {} and {:.1} min at this rate",
            exits / 1e6,
            nppp_files::format_bytes((exits * sum.bytes_per_exit()) as u64),
            exits / st.exits_per_second() / 60.0
        ))?;
    }
    if a.measure_bvh {
        let cpu0 = process_cpu_seconds();
        let m = measure_bvh(&obj, a.seed ^ 0x5eed_b7a5, 1 << 18, 2.0);
        let bvh_cpu = cpu_since(cpu0);
        let queries = (st.exits + st.bounce_sum + st.rays) as f64;
        crate::print_summary(&format_args!(
            "  bare BVH    {:.2} M closest-hit rays/s on random chords ({:.1}% hit, {threads} threads)",
            m.rays_per_second() / 1e6,
            100.0 * m.hits as f64 / m.rays.max(1) as f64
        ))?;
        // Per CPU-second when the OS tells us, so that other load on the
        // machine during one of the two phases does not skew the ratio.
        let (walk_rate, bvh_rate, basis) = match (gen_cpu, bvh_cpu) {
            (Some(g), Some(b)) if g > 0.0 && b > 0.0 => {
                (queries / g, m.rays as f64 / b, "per CPU-second")
            }
            _ => (
                st.bvh_queries_per_second(),
                m.rays_per_second(),
                "per second",
            ),
        };
        crate::print_summary(&format_args!(
            "  ratio       walks: {:.2} M queries {basis} = {:.0}% of the bare BVH's {:.2} M ({:.2} queries per exit: entry hit + bounces)",
            walk_rate / 1e6,
            100.0 * walk_rate / bvh_rate,
            bvh_rate / 1e6,
            queries / st.exits.max(1) as f64
        ))?;
    }
    Ok(())
}

/// User + system CPU time of this process (Linux `/proc`; `None` elsewhere).
fn process_cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the command name, which is in parentheses and may contain spaces.
    let rest = stat.get(stat.rfind(')')? + 1..)?;
    let f: Vec<&str> = rest.split_whitespace().collect();
    // utime and stime are fields 14 and 15 of the file, in USER_HZ (100 on Linux) ticks.
    let ticks = f.get(11)?.parse::<f64>().ok()? + f.get(12)?.parse::<f64>().ok()?;
    Some(ticks / 100.0)
}

fn cpu_since(start: Option<f64>) -> Option<f64> {
    Some(process_cpu_seconds()? - start?)
}

fn progress_bar(rays: u64, quiet: bool) -> ProgressBar {
    if quiet {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::with_draw_target(Some(rays), ProgressDrawTarget::stderr_with_hz(4));
    bar.set_style(nppp_files::progress_style(
        "{spinner} [{elapsed_precise}] {wide_bar} {pos}/{len} rays, {msg}, ETA {eta}",
        "rays",
    ));
    bar.enable_steady_tick(Duration::from_millis(250));
    bar
}

/// Refuses an object whose mesh and BVH would not fit in the memory
/// available (as `nppp render` does, at its bytes a triangle), before they
/// are built: a message instead of an allocation failure.
fn check_memory(triangles: u64, what: &str) -> Result<()> {
    let per = nppp_render::scene_data::RENDER_BYTES_PER_TRIANGLE;
    let need = triangles.saturating_mul(per);
    if let Some(available) = nppp_files::available_memory()
        && need > available
    {
        bail!(
            "{what}: its mesh has {triangles} triangles; tracing it takes about {} (about {per} \
             bytes a triangle: the mesh and its BVH), more than the {} of memory available: use \
             a coarser mesh",
            nppp_files::format_bytes(need),
            nppp_files::format_bytes(available)
        );
    }
    Ok(())
}

/// The object named by the flags, and the files it was read from (which
/// `--out` must not name).
fn load_object(a: &GenArgs) -> Result<(GenObject, Vec<(String, PathBuf)>)> {
    // clap's `requires` does not hold here when --mesh is given (it
    // conflicts with --scene): the instance was ignored, silently.
    if let (None, Some(i)) = (&a.scene, a.instance) {
        bail!(
            "--instance {i} names an instance of --scene, and no --scene was given: give \
             --scene FILE --instance N, or --mesh and --material without --instance"
        );
    }
    if let Some(path) = &a.scene {
        let scene = nppp_scene::load_scene(path)?;
        let index = a.instance.context("--scene needs --instance N")?;
        if let Some(inst) = scene.instances.get(index) {
            let triangles = scene.meshes[inst.mesh].triangles.len() as u64;
            check_memory(triangles, &format!("--instance {index}"))?;
        }
        return Ok((
            GenObject::from_scene_instance(&scene, index)?,
            scene.input_files(),
        ));
    }
    let mut inputs = Vec::new();
    if let Some(m) = &a.mesh
        && Path::new(m).is_file()
    {
        inputs.push(("the --mesh OBJ file".to_string(), PathBuf::from(m)));
    }
    Ok((load_flag_object(a)?, inputs))
}

/// The object named by --mesh and --material, each validated by the scene
/// loader exactly as in a scene file (`nppp_scene::parse_material`,
/// `parse_mesh`), errors naming the flag.
fn load_flag_object(a: &GenArgs) -> Result<GenObject> {
    let (Some(mesh_arg), Some(material_arg)) = (&a.mesh, &a.material) else {
        bail!("name the object with --scene FILE --instance N, or with --mesh and --material");
    };
    let (material_name, material_json) = material_spec(material_arg)?;
    let material = nppp_scene::parse_material(&material_json, "--material")?;
    let procedural = procedural_spec(mesh_arg)?;
    // Only an OBJ file has vertex normals to shade with.
    ensure!(
        !a.smooth || (procedural.is_none() && !mesh_arg.trim_start().starts_with('{')),
        "--smooth: --mesh {mesh_arg} has no vertex normals to shade with (it applies to an OBJ file)"
    );
    let (mesh_name, mesh) = match procedural {
        Some(p) => {
            check_memory(p.triangle_count(), &format!("--mesh {mesh_arg}"))?;
            let m = p.build().with_context(|| format!("--mesh {mesh_arg}"))?;
            (
                p.name(),
                Mesh {
                    positions: m.positions,
                    triangles: m.triangles,
                    shading_normals: None,
                },
            )
        }
        None => {
            let (name, json) = mesh_spec(mesh_arg, a.smooth)?;
            // The loader's memory check at what tracing the mesh holds: for
            // a shape before it is built, for an OBJ as it is read.
            let traced = nppp_render::scene_data::RENDER_BYTES_PER_TRIANGLE;
            let mesh = nppp_scene::parse_mesh_charged(&json, "--mesh", traced)?;
            (name, mesh)
        }
    };
    // The scene contract's rule for translucent objects, as the loader
    // applies it to a scene's instances.
    if matches!(material, Material::Translucent { .. })
        && let Some(edge) = nppp_scene::open_edge(&mesh)
    {
        bail!(
            "--mesh {mesh_arg}: is used with the translucent --material but is not a closed mesh: \
             {edge}; a medium needs a watertight, consistently oriented boundary"
        );
    }
    // The scene loader's size rules, in the mesh's own units (gen walks
    // the object there).
    let free_path = material.densest_sigma_t().map(|s| 1.0 / s);
    if let Some(why) = nppp_scene::mesh_units_problem(&mesh, free_path) {
        bail!("--mesh {mesh_arg}: {why}");
    }
    Ok(GenObject::new(&mesh_name, &mesh, &material_name, material)?)
}

/// `builtin` and `procedural:TYPE`: the project's standard objects.
fn procedural_spec(s: &str) -> Result<Option<Procedural>> {
    // `builtin` is the object of the default scene, data/scenes/cornell-box.json.
    let ty = match s {
        "builtin" => "torus_knot",
        _ => match s.strip_prefix("procedural:") {
            Some(ty) => ty,
            None => return Ok(None),
        },
    };
    let found = Procedural::defaults().into_iter().find(|p| {
        matches!(
            (ty, p),
            ("displaced_sphere", Procedural::DisplacedSphere { .. })
                | ("torus_knot", Procedural::TorusKnot { .. })
                | ("menger_sponge", Procedural::MengerSponge { .. })
        )
    });
    match found {
        Some(p) => Ok(Some(p)),
        None => bail!(
            "--mesh {s}: unknown procedural type \"{ty}\" (known: torus_knot, displaced_sphere, menger_sponge)"
        ),
    }
}

/// An OBJ path or a JSON mesh object, as the scene-format mesh JSON and a name.
fn mesh_spec(s: &str, smooth: bool) -> Result<(String, String)> {
    if s.trim_start().starts_with('{') {
        let v: serde_json::Value =
            serde_json::from_str(s).with_context(|| format!("--mesh: not valid JSON: {s}"))?;
        ensure!(
            v.is_object(),
            "--mesh: expected a JSON object such as {{\"icosphere\": {{...}}}}, got {s}"
        );
        // The text as given, not `v` re-serialized: serde_json keeps the
        // last of duplicated keys, which the scene loader refuses.
        return Ok(("inline-mesh".to_string(), s.to_string()));
    }
    let path = Path::new(s);
    ensure!(
        path.exists(),
        "--mesh {s}: no such file (expected an OBJ file, `builtin`, `procedural:TYPE` or a JSON mesh object)"
    );
    nppp_files::check_regular(path).with_context(|| format!("--mesh {s}"))?;
    let abs = std::path::absolute(path).with_context(|| format!("--mesh {s}"))?;
    let name = path
        .file_stem()
        .map_or_else(|| "mesh".to_string(), |n| n.to_string_lossy().into_owned());
    let json = serde_json::json!({ "obj": abs.to_string_lossy(), "smooth": smooth });
    Ok((name, json.to_string()))
}

/// A preset name or material JSON, as a name and the scene-format JSON.
fn material_spec(s: &str) -> Result<(String, String)> {
    if let Some((name, json)) = PRESETS.iter().find(|(n, _)| *n == s) {
        return Ok((name.to_string(), json.to_string()));
    }
    if !s.trim_start().starts_with('{') {
        let names: Vec<&str> = PRESETS.iter().map(|(n, _)| *n).collect();
        bail!(
            "--material {s}: not a preset ({}) nor a JSON object such as {{\"type\": \"diffuse\", \"albedo\": [0.8, 0.6, 0.35]}}",
            names.join(", ")
        );
    }
    let v: serde_json::Value =
        serde_json::from_str(s).with_context(|| format!("--material: not valid JSON: {s}"))?;
    let ty = v
        .get("type")
        .and_then(|t| t.as_str())
        .unwrap_or("material")
        .to_string();
    ensure!(v.is_object(), "--material: expected a JSON object, got {s}");
    // The text as given (see `mesh_spec`).
    Ok((ty, s.to_string()))
}
