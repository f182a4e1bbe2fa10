//! Answering a wavefront step's estimator entries in batches: one decoder
//! call per neural estimator ([`nppp_estimator::EstimatorSampler::sample_batch`]),
//! one object walk per oracle entry, a free exit per cost-floor or
//! free-exits entry, and
//! the skipped vertices next-event estimation through the estimator uses.
//! The integrator gathers the entries ([`crate::estimator::Estimators::intersect`])
//! and continues each path from its exit.

use crate::estimator::{
    EntryNee, EstimatorEntry, EstimatorModel, EstimatorStats, Estimators, LatentLookup,
    SkippedVertices, first_vertex_skipped, network_skipped, pick_skipped,
};
use crate::object_walk::{Walk, WalkVertex};
use crate::path::PathState;
use crate::scene_data::RenderScene;
use crate::surface::SurfaceKind;
use glam::Vec3;
use nppp_estimator::{Corners, Exit, ExitBatch};

/// Reusable buffers for answering a wavefront step's entries in batches.
#[derive(Default)]
pub struct EntryBatch {
    /// (path index, entry)
    pub entries: Vec<(usize, EstimatorEntry)>,
    rows: Vec<usize>,
    /// Per row of a neural batch, where its latent lookup reads.
    corners: Vec<Corners>,
    decode: ExitBatch,
    pub exits: Vec<Exit>,
    /// Per entry, parallel to `exits`: the vertices the renderer still uses.
    pub skipped: Vec<SkippedVertices>,
    walk_vertices: Vec<WalkVertex>,
    /// Per row of a batch with a vertex head: the grid cell, then the
    /// site of the triangle, its vertex meets the real surface at
    /// ([`crate::surface_snap`]).
    snap_sites: Vec<Option<u32>>,
}

impl EntryBatch {
    /// Answers every gathered entry: one decoder call per neural estimator,
    /// one object walk per oracle entry, each drawing from its own path's stream.
    pub fn answer(
        &mut self,
        ests: &Estimators,
        scene: &RenderScene,
        paths: &mut [PathState],
        max_bounces: u32,
        stats: &mut EstimatorStats,
    ) {
        self.exits.clear();
        self.exits.resize(self.entries.len(), Exit::default());
        self.skipped.clear();
        self.skipped
            .resize(self.entries.len(), SkippedVertices::default());
        stats.entries += self.entries.len() as u64;
        for (ei, est) in ests.list.iter().enumerate() {
            self.rows.clear();
            self.rows.extend(
                self.entries
                    .iter()
                    .enumerate()
                    .filter(|(_, (_, e))| {
                        ests.per_instance()[e.instance as usize] == Some(ei as u32)
                    })
                    .map(|(i, _)| i),
            );
            if self.rows.is_empty() {
                continue;
            }
            match &est.model {
                EstimatorModel::Neural { sampler } => {
                    let (entries, rows) = (&self.entries, &self.rows);
                    let lookup = ests.latent_lookup;
                    // Every row's latent reads start before any is blended.
                    self.corners.clear();
                    if lookup == LatentLookup::Interpolate {
                        self.corners.extend(
                            rows.iter()
                                .map(|&i| sampler.latent_corners(&entries[i].1.pair)),
                        );
                    }
                    let corners = &self.corners;
                    let fill = |k: usize, z: &mut [f32], noise: &mut [f32]| {
                        let (path, entry) = &entries[rows[k]];
                        let rng = &mut paths[*path].rng;
                        match lookup {
                            LatentLookup::Interpolate => sampler.latent_at(&corners[k], z),
                            LatentLookup::Stochastic => {
                                let u =
                                    [rng.uniform(), rng.uniform(), rng.uniform(), rng.uniform()];
                                sampler.latent_stochastic(&entry.pair, u, z);
                            }
                        }
                        rng.fill_normals(noise);
                    };
                    let decoded = sampler.sample_batch(
                        &mut self.decode,
                        rows.len(),
                        fill,
                        &mut stats.repairs,
                    );
                    stats.decoder_fallbacks += u64::from(decoded.fell_back);
                    stats.decoder_batches += 1;
                    stats.count_decoder_rows(
                        rows.len(),
                        sampler.decoder_multiply_adds(),
                        sampler.noise_dim(),
                    );
                    for (&i, exit) in rows.iter().zip(decoded.exits) {
                        self.exits[i] = *exit;
                    }
                    // Picked-vertex NEE: the vertex head on the same rows
                    // (their latents and their exits' noise).
                    if let (true, SurfaceKind::Scatter(bsdf)) =
                        (est.entry_nee.is_picked(), est.surface)
                        && let Some(verts) = sampler
                            .sample_vertices_from_exit_noise(&mut self.decode, &mut stats.repairs)
                    {
                        let macs = sampler.vertex_multiply_adds().unwrap_or(0);
                        stats.count_decoder_rows(verts.len(), macs, 0);
                        let snap = est.surface_snap.as_ref();
                        // Where each vertex meets the real surface: a grid
                        // cell, then its triangle's site, read for the
                        // whole batch before any is used (each read is a
                        // cache miss; one vertex after the other, the
                        // lookups took 6%-10% of a render).
                        self.snap_sites.clear();
                        if let Some(snap) = snap {
                            self.snap_sites.extend(verts.iter().map(|v| {
                                let cell = snap.cell_of(est.sphere.from_unit_point(v.position));
                                if let Some(c) = cell {
                                    snap.prefetch_cell(c);
                                }
                                cell
                            }));
                            for s in &mut self.snap_sites {
                                *s = s.and_then(|c| snap.site_in(c));
                                if let Some(s) = *s {
                                    snap.prefetch_site(s);
                                }
                            }
                        }
                        for (k, (&i, v)) in rows.iter().zip(verts).enumerate() {
                            let depth = paths[self.entries[i].0].depth;
                            let budget = max_bounces.saturating_sub(depth);
                            let site = self.snap_sites.get(k).copied().flatten();
                            let on_surface = |p: Vec3| {
                                let at = snap?.closest_on(site?, p)?;
                                Some((at.point, at.ng, at.ns))
                            };
                            self.skipped[i] =
                                network_skipped(v, &est.sphere, bsdf, budget, on_surface);
                        }
                    }
                    let max_b = sampler.meta().max_internal_bounces;
                    if let (EntryNee::FirstVertex, SurfaceKind::Scatter(bsdf)) =
                        (est.entry_nee, est.surface)
                    {
                        let tracer = scene.object_tracer(est, max_b);
                        for &i in &self.rows {
                            let (path, entry) = &self.entries[i];
                            let budget = max_bounces.saturating_sub(paths[*path].depth);
                            let first = tracer.first_vertex(&entry.ray);
                            self.skipped[i] =
                                first_vertex_skipped(first, bsdf, budget, &self.exits[i]);
                        }
                    }
                }
                EstimatorModel::CostFloor { continue_with, .. } => {
                    // Straight through, free: ending the path (zero
                    // throughput) or going on with the typical exit's.
                    let typical = continue_with.unwrap_or_default();
                    for &i in &self.rows {
                        let entry = &self.entries[i].1;
                        self.exits[i] = Exit {
                            position: entry.pair.exit(),
                            direction: entry.ray.dir,
                            ..typical
                        };
                    }
                }
                EstimatorModel::Oracle {
                    max_internal_bounces,
                } => {
                    let mut tracer = scene.object_tracer(est, *max_internal_bounces);
                    for &i in &self.rows {
                        let (path, entry) = &self.entries[i];
                        let path = &mut paths[*path];
                        let budget = max_bounces.saturating_sub(path.depth);
                        tracer.max_internal_bounces = budget.clamp(1, *max_internal_bounces);
                        let walk = if est.entry_nee == EntryNee::Off {
                            tracer.walk(&entry.ray, &mut path.rng)
                        } else {
                            let verts = &mut self.walk_vertices;
                            verts.clear();
                            tracer.walk_recording(&entry.ray, &mut path.rng, |v| verts.push(v))
                        };
                        self.exits[i] = match walk {
                            Walk::Exit(e) => e,
                            // The exact mask said hit, so the walk hits too; keep the path alive straight through.
                            Walk::Miss => Exit {
                                position: entry.pair.exit(),
                                direction: entry.ray.dir,
                                throughput: Vec3::ONE,
                                radiance: Vec3::ZERO,
                                bounces: 0,
                            },
                        };
                        if let SurfaceKind::Scatter(bsdf) = est.surface {
                            let verts = &self.walk_vertices;
                            self.skipped[i] = match est.entry_nee {
                                EntryNee::Off => SkippedVertices::default(),
                                EntryNee::FirstVertex => first_vertex_skipped(
                                    verts.first().copied(),
                                    bsdf,
                                    budget,
                                    &self.exits[i],
                                ),
                                EntryNee::PickedVertex => {
                                    let u_pick = path.rng.uniform();
                                    pick_skipped(verts, bsdf, budget, u_pick)
                                }
                                EntryNee::PickedVertexLightOnly => {
                                    let u_pick = path.rng.uniform();
                                    SkippedVertices {
                                        light_alone: true,
                                        ..pick_skipped(verts, bsdf, budget, u_pick)
                                    }
                                }
                            };
                        }
                    }
                }
            }
        }
    }
}
