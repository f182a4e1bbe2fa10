//! The estimator at render time: mask lookup, latent lookup, decoder, and the
//! inverse output transform, for rays already in the unit sphere's frame.
//!
//! [`EstimatorSampler::sample_batch`] is the one way exits are decoded: the
//! renderer's wavefront, bake's evaluation of the baked file and the
//! benchmarks all call it, whatever decoder backend runs the network
//! ([`crate::decoder`]). Everything is read-only after construction, so one
//! sampler is shared by all render threads; each caller keeps its own
//! [`ExitBatch`] so that batches do not allocate once its buffers have grown.

use crate::baked::{BakedEstimator, EstimatorFileError, EstimatorMeta};
use crate::decoder::{CpuDecoder, ExitDecoder};
use crate::exit::{DecodeRepairs, EXIT_FEATURES, Exit};
use crate::grid::Corners;
use crate::mask_sign::{MaskSign, MaskSignTable};
use crate::vertex::{PickedVertex, VERTEX_FEATURES};
use nppp_geom::SpherePair;

pub struct EstimatorSampler {
    baked: BakedEstimator,
    /// The plain-Rust decoder: the default, and the fallback when `backend`
    /// fails on a batch.
    cpu: CpuDecoder,
    /// Another decoder backend, when one was attached.
    backend: Option<Box<dyn ExitDecoder>>,
    /// The vertex head's decoder (always plain Rust: it runs on the rows the
    /// exit decoder just ran on, whose latents it reuses).
    vertex_cpu: Option<CpuDecoder>,
    /// Where the mask's answer is known without interpolating it.
    mask_sign: MaskSignTable,
    latent_dim: usize,
    noise_dim: usize,
    /// The most throughput and radiance per channel a decoded exit keeps:
    /// the file does not record the material, so whoever knows it sets this
    /// (a non-emitting surface by default).
    pub bounds: crate::ExitBounds,
}

/// Reusable buffers of [`EstimatorSampler::sample_batch`].
#[derive(Clone, Debug, Default)]
pub struct ExitBatch {
    inputs: Vec<f32>,
    features: Vec<f32>,
    exits: Vec<Exit>,
    vertices: Vec<PickedVertex>,
}

/// What [`EstimatorSampler::sample_batch`] gives back.
#[derive(Debug)]
pub struct DecodedBatch<'a> {
    /// One exit per row, in the unit sphere's frame.
    pub exits: &'a [Exit],
    /// The attached decoder backend failed on this batch and the CPU decoder
    /// answered it instead (renders count these).
    pub fell_back: bool,
}

impl EstimatorSampler {
    /// Panics if `baked` fails [`BakedEstimator::check`], which cannot happen
    /// for one from `load` or `from_f32_grids`; use [`Self::try_new`] for
    /// estimators assembled by hand.
    pub fn new(baked: BakedEstimator) -> Self {
        match Self::try_new(baked) {
            Ok(s) => s,
            Err(e) => panic!("{e}"),
        }
    }

    pub fn try_new(baked: BakedEstimator) -> Result<Self, EstimatorFileError> {
        baked.check().map_err(EstimatorFileError::Build)?;
        let latent_dim = baked.meta.latent_dim as usize;
        let noise_dim = baked.meta.noise_dim as usize;
        let cpu = CpuDecoder::new(&baked.decoder);
        let vertex_cpu = baked.vertex.as_ref().map(|v| CpuDecoder::new(&v.decoder));
        let mask_sign = MaskSignTable::new(&baked.mask);
        Ok(Self { baked, cpu, backend: None, vertex_cpu, mask_sign, latent_dim, noise_dim, bounds: crate::ExitBounds::SURFACE })
    }

    /// Runs the decoder on `backend` instead of the CPU decoder (which still
    /// answers any batch the backend fails on). The backend must implement
    /// this file's decoder (`baked().decoder`).
    pub fn set_decoder(&mut self, backend: Box<dyn ExitDecoder>) {
        self.backend = Some(backend);
    }

    /// The name of the decoder that answers batches.
    pub fn decoder_name(&self) -> &str {
        self.backend.as_deref().map_or(self.cpu.name(), |b| b.name())
    }

    /// Multiply-adds of one exit decoder row.
    pub fn decoder_multiply_adds(&self) -> usize {
        self.baked.decoder.multiply_adds()
    }

    /// Multiply-adds of one vertex head row, if the file has a head.
    pub fn vertex_multiply_adds(&self) -> Option<usize> {
        self.baked.vertex.as_ref().map(|v| v.decoder.multiply_adds())
    }

    /// The plain-Rust decoder (for measuring it alone).
    pub fn cpu_decoder(&self) -> &CpuDecoder {
        &self.cpu
    }

    pub fn baked(&self) -> &BakedEstimator {
        &self.baked
    }

    pub fn meta(&self) -> &EstimatorMeta {
        &self.baked.meta
    }

    pub fn latent_dim(&self) -> usize {
        self.latent_dim
    }

    /// How many standard normals each exit consumes.
    pub fn noise_dim(&self) -> usize {
        self.noise_dim
    }

    pub fn memory_bytes(&self) -> usize {
        self.baked.memory_bytes() + self.mask_sign.memory_bytes()
    }

    /// The interpolated mask logit: a soft, signed value whose sign decides
    /// the hit (thresholding after interpolation avoids staircase edges).
    #[inline]
    pub fn mask_logit(&self, pair: &SpherePair) -> f32 {
        let mut out = [0.0f32];
        self.baked.mask.interpolate(pair, &mut out);
        out[0]
    }

    /// Whether a ray with this chord would hit the mesh: the interpolated
    /// mask logit is positive. Read from the sign table where it knows the
    /// answer (one byte in cache instead of 16 grid nodes).
    #[inline]
    pub fn hits(&self, pair: &SpherePair) -> bool {
        match self.mask_sign.sign(pair) {
            MaskSign::Hit => true,
            MaskSign::Miss => false,
            MaskSign::Mixed => self.mask_logit(pair) > 0.0,
        }
    }

    /// The interpolated latent into `out[..latent_dim]`.
    #[inline]
    pub fn latent(&self, pair: &SpherePair, out: &mut [f32]) {
        self.baked.latent.interpolate(pair, out);
    }

    /// Where [`Self::latent`] at `pair` reads, with those reads started: a
    /// batch takes every row's corners first and blends them after
    /// ([`Self::latent_at`]), so that the rows' cache misses in the latent
    /// grid overlap instead of following one another (perf of cornell-glass
    /// at P = 1: the grid lookups, the mask's included, fell from 5.3-6.0%
    /// of the render's samples to 3.8-4.0%).
    #[inline]
    pub fn latent_corners(&self, pair: &SpherePair) -> Corners {
        let corners = self.baked.latent.corners(pair);
        self.baked.latent.prefetch(&corners);
        corners
    }

    /// The latent at `corners` (from [`Self::latent_corners`]) into
    /// `out[..latent_dim]`: the same values as [`Self::latent`].
    #[inline]
    pub fn latent_at(&self, corners: &Corners, out: &mut [f32]) {
        self.baked.latent.blend(corners, out);
    }

    /// One grid node's latent into `out[..latent_dim]`, picked with the
    /// probability of its interpolation weight (stochastic filtering, see
    /// [`crate::grid::QuantizedGrid::lookup_stochastic`]): one node read
    /// instead of sixteen.
    #[inline]
    pub fn latent_stochastic(&self, pair: &SpherePair, u: [f32; 4], out: &mut [f32]) {
        self.baked.latent.lookup_stochastic(pair, u, out);
    }

    /// Decodes `rows` exits in one decoder call: the estimator's one decode
    /// path. `fill(row, z, r)` writes row `row`'s decoder input, its latent
    /// `z` (`latent_dim` floats: [`Self::latent`] or
    /// [`Self::latent_stochastic`] of the row's chord) and its noise `r`
    /// (`noise_dim` standard normals); it is called for rows 0, 1, ... in
    /// order, so a caller may draw from one stream. The decoder then runs on
    /// all rows (the attached backend, or the CPU decoder, which also
    /// answers a batch the backend fails on), and each row's features go
    /// through the file's inverse transform (repairs counted in `repairs`).
    pub fn sample_batch<'b>(
        &self,
        batch: &'b mut ExitBatch,
        rows: usize,
        mut fill: impl FnMut(usize, &mut [f32], &mut [f32]),
        repairs: &mut DecodeRepairs,
    ) -> DecodedBatch<'b> {
        let (ld, width) = (self.latent_dim, self.latent_dim + self.noise_dim);
        batch.inputs.clear();
        batch.inputs.resize(rows * width, 0.0);
        for (k, row) in batch.inputs.chunks_exact_mut(width).enumerate() {
            let (z, r) = row.split_at_mut(ld);
            fill(k, z, r);
        }
        batch.features.clear();
        batch.features.resize(rows * EXIT_FEATURES, 0.0);
        let mut fell_back = false;
        match &self.backend {
            Some(backend) => {
                if backend.decode(&batch.inputs, rows, &mut batch.features).is_err() {
                    fell_back = true;
                    self.cpu.forward(&batch.inputs, &mut batch.features);
                }
            }
            None => self.cpu.forward(&batch.inputs, &mut batch.features),
        }
        let max_b = self.baked.meta.max_internal_bounces;
        batch.exits.clear();
        batch.exits.extend(batch.features.chunks_exact(EXIT_FEATURES).map(|f| {
            let f: &[f32; EXIT_FEATURES] = f.try_into().unwrap_or(&[0.0; EXIT_FEATURES]);
            self.baked.transform.decode(f, max_b, self.bounds, repairs)
        }));
        DecodedBatch { exits: &batch.exits, fell_back }
    }

    /// Whether the file has a vertex head ([`Self::sample_vertices`]).
    pub fn has_vertex_head(&self) -> bool {
        self.vertex_cpu.is_some()
    }

    /// The vertex head on the rows of the last [`Self::sample_batch`] call
    /// on `batch`: each row keeps its latent, and `noise(row, r)` writes its
    /// own `noise_dim` standard normals (in row order). Returns one picked
    /// vertex per row (unit sphere frame), or `None` without a vertex head.
    /// The vertex is drawn independently of the row's exit (see
    /// [`crate::vertex`]).
    pub fn sample_vertices<'b>(
        &self,
        batch: &'b mut ExitBatch,
        mut noise: impl FnMut(usize, &mut [f32]),
        repairs: &mut DecodeRepairs,
    ) -> Option<&'b [PickedVertex]> {
        self.vertex_cpu.as_ref()?;
        let (ld, width) = (self.latent_dim, self.latent_dim + self.noise_dim);
        for (k, row) in batch.inputs.chunks_exact_mut(width).enumerate() {
            noise(k, &mut row[ld..]);
        }
        self.sample_vertices_from_exit_noise(batch, repairs)
    }

    /// The vertex head on the rows of the last [`Self::sample_batch`] call
    /// on `batch`, each row with its latent and the noise its exit was
    /// drawn from. Each vertex then has the head's distribution, as with
    /// [`Self::sample_vertices`], but is not independent of its row's exit:
    /// a renderer that adds the exit's light and the vertex's light sample
    /// (whose expectations depend on each one's own distribution only)
    /// stays unbiased, and saves `noise_dim` normals per row. On the default
    /// scene at P = 1 the relMSE was the same as with the vertex's own noise
    /// (0.00182 on average over six seeds, both ways).
    pub fn sample_vertices_from_exit_noise<'b>(&self, batch: &'b mut ExitBatch, repairs: &mut DecodeRepairs) -> Option<&'b [PickedVertex]> {
        let (cpu, head) = (self.vertex_cpu.as_ref()?, self.baked.vertex.as_ref()?);
        let width = self.latent_dim + self.noise_dim;
        let rows = batch.inputs.len() / width.max(1);
        batch.features.clear();
        batch.features.resize(rows * VERTEX_FEATURES, 0.0);
        cpu.forward(&batch.inputs, &mut batch.features);
        let max_b = self.baked.meta.max_internal_bounces;
        batch.vertices.clear();
        batch.vertices.extend(batch.features.chunks_exact(VERTEX_FEATURES).map(|f| {
            let f: &[f32; VERTEX_FEATURES] = f.try_into().unwrap_or(&[0.0; VERTEX_FEATURES]);
            let (v, repaired) = head.transform.decode(f, max_b);
            repairs.vertices += u32::from(repaired);
            v
        }));
        Some(&batch.vertices)
    }

    /// One exit for the chord `pair`, driven by `r` (`noise_dim` standard
    /// normals; missing ones count as 0), through [`Self::sample_batch`].
    /// Allocates a batch: for tools and tests, not for a loop over rays.
    pub fn sample(&self, pair: &SpherePair, r: &[f32], repairs: &mut DecodeRepairs) -> Exit {
        let mut batch = ExitBatch::default();
        let decoded = self.sample_batch(
            &mut batch,
            1,
            |_, z, noise| {
                self.latent(pair, z);
                for (x, &v) in noise.iter_mut().zip(r) {
                    *x = v;
                }
            },
            repairs,
        );
        decoded.exits[0]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::baked::tests::tiny_estimator;
    use nppp_geom::{Ray, Vec3};

    fn assert_valid(e: &Exit, max_b: u32) {
        assert!((e.position.length() - 1.0).abs() < 1e-4, "{e:?}");
        assert!((e.direction.length() - 1.0).abs() < 1e-4, "{e:?}");
        assert!(e.direction.dot(e.position) >= -1e-4, "{e:?}");
        assert!(e.throughput.is_finite() && e.throughput.min_element() >= 0.0);
        assert!(e.radiance.is_finite() && e.radiance.min_element() >= 0.0);
        assert!(e.bounces <= max_b);
    }

    #[test]
    fn is_send_and_sync() {
        fn check<T: Send + Sync>() {}
        check::<EstimatorSampler>();
        check::<ExitBatch>();
    }

    /// A backend that fails every batch, or answers with a fixed value.
    struct TestBackend(Option<f32>);

    impl ExitDecoder for TestBackend {
        fn decode(&self, _: &[f32], rows: usize, output: &mut [f32]) -> Result<(), String> {
            let v = self.0.ok_or("out of device memory")?;
            output[..rows * EXIT_FEATURES].iter_mut().for_each(|x| *x = v);
            Ok(())
        }
        fn name(&self) -> &str {
            "test"
        }
    }

    /// The vertex head reuses each row's latent, and its exit's noise or
    /// noise of its own, and gives what the head's decoder and transform
    /// give by hand.
    #[test]
    fn vertex_head_decodes_the_rows_latents_with_their_exits_or_its_own_noise() {
        use crate::baked::tests::tiny_vertex_head;
        let plain = EstimatorSampler::new(tiny_estimator(4, 3, 8));
        let mut batch = ExitBatch::default();
        let mut rep = DecodeRepairs::default();
        assert!(!plain.has_vertex_head());
        assert!(plain.sample_vertices(&mut batch, |_, _| {}, &mut rep).is_none());
        let est = tiny_estimator(4, 3, 8).with_vertex_head(tiny_vertex_head(4, 3)).unwrap();
        let s = EstimatorSampler::new(est.clone());
        assert!(s.has_vertex_head());
        let pairs = [SpherePair([0.3, 0.9, 0.6, 0.2]), SpherePair([0.0, 0.1, 0.9, 0.5])];
        let exit_noise = [0.5f32, -1.0, 2.0];
        let vertex_noise = [[0.1f32, 0.2, -0.3], [1.5, -0.5, 0.0]];
        s.sample_batch(
            &mut batch,
            2,
            |k, z, r| {
                s.latent(&pairs[k], z);
                r.copy_from_slice(&exit_noise);
            },
            &mut rep,
        );
        // Without noise of their own the rows keep their exits'.
        let shared = s.sample_vertices_from_exit_noise(&mut batch, &mut rep).unwrap().to_vec();
        for (k, got) in shared.iter().enumerate() {
            let mut z = [0.0f32; 4];
            est.latent.interpolate(&pairs[k], &mut z);
            let input: Vec<f32> = z.iter().chain(&exit_noise).copied().collect();
            let mut f = [0.0f32; VERTEX_FEATURES];
            est.vertex.as_ref().unwrap().decoder.forward_batch(&input, &mut f);
            let (want, _) = est.vertex.as_ref().unwrap().transform.decode(&f, 64);
            assert!(got.position.distance(want.position) < 1e-5, "{got:?} {want:?}");
            assert_eq!(got.index, want.index);
        }
        let mut order = Vec::new();
        let verts = s
            .sample_vertices(
                &mut batch,
                |k, r| {
                    order.push(k);
                    r.copy_from_slice(&vertex_noise[k]);
                },
                &mut rep,
            )
            .unwrap()
            .to_vec();
        assert_eq!(order, [0, 1]);
        let head = est.vertex.as_ref().unwrap();
        for k in 0..2 {
            let mut z = [0.0f32; 4];
            est.latent.interpolate(&pairs[k], &mut z);
            let input: Vec<f32> = z.iter().chain(&vertex_noise[k]).copied().collect();
            let mut f = [0.0f32; VERTEX_FEATURES];
            head.decoder.forward_batch(&input, &mut f);
            let (want, _) = head.transform.decode(&f, 64);
            let got = verts[k];
            assert!(got.position.distance(want.position) < 1e-5, "{got:?} {want:?}");
            assert!(got.normal.distance(want.normal) < 1e-4 && got.wo.distance(want.wo) < 1e-4);
            assert!((got.beta - want.beta).abs().max_element() <= 1e-4 * (1.0 + want.beta.max_element()));
            assert_eq!(got.index, want.index);
        }
    }

    #[test]
    fn sample_matches_manual_pipeline() {
        let est = tiny_estimator(4, 3, 8);
        let s = EstimatorSampler::new(est.clone());
        let mut rep = DecodeRepairs::default();
        let pair = SpherePair([0.3, 0.9, 0.6, 0.2]);
        let r = [0.5f32, -1.0, 2.0];
        let e = s.sample(&pair, &r, &mut rep);
        let mut z = [0.0f32; 4];
        est.latent.interpolate(&pair, &mut z);
        let input: Vec<f32> = z.iter().chain(&r).copied().collect();
        let mut f = [0.0f32; EXIT_FEATURES];
        est.decoder.forward_batch(&input, &mut f);
        let mut rep2 = DecodeRepairs::default();
        let want = est.transform.decode(&f, 64, crate::ExitBounds::SURFACE, &mut rep2);
        assert!(e.position.distance(want.position) < 1e-5 && e.direction.distance(want.direction) < 1e-5, "{e:?} {want:?}");
        assert!((e.throughput - want.throughput).abs().max_element() <= 1e-4 * (1.0 + want.throughput.max_element()));
        assert_eq!(e.bounces, want.bounces);
        assert_eq!(rep, rep2);
        // A batch gives each row what it gives alone, and calls `fill` in row order.
        let pairs = [pair, SpherePair([0.0, 0.0, 1.0, 0.5]), pair];
        let rs = [r, [0.0; 3], [1.0, 1.0, 1.0]].concat();
        let mut batch = ExitBatch::default();
        let mut order = Vec::new();
        let decoded = s.sample_batch(
            &mut batch,
            3,
            |k, z, noise| {
                order.push(k);
                s.latent(&pairs[k], z);
                noise.copy_from_slice(&rs[k * 3..k * 3 + 3]);
            },
            &mut rep,
        );
        assert!(!decoded.fell_back);
        assert_eq!(decoded.exits.len(), 3);
        assert_eq!(decoded.exits[0], e);
        assert_eq!(decoded.exits[1], s.sample(&pairs[1], &rs[3..6], &mut rep));
        assert_eq!(decoded.exits[2], s.sample(&pairs[2], &rs[6..9], &mut rep));
        assert_eq!(order, [0, 1, 2]);
        // The mask: hits is the sign of the interpolated logit.
        for p in [pair, pairs[1]] {
            assert_eq!(s.hits(&p), s.mask_logit(&p) > 0.0);
        }
    }

    /// An attached backend answers the batches; one that fails is replaced
    /// by the CPU decoder for that batch, which says so.
    #[test]
    fn backends_answer_and_fall_back() {
        let mut s = EstimatorSampler::new(tiny_estimator(4, 3, 8));
        let mut rep = DecodeRepairs::default();
        let pair = SpherePair([0.3, 0.9, 0.6, 0.2]);
        let r = [0.5f32, -1.0, 2.0];
        let cpu = s.sample(&pair, &r, &mut rep);
        assert_eq!(s.decoder_name(), "cpu");
        let fill = |_: usize, z: &mut [f32], noise: &mut [f32]| {
            z.fill(0.1);
            noise.copy_from_slice(&r);
        };
        let mut batch = ExitBatch::default();
        let want = s.sample_batch(&mut batch, 2, fill, &mut rep).exits.to_vec();
        s.set_decoder(Box::new(TestBackend(None)));
        assert_eq!(s.decoder_name(), "test");
        let got = s.sample_batch(&mut batch, 2, fill, &mut rep);
        assert!(got.fell_back);
        assert_eq!(got.exits, want);
        assert_eq!(s.sample(&pair, &r, &mut rep), cpu);
        s.set_decoder(Box::new(TestBackend(Some(0.0))));
        let got = s.sample_batch(&mut batch, 2, fill, &mut rep);
        assert!(!got.fell_back);
        let mut rep2 = DecodeRepairs::default();
        let zero = s.baked().transform.decode(&[0.0; EXIT_FEATURES], 64, s.bounds, &mut rep2);
        assert_eq!(got.exits, [zero, zero]);
    }

    #[test]
    fn stress_rays_give_valid_exits() {
        let s = EstimatorSampler::new(tiny_estimator(4, 2, 4));
        let mut rep = DecodeRepairs::default();
        let mut rays = vec![
            // Exactly tangent (chord of length 0).
            Ray::new(Vec3::new(0.0, 1.0, -5.0), Vec3::Z),
            Ray::new(Vec3::new(1.0, 0.0, -3.0), Vec3::Z),
            // Through both poles.
            Ray::new(Vec3::new(0.0, 0.0, -4.0), Vec3::Z),
            Ray::new(Vec3::new(0.0, 0.0, 4.0), -Vec3::Z),
            // Along the phi = 0 seam, and across it.
            Ray::new(Vec3::new(-3.0, 0.0, 0.0), Vec3::X),
            Ray::new(Vec3::new(0.5, -3.0, 0.1), Vec3::Y),
            Ray::new(Vec3::new(0.5, -1e-7, -3.0), Vec3::Z),
            Ray::new(Vec3::new(0.5, 1e-7, -3.0), Vec3::Z),
        ];
        for k in 0..64 {
            let a = k as f32 * 0.1;
            rays.push(Ray::new(Vec3::new(a.cos() * 3.0, a.sin() * 3.0, 0.3), -Vec3::new(a.cos(), a.sin(), 0.0)));
        }
        for ray in &rays {
            let (pair, _) = SpherePair::from_ray(ray).expect("ray hits sphere");
            let e = s.sample(&pair, &[0.3, -0.2], &mut rep);
            assert_valid(&e, 64);
            assert!(s.mask_logit(&pair).is_finite());
        }
        assert!(SpherePair::from_ray(&Ray::new(Vec3::new(0.0, 2.0, -5.0), Vec3::Z)).is_none());
        // Continuity across the v seam.
        let mut a = [0.0f32; 4];
        let mut b = [0.0f32; 4];
        s.latent(&SpherePair([0.4, 1.0 - 1e-6, 0.6, 0.3]), &mut a);
        s.latent(&SpherePair([0.4, 1e-6, 0.6, 0.3]), &mut b);
        assert!(a.iter().zip(&b).all(|(x, y)| (x - y).abs() < 1e-3));
        // Hostile pairs and noise.
        for p in [[f32::NAN; 4], [f32::INFINITY, -1.0, 2.0, f32::NEG_INFINITY], [1e30, -1e30, 0.5, 0.5]] {
            let e = s.sample(&SpherePair(p), &[f32::NAN, 1e30], &mut rep);
            assert_valid(&e, 64);
        }
    }

    #[test]
    fn broken_decoder_outputs_are_repaired_and_counted() {
        let mut est = tiny_estimator(4, 2, 8);
        est.transform = crate::exit::ExitTransform::default();
        // A last layer that outputs huge values, negative throughput and a
        // zero position: every repair path.
        let last = est.decoder.layers.last_mut().unwrap();
        last.weight.iter_mut().for_each(|w| *w = 0.0);
        last.bias = vec![0.0, 0.0, 0.0, 1e30, -1e30, 0.0, -50.0, 1e30, -1.0, 0.0, 0.0, 0.0, 1e3];
        let s = EstimatorSampler::new(est);
        let mut rep = DecodeRepairs::default();
        let e = s.sample(&SpherePair([0.5; 4]), &[0.0, 0.0], &mut rep);
        assert_valid(&e, 64);
        assert_eq!(e.bounces, 64);
        assert!(rep.degenerate >= 1 && rep.clamped >= 1, "{rep:?}");
    }

    #[test]
    fn try_new_rejects_inconsistent_estimators() {
        let mut est = tiny_estimator(4, 2, 8);
        est.meta.noise_dim = 5;
        assert!(EstimatorSampler::try_new(est).is_err());
    }
}
