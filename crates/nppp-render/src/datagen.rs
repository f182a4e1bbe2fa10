//! Training data for one estimator: input rays drawn uniformly in the 4D
//! sphere-pair parameterization, each with its mask label and, for hits, k
//! exits traced through the object alone by [`ObjectTracer`] (the renderer's
//! own BSDF sampling, so the estimator learns exactly what the renderer
//! would have computed).
//!
//! Every random number comes from a stream keyed by (seed, ray index,
//! sample): the input ray from sample 0, exit j from sample 1 + j. Rays are
//! traced in parallel in batches and written in ray order, so the file is
//! byte-identical at any thread count, and one exit can be re-traced alone
//! when a test or a bug report needs it.
//!
//! For an object with a non-delta surface each exit also carries the vertex
//! of its walk picked for next-event estimation ([`PickedVertex`]), drawn
//! after the walk from the same stream, so the exits are the same with or
//! without it.

use crate::accel::Blas;
use crate::estimator::pick_skipped;
use crate::medium::Medium;
use crate::object_walk::{ObjectTracer, Walk, WalkVertex};
use crate::surface::SurfaceKind;
use glam::Vec3;
use nppp_estimator::dataset::MAX_K;
use nppp_estimator::{
    DatasetError, DatasetHeader, DatasetSummary, DatasetWriter, Exit, PickedVertex, RayRecord,
    WriterOptions,
};
use nppp_geom::sphere_pair::unit_sphere_chord;
use nppp_geom::{BoundingSphere, Ray, SampleRng, SpherePair};
use nppp_scene::{Material, Mesh, Scene, material_content_hash, mesh_content_hash};
use rayon::prelude::*;
use std::ops::Range;
use std::path::Path;
use std::time::Instant;
use thiserror::Error;

/// The renderer adds an exit's bounce count to its path and ends paths past
/// M, so for any M up to the cap a capped (zero-throughput) exit gives the
/// same image as the real continuation would: the cap only bounds the cost
/// of light trapped inside (a faceted glass ball traps ~0.5% of its exits
/// past 64 bounces by total internal reflection; see the glass test).
pub const DEFAULT_MAX_INTERNAL_BOUNCES: u32 = 64;

/// The cap for translucent objects: a dense, high-albedo medium scatters
/// hundreds of times before light leaves it.
pub const DEFAULT_MAX_INTERNAL_BOUNCES_MEDIUM: u32 = 2048;

/// `nppp gen`'s internal bounce cap for a material when none is given.
pub fn default_max_internal_bounces(m: &Material) -> u32 {
    match m {
        Material::Translucent { .. } => DEFAULT_MAX_INTERNAL_BOUNCES_MEDIUM,
        _ => DEFAULT_MAX_INTERNAL_BOUNCES,
    }
}

pub use nppp_estimator::SPHERE_MARGIN;

/// Exits traced per batch: large enough that every thread of a big machine
/// has work between two writes, small enough that two batches in flight
/// (one traced, one written) stay in the tens of megabytes.
const BATCH_EXITS: u64 = 1 << 18;
const MAX_BATCH_RAYS: u64 = 1 << 14;
/// Exits of one ray traced as one parallel task: big enough to amortize the
/// task, small enough that a few rays with large k still spread over all threads.
const EXITS_PER_TASK: usize = 32;

#[derive(Debug, Error)]
pub enum GenError {
    #[error("mesh \"{0}\" has no triangles: there is nothing to learn")]
    EmptyMesh(String),
    #[error(
        "scene {scene}: instance {index} does not exist (the scene has {count} instances, numbered from 0)"
    )]
    NoSuchInstance {
        scene: String,
        index: usize,
        count: usize,
    },
    #[error(
        "material \"{0}\" is an emitter: it reflects nothing, so a path that reaches it ends \
         there and there is nothing for an estimator to learn (the renderer samples a lamp's \
         light directly and leaves an estimator on it unused)"
    )]
    Emitter(String),
    #[error("{0}")]
    Config(String),
    #[error(transparent)]
    Dataset(#[from] DatasetError),
}

/// One (mesh, material) prepared for tracing: the BLAS, normals and the
/// bounding sphere, plus the names and content hashes the dataset header
/// carries so that a baked estimator can be bound to exactly this object.
pub struct GenObject {
    pub mesh_name: String,
    pub mesh_hash: u64,
    pub material_name: String,
    pub material: Material,
    pub material_hash: u64,
    pub sphere: BoundingSphere,
    pub blas: Blas,
    /// Unit mesh-space geometric normal per triangle, computed as the
    /// renderer computes them so that both see the same surface.
    pub geo_normals: Vec<Vec3>,
    pub shading_normals: Option<Vec<[Vec3; 3]>>,
    pub triangles: usize,
}

impl GenObject {
    /// Prepares `mesh` in its own (mesh) space: the estimator is attached to
    /// instances later, each with its own transform.
    pub fn new(
        mesh_name: &str,
        mesh: &Mesh,
        material_name: &str,
        material: Material,
    ) -> Result<Self, GenError> {
        if mesh.triangles.is_empty() {
            return Err(GenError::EmptyMesh(mesh_name.to_string()));
        }
        if matches!(material, Material::Emitter { .. }) {
            return Err(GenError::Emitter(material_name.to_string()));
        }
        let geo_normals = mesh
            .triangles
            .iter()
            .map(|t| {
                let p = |k: usize| mesh.positions[t[k] as usize];
                nppp_geom::unit_normal((p(1) - p(0)).cross(p(2) - p(0)))
            })
            .collect();
        Ok(Self {
            mesh_name: mesh_name.to_string(),
            mesh_hash: mesh_content_hash(mesh),
            material_name: material_name.to_string(),
            material,
            material_hash: material_content_hash(&material),
            sphere: BoundingSphere::around(&mesh.positions, SPHERE_MARGIN),
            blas: Blas::build(mesh),
            geo_normals,
            shading_normals: mesh.shading_normals.clone(),
            triangles: mesh.triangles.len(),
        })
    }

    /// The mesh and material of instance `index` of a loaded scene, without
    /// the instance's transform.
    pub fn from_scene_instance(scene: &Scene, index: usize) -> Result<Self, GenError> {
        let inst = scene
            .instances
            .get(index)
            .ok_or_else(|| GenError::NoSuchInstance {
                scene: scene.path.display().to_string(),
                index,
                count: scene.instances.len(),
            })?;
        Self::new(
            &scene.mesh_names[inst.mesh],
            &scene.meshes[inst.mesh],
            &scene.material_names[inst.material],
            scene.materials[inst.material],
        )
    }

    pub fn tracer(&self, max_internal_bounces: u32) -> ObjectTracer<'_> {
        ObjectTracer {
            blas: &self.blas,
            surface: SurfaceKind::of(&self.material),
            medium: Medium::of(&self.material),
            sphere: self.sphere,
            geo_normals: &self.geo_normals,
            shading_normals: self.shading_normals.as_deref(),
            max_internal_bounces,
        }
    }

    pub fn header(&self, cfg: &GenConfig) -> DatasetHeader {
        DatasetHeader {
            mesh_name: self.mesh_name.clone(),
            mesh_hash: self.mesh_hash,
            material_name: self.material_name.clone(),
            material_hash: self.material_hash,
            material_json: material_json(&self.material),
            sphere: self.sphere,
            k: cfg.k,
            seed: cfg.seed,
            max_internal_bounces: cfg.max_internal_bounces,
            shard: None,
            vertices: SurfaceKind::of(&self.material)
                .light_sampled_bsdf()
                .is_some(),
        }
    }
}

/// The material in the scene format's JSON, so a trainer or a person can
/// see what the data was made for without the scene. f32 `Display` prints
/// the shortest decimal that reads back as the same value.
pub fn material_json(m: &Material) -> String {
    let v = |c: Vec3| format!("[{}, {}, {}]", c.x, c.y, c.z);
    match *m {
        Material::Diffuse { albedo } => {
            format!(r#"{{"type": "diffuse", "albedo": {}}}"#, v(albedo))
        }
        Material::Conductor {
            reflectance,
            roughness,
        } => {
            format!(
                r#"{{"type": "conductor", "reflectance": {}, "roughness": {roughness}}}"#,
                v(reflectance)
            )
        }
        Material::Dielectric { ior } => format!(r#"{{"type": "dielectric", "ior": {ior}}}"#),
        Material::Translucent {
            ior,
            sigma_s,
            sigma_a,
            g,
        } => format!(
            r#"{{"type": "translucent", "ior": {ior}, "sigma_s": {}, "sigma_a": {}, "g": {g}}}"#,
            v(sigma_s),
            v(sigma_a)
        ),
        Material::Emitter { radiance } => {
            format!(r#"{{"type": "emitter", "radiance": {}}}"#, v(radiance))
        }
    }
}

/// How much data to make and how.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct GenConfig {
    pub rays: u64,
    /// Exits per hit ray.
    pub k: u32,
    pub seed: u64,
    pub max_internal_bounces: u32,
}

impl GenConfig {
    pub fn validate(&self) -> Result<(), GenError> {
        let bad = |s: String| Err(GenError::Config(s));
        if self.rays == 0 {
            return bad("rays = 0: at least one input ray is needed".into());
        }
        if self.k == 0 || self.k > MAX_K {
            return bad(format!(
                "k = {}: the exits per hit ray must be 1 to {MAX_K}",
                self.k
            ));
        }
        if self.max_internal_bounces == 0 {
            return bad(
                "max_internal_bounces = 0 would make every hit an absorbed exit; use at least 1"
                    .into(),
            );
        }
        Ok(())
    }
}

/// Input ray `index` under `seed`: (u1, v1, u2, v2) uniform in [0, 1)^4
/// and the unit-frame ray from the entry point to the exit point. A draw
/// whose two points coincide has no direction; it is redrawn from the same
/// stream, so the result is still a pure function of (seed, index).
pub fn input_ray(seed: u64, index: u64) -> (SpherePair, Ray) {
    let mut rng = SampleRng::new(seed, index, 0);
    loop {
        let pair = SpherePair([rng.uniform(), rng.uniform(), rng.uniform(), rng.uniform()]);
        if let Some(ray) = pair.to_ray() {
            return (pair, ray);
        }
    }
}

/// The random stream of exit `j` of ray `index`.
pub fn exit_rng(seed: u64, index: u64, j: u32) -> SampleRng {
    SampleRng::new(seed, index, 1 + u64::from(j))
}

/// One input ray with its label and, for a hit, its k exits (and their
/// picked vertices, for an object with [`SurfaceKind::light_sampled_bsdf`]).
pub fn trace_ray(tracer: &ObjectTracer, seed: u64, index: u64, k: u32) -> RayRecord {
    let (pair, ray) = input_ray(seed, index);
    if !tracer.hits(&ray) {
        return RayRecord {
            pair,
            hit: false,
            exits: Vec::new(),
            vertices: Vec::new(),
        };
    }
    let nee_bsdf = tracer.surface.light_sampled_bsdf();
    let mut walks: Vec<(Exit, Option<PickedVertex>)> = Vec::with_capacity(k as usize);
    (0..k)
        .into_par_iter()
        .with_min_len(EXITS_PER_TASK)
        .map_init(Vec::new, |verts: &mut Vec<WalkVertex>, j| {
            let mut rng = exit_rng(seed, index, j);
            verts.clear();
            let walk = match nee_bsdf {
                None => tracer.walk(&ray, &mut rng),
                Some(_) => tracer.walk_recording(&ray, &mut rng, |v| verts.push(v)),
            };
            let exit = match walk {
                Walk::Exit(e) => e,
                // `walk` starts with the same query as `hits`, so this cannot
                // happen; if it did, the light went straight through.
                Walk::Miss => straight_through(&ray),
            };
            let picked = nee_bsdf.map(|bsdf| {
                let u = rng.uniform();
                let skipped = pick_skipped(verts, bsdf, tracer.max_internal_bounces, u);
                match skipped.nee {
                    Some((v, _)) => PickedVertex {
                        position: tracer.sphere.to_unit_point(v.point),
                        normal: v.ns,
                        wo: v.wo,
                        beta: v.beta,
                        index: v.index,
                    },
                    // No vertex to light (the walk missed): zero throughput.
                    None => PickedVertex {
                        normal: Vec3::Z,
                        wo: Vec3::Z,
                        ..PickedVertex::default()
                    },
                }
            });
            (exit, picked)
        })
        .collect_into_vec(&mut walks);
    let vertices = walks.iter().filter_map(|w| w.1).collect();
    RayRecord {
        pair,
        hit: true,
        exits: walks.into_iter().map(|w| w.0).collect(),
        vertices,
    }
}

fn straight_through(ray: &Ray) -> Exit {
    let t = unit_sphere_chord(ray).map_or(0.0, |c| c.t_out.max(0.0));
    Exit {
        position: ray.at(t).normalize_or(Vec3::Z),
        direction: ray.dir,
        throughput: Vec3::ONE,
        radiance: Vec3::ZERO,
        bounces: 0,
    }
}

/// Rays `range`, traced in parallel on the current rayon pool, in ray order.
pub fn trace_rays(tracer: &ObjectTracer, seed: u64, range: Range<u64>, k: u32) -> Vec<RayRecord> {
    range
        .into_par_iter()
        .map(|i| trace_ray(tracer, seed, i, k))
        .collect()
}

/// Running totals, accumulated in ray order so they are reproducible too.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct GenStats {
    pub rays: u64,
    pub hits: u64,
    pub exits: u64,
    /// Exits with zero throughput (absorbed or over the bounce cap).
    pub zero_exits: u64,
    /// Zero exits that stopped at the internal bounce cap.
    pub capped_exits: u64,
    /// Exits whose throughput or radiance was not finite and was replaced by
    /// zero (a BSDF bug, never expected; the writer would reject them).
    pub repaired_exits: u64,
    pub throughput_sum: [f64; 3],
    pub bounce_sum: u64,
    /// Wall time since generation started.
    pub seconds: f64,
}

impl GenStats {
    pub fn hit_fraction(&self) -> f64 {
        self.hits as f64 / self.rays.max(1) as f64
    }

    /// Mean exit throughput over all exits of hit rays (absorbed ones count as zero).
    pub fn mean_throughput(&self) -> [f64; 3] {
        self.throughput_sum.map(|s| s / self.exits.max(1) as f64)
    }

    pub fn mean_bounces(&self) -> f64 {
        self.bounce_sum as f64 / self.exits.max(1) as f64
    }

    pub fn exits_per_second(&self) -> f64 {
        self.exits as f64 / self.seconds.max(1e-9)
    }

    pub fn rays_per_second(&self) -> f64 {
        self.rays as f64 / self.seconds.max(1e-9)
    }

    /// BVH queries per second made by the walks: each exit costs its
    /// bounces plus one query (the entry hit, then one per scattered ray,
    /// the last of which escapes).
    pub fn bvh_queries_per_second(&self) -> f64 {
        (self.exits + self.bounce_sum + self.rays) as f64 / self.seconds.max(1e-9)
    }

    fn add(&mut self, rec: &mut RayRecord, cap: u32) {
        self.rays += 1;
        self.hits += rec.hit as u64;
        for e in &mut rec.exits {
            if !(e.throughput.is_finite() && e.radiance.is_finite()) {
                self.repaired_exits += 1;
                e.throughput = Vec3::ZERO;
                e.radiance = Vec3::ZERO;
            }
            self.exits += 1;
            if e.throughput == Vec3::ZERO {
                self.zero_exits += 1;
                self.capped_exits += (e.bounces >= cap) as u64;
            }
            for (s, t) in self.throughput_sum.iter_mut().zip(e.throughput.to_array()) {
                *s += f64::from(t);
            }
            self.bounce_sum += u64::from(e.bounces);
        }
    }
}

/// What [`generate`] made.
#[derive(Clone, Debug)]
pub struct GenReport {
    pub stats: GenStats,
    pub summary: DatasetSummary,
}

fn batch_rays(k: u32) -> u64 {
    (BATCH_EXITS / u64::from(k.max(1))).clamp(1, MAX_BATCH_RAYS)
}

/// Traces `cfg.rays` input rays and streams them into the dataset file
/// `out` (written to a temporary file and renamed at the end, so an
/// interrupted run leaves the previous file intact). Tracing of one batch
/// overlaps with compressing and writing the previous one. `progress` sees
/// the totals after every batch.
pub fn generate(
    obj: &GenObject,
    cfg: &GenConfig,
    out: &Path,
    options: WriterOptions,
    progress: &mut (dyn FnMut(&GenStats) + Send),
) -> Result<GenReport, GenError> {
    generate_shard(obj, cfg, None, out, options, progress)
}

/// [`generate`] for the input rays `shard` of the data set `cfg` describes
/// (all of them if `None`): the file is a shard (its header says which
/// rays) that `nppp merge` joins with the others into the file [`generate`]
/// writes. A shard starts at a multiple of `options.chunk_rays`
/// ([`nppp_estimator::shard::shard_rays`] makes such ranges).
pub fn generate_shard(
    obj: &GenObject,
    cfg: &GenConfig,
    shard: Option<Range<u64>>,
    out: &Path,
    options: WriterOptions,
    progress: &mut (dyn FnMut(&GenStats) + Send),
) -> Result<GenReport, GenError> {
    cfg.validate()?;
    let tracer = obj.tracer(cfg.max_internal_bounces);
    let mut header = obj.header(cfg);
    let rays = shard.clone().unwrap_or(0..cfg.rays);
    if let Some(r) = &shard {
        let chunk = u64::from(options.chunk_rays.max(1));
        if !(r.start < r.end && r.end <= cfg.rays && r.start.is_multiple_of(chunk)) {
            return Err(GenError::Config(format!(
                "shard rays {}..{} are not a range of whole {chunk}-ray chunks of 0..{}",
                r.start, r.end, cfg.rays
            )));
        }
        header.shard = Some(nppp_estimator::shard::DatasetShard {
            first_ray: r.start,
            end_ray: r.end,
            rays: cfg.rays,
            chunk_rays: options.chunk_rays,
            compress: options.compress,
        });
    }
    let mut writer = DatasetWriter::create_with(out, header, options)?;
    let t0 = Instant::now();
    let batch = batch_rays(cfg.k);
    let mut stats = GenStats::default();
    let mut write = |records: Vec<RayRecord>, stats: &mut GenStats| -> Result<(), GenError> {
        for mut rec in records {
            stats.add(&mut rec, cfg.max_internal_bounces);
            writer.write(&rec)?;
        }
        stats.seconds = t0.elapsed().as_secs_f64();
        progress(stats);
        Ok(())
    };
    let mut start = rays.start;
    let mut pending: Vec<RayRecord> = Vec::new();
    while start < rays.end {
        let end = (start + batch).min(rays.end);
        let (written, next) = rayon::join(
            || write(std::mem::take(&mut pending), &mut stats),
            || trace_rays(&tracer, cfg.seed, start..end, cfg.k),
        );
        written?;
        pending = next;
        start = end;
    }
    write(pending, &mut stats)?;
    let summary = writer.finish()?;
    stats.seconds = t0.elapsed().as_secs_f64();
    Ok(GenReport { stats, summary })
}

/// Closest-hit throughput of the bare BVH on the generator's own input rays.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BvhMeasurement {
    pub rays: u64,
    pub hits: u64,
    pub seconds: f64,
}

impl BvhMeasurement {
    pub fn rays_per_second(&self) -> f64 {
        self.rays as f64 / self.seconds.max(1e-9)
    }
}

/// Measures how fast the BLAS answers closest-hit queries for `n` random
/// chords of the bounding sphere, on the current rayon pool, for at least
/// `min_seconds` after a warm-up pass. This is the ceiling for data
/// generation: a walk is a chain of such queries plus BSDF sampling.
pub fn measure_bvh(obj: &GenObject, seed: u64, n: usize, min_seconds: f64) -> BvhMeasurement {
    let rays: Vec<(Vec3, Vec3)> = (0..n as u64)
        .into_par_iter()
        .map(|i| {
            let (_, r) = input_ray(seed, i);
            (obj.sphere.from_unit_point(r.origin), r.dir)
        })
        .collect();
    let pass = || -> u64 {
        rays.par_iter()
            .with_min_len(256)
            .filter(|(o, d)| {
                obj.blas
                    .intersect((*o).into(), (*d).into(), 0.0, f32::INFINITY)
                    .is_some()
            })
            .count() as u64
    };
    pass();
    let t0 = Instant::now();
    let mut m = BvhMeasurement {
        rays: 0,
        hits: 0,
        seconds: 0.0,
    };
    while m.rays == 0 || m.seconds < min_seconds {
        m.hits += pass();
        m.rays += n as u64;
        m.seconds = t0.elapsed().as_secs_f64();
    }
    m
}
