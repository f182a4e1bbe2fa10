//! The estimator at render time: mask lookup, latent lookup, decoder, and the
//! inverse output transform, for rays already in the unit sphere's frame.
//!
//! Everything is read-only after construction, so one sampler is shared by
//! all render threads; per-thread state lives in [`SamplerScratch`] so that
//! no call allocates.

use crate::baked::{BakedEstimator, EstimatorFileError, EstimatorMeta};
use crate::exit::{DecodeRepairs, EXIT_FEATURES, Exit};
use nppp_geom::{Ray, SpherePair};

pub struct EstimatorSampler {
    baked: BakedEstimator,
    /// The decoder with transposed weights (see [`FastLayer`]).
    layers: Vec<FastLayer>,
    latent_dim: usize,
    noise_dim: usize,
    mlp_scratch: usize,
    /// The most throughput per channel a decoded exit keeps
    /// ([`crate::exit_throughput_bound`]): the file does not record the
    /// material, so whoever knows it sets this (1, a surface, by default).
    pub throughput_bound: f32,
}

/// A decoder layer stored `[inputs][outputs]`. `Mlp::forward_into` computes
/// each output as a dot product, a serial chain of dependent adds; here each
/// input adds a scaled weight row to all outputs at once, which vectorizes
/// and skips the inputs that ReLU zeroed. Same sums, different order: equal
/// to `Mlp::forward_into` within float rounding, not bit for bit.
#[derive(Clone, Debug)]
struct FastLayer {
    inputs: usize,
    outputs: usize,
    weight_t: Vec<f32>,
    bias: Vec<f32>,
    relu: bool,
}

impl FastLayer {
    fn from_mlp(mlp: &crate::mlp::Mlp) -> Vec<Self> {
        let last = mlp.layers.len().saturating_sub(1);
        mlp.layers
            .iter()
            .enumerate()
            .map(|(li, l)| {
                let mut weight_t = vec![0.0; l.inputs * l.outputs];
                for o in 0..l.outputs {
                    for i in 0..l.inputs {
                        weight_t[i * l.outputs + o] = l.weight[o * l.inputs + i];
                    }
                }
                Self { inputs: l.inputs, outputs: l.outputs, weight_t, bias: l.bias.clone(), relu: li < last }
            })
            .collect()
    }
}

/// Runs the layers on one row held in `buf[..inputs]`; returns the output's
/// position in `buf` (the first or the second half).
#[inline]
fn forward_fast(layers: &[FastLayer], buf: &mut [f32]) -> usize {
    let half = buf.len() / 2;
    let (mut a, mut b) = buf.split_at_mut(half);
    let mut in_second = false;
    for l in layers {
        let next = &mut b[..l.outputs];
        next.copy_from_slice(&l.bias);
        for (&x, row) in a[..l.inputs].iter().zip(l.weight_t.chunks_exact(l.outputs)) {
            if x != 0.0 {
                for (n, &w) in next.iter_mut().zip(row) {
                    *n += x * w;
                }
            }
        }
        if l.relu {
            next.iter_mut().for_each(|v| *v = v.max(0.0));
        }
        std::mem::swap(&mut a, &mut b);
        in_second = !in_second;
    }
    if in_second { half } else { 0 }
}

/// Per-thread buffers for [`EstimatorSampler::sample`].
#[derive(Clone, Debug)]
pub struct SamplerScratch {
    output: [f32; EXIT_FEATURES],
    /// Two layer-width halves; the first starts as the decoder input `[z, r]`.
    mlp: Vec<f32>,
}

impl SamplerScratch {
    pub fn new(sampler: &EstimatorSampler) -> Self {
        Self { output: [0.0; EXIT_FEATURES], mlp: vec![0.0; sampler.mlp_scratch] }
    }
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
        let mlp_scratch = 2 * baked.decoder.max_width();
        let layers = FastLayer::from_mlp(&baked.decoder);
        Ok(Self { baked, layers, latent_dim, noise_dim, mlp_scratch, throughput_bound: crate::EXIT_THROUGHPUT_BOUND })
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

    /// How many standard normals `sample` consumes per ray.
    pub fn noise_dim(&self) -> usize {
        self.noise_dim
    }

    pub fn memory_bytes(&self) -> usize {
        self.baked.memory_bytes()
    }

    /// The interpolated mask logit: a soft, signed value whose sign decides
    /// the hit (thresholding after interpolation avoids staircase edges).
    #[inline]
    pub fn mask_logit(&self, pair: &SpherePair) -> f32 {
        let mut out = [0.0f32];
        self.baked.mask.interpolate(pair, &mut out);
        out[0]
    }

    /// Whether a ray with this chord would hit the mesh.
    #[inline]
    pub fn hits(&self, pair: &SpherePair) -> bool {
        self.mask_logit(pair) > 0.0
    }

    /// The interpolated latent into `out[..latent_dim]`.
    #[inline]
    pub fn latent(&self, pair: &SpherePair, out: &mut [f32]) {
        self.baked.latent.interpolate(pair, out);
    }

    /// One grid node's latent into `out[..latent_dim]`, picked with the
    /// probability of its interpolation weight (stochastic filtering, see
    /// [`crate::grid::QuantizedGrid::lookup_stochastic`]): one node read
    /// instead of sixteen.
    #[inline]
    pub fn latent_stochastic(&self, pair: &SpherePair, u: [f32; 4], out: &mut [f32]) {
        self.baked.latent.lookup_stochastic(pair, u, out);
    }

    /// One exit for the chord `pair`, driven by `r` (`noise_dim` standard
    /// normals; panics if shorter). The exit is in the unit sphere's frame.
    pub fn sample(&self, pair: &SpherePair, r: &[f32], scratch: &mut SamplerScratch, repairs: &mut DecodeRepairs) -> Exit {
        let (z, noise) = scratch.mlp[..self.latent_dim + self.noise_dim].split_at_mut(self.latent_dim);
        self.baked.latent.interpolate(pair, z);
        noise.copy_from_slice(&r[..self.noise_dim]);
        let at = forward_fast(&self.layers, &mut scratch.mlp);
        scratch.output.copy_from_slice(&scratch.mlp[at..at + EXIT_FEATURES]);
        self.baked.transform.decode(&scratch.output, self.baked.meta.max_internal_bounces, self.throughput_bound, repairs)
    }

    /// The decoder's raw output (standardized features) for one input row
    /// `[z, r]`; what [`Self::sample`] feeds to the inverse transform.
    pub fn decode_features(&self, input: &[f32], scratch: &mut SamplerScratch) -> [f32; EXIT_FEATURES] {
        let n = self.latent_dim + self.noise_dim;
        scratch.mlp[..n].copy_from_slice(&input[..n]);
        let at = forward_fast(&self.layers, &mut scratch.mlp);
        let mut f = [0.0; EXIT_FEATURES];
        f.copy_from_slice(&scratch.mlp[at..at + EXIT_FEATURES]);
        f
    }

    /// The decoder on `rows` rows of `[z, r]` stored contiguously, giving
    /// `EXIT_FEATURES` standardized features per row: `Mlp::forward_batch`
    /// with the faster layer order (equal within float rounding). For a
    /// wavefront that fills the decoder inputs itself.
    ///
    /// Each layer runs as one matrix product (`matrixmultiply`, which picks
    /// AVX/FMA kernels at run time): several times faster than row by row on
    /// the wavefront's batches of hundreds of entries. Every batch, however
    /// small, takes this path, so each row's result does not depend on the
    /// other rows of its batch nor on their number: a render's pixels are
    /// the same bits however its entries batch up (thread counts, render
    /// shards that split a tile's samples differently).
    pub fn forward_batch(&self, input: &[f32], output: &mut [f32]) {
        let n = self.latent_dim + self.noise_dim;
        let rows = (input.len() / n).min(output.len() / EXIT_FEATURES);
        if rows == 0 {
            return;
        }
        let width = self.layers.iter().map(|l| l.outputs).max().unwrap_or(0).max(n);
        let mut a = vec![0.0f32; rows * width];
        let mut b = vec![0.0f32; rows * width];
        a[..rows * n].copy_from_slice(&input[..rows * n]);
        for l in &self.layers {
            let (k, m) = (l.inputs, l.outputs);
            let c = &mut b[..rows * m];
            for row in c.chunks_exact_mut(m) {
                row.copy_from_slice(&l.bias);
            }
            // C (rows x m) += A (rows x k) * W^T (k x m), all row-major.
            // SAFETY: `a` holds rows x k floats (the previous layer's
            // outputs or the input), `weight_t` k x m, `c` rows x m; the
            // strides below describe exactly those dense row-major layouts,
            // and `c` does not alias `a` or the weights.
            unsafe {
                matrixmultiply::sgemm(
                    rows,
                    k,
                    m,
                    1.0,
                    a.as_ptr(),
                    k as isize,
                    1,
                    l.weight_t.as_ptr(),
                    m as isize,
                    1,
                    1.0,
                    c.as_mut_ptr(),
                    m as isize,
                    1,
                );
            }
            if l.relu {
                c.iter_mut().for_each(|v| *v = v.max(0.0));
            }
            std::mem::swap(&mut a, &mut b);
        }
        output[..rows * EXIT_FEATURES].copy_from_slice(&a[..rows * EXIT_FEATURES]);
    }

    pub fn forward_batch_with(&self, input: &[f32], output: &mut [f32], scratch: &mut SamplerScratch) {
        let n = self.latent_dim + self.noise_dim;
        for (x, y) in input.chunks_exact(n).zip(output.chunks_exact_mut(EXIT_FEATURES)) {
            scratch.mlp[..n].copy_from_slice(x);
            let at = forward_fast(&self.layers, &mut scratch.mlp);
            y.copy_from_slice(&scratch.mlp[at..at + EXIT_FEATURES]);
        }
    }

    /// [`Self::sample`] for a ray given in the unit sphere's frame; `None`
    /// when its line misses the sphere. The mask is not consulted.
    pub fn sample_ray(&self, ray: &Ray, r: &[f32], scratch: &mut SamplerScratch, repairs: &mut DecodeRepairs) -> Option<Exit> {
        let (pair, _) = SpherePair::from_ray(ray)?;
        Some(self.sample(&pair, r, scratch, repairs))
    }

    /// One exit per pair; `r` holds `noise_dim` normals per pair, row after
    /// row. This is the wavefront entry point: one call per gathered batch.
    pub fn sample_batch(&self, pairs: &[SpherePair], r: &[f32], out: &mut [Exit], repairs: &mut DecodeRepairs) {
        let mut scratch = SamplerScratch::new(self);
        self.sample_batch_with(pairs, r, out, &mut scratch, repairs);
    }

    /// [`Self::sample_batch`] without even the per-batch scratch allocation.
    pub fn sample_batch_with(
        &self,
        pairs: &[SpherePair],
        r: &[f32],
        out: &mut [Exit],
        scratch: &mut SamplerScratch,
        repairs: &mut DecodeRepairs,
    ) {
        assert!(out.len() >= pairs.len(), "sample_batch: {} outputs for {} pairs", out.len(), pairs.len());
        assert!(
            r.len() >= pairs.len() * self.noise_dim,
            "sample_batch: {} normals for {} pairs x {}",
            r.len(),
            pairs.len(),
            self.noise_dim
        );
        let nd = self.noise_dim;
        for (i, (pair, o)) in pairs.iter().zip(out.iter_mut()).enumerate() {
            *o = self.sample(pair, &r[i * nd..(i + 1) * nd], scratch, repairs);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::baked::tests::tiny_estimator;
    use nppp_geom::Vec3;

    fn assert_valid(e: &Exit, max_b: u32) {
        assert!((e.position.length() - 1.0).abs() < 1e-4, "{e:?}");
        assert!((e.direction.length() - 1.0).abs() < 1e-4, "{e:?}");
        assert!(e.direction.dot(e.position) >= -1e-4, "{e:?}");
        assert!(e.throughput.is_finite() && e.throughput.min_element() >= 0.0);
        assert!(e.radiance.is_finite() && e.radiance.min_element() >= 0.0);
        assert!(e.bounces <= max_b);
    }

    /// The matrix-product path gives each row the same bits whatever else is
    /// in its batch (renders stay deterministic however entries batch up),
    /// and agrees with the row-by-row path within float rounding.
    #[test]
    fn gemm_rows_do_not_depend_on_their_batch() {
        let s = EstimatorSampler::new(tiny_estimator(4, 3, 8));
        let n = s.latent_dim() + s.noise_dim();
        let rows = 64;
        let input: Vec<f32> = (0..rows * n).map(|k| ((k * 37 % 29) as f32 - 14.0) / 6.0).collect();
        let mut all = vec![0.0f32; rows * EXIT_FEATURES];
        s.forward_batch(&input, &mut all);
        for (lo, hi) in [(10, 40), (0, 16), (47, 64), (0, 1), (5, 8), (63, 64)] {
            let mut part = vec![0.0f32; (hi - lo) * EXIT_FEATURES];
            s.forward_batch(&input[lo * n..hi * n], &mut part);
            assert_eq!(part, all[lo * EXIT_FEATURES..hi * EXIT_FEATURES], "rows {lo}..{hi}");
        }
        let mut scratch = SamplerScratch::new(&s);
        for k in 0..rows {
            let one = s.decode_features(&input[k * n..(k + 1) * n], &mut scratch);
            for (a, b) in one.iter().zip(&all[k * EXIT_FEATURES..(k + 1) * EXIT_FEATURES]) {
                assert!((a - b).abs() <= 1e-5 * (1.0 + b.abs()), "row {k}: {a} vs {b}");
            }
        }
    }

    #[test]
    fn is_send_and_sync() {
        fn check<T: Send + Sync>() {}
        check::<EstimatorSampler>();
        check::<SamplerScratch>();
    }

    #[test]
    fn sample_matches_manual_pipeline() {
        let est = tiny_estimator(4, 3, 8);
        let s = EstimatorSampler::new(est.clone());
        let mut scratch = SamplerScratch::new(&s);
        let mut rep = DecodeRepairs::default();
        let pair = SpherePair([0.3, 0.9, 0.6, 0.2]);
        let r = [0.5f32, -1.0, 2.0];
        let e = s.sample(&pair, &r, &mut scratch, &mut rep);
        let mut z = [0.0f32; 4];
        est.latent.interpolate(&pair, &mut z);
        let input: Vec<f32> = z.iter().chain(&r).copied().collect();
        let mut f = [0.0f32; EXIT_FEATURES];
        est.decoder.forward_batch(&input, &mut f);
        let fast = s.decode_features(&input, &mut scratch);
        for (a, b) in fast.iter().zip(&f) {
            assert!((a - b).abs() <= 1e-5 * (1.0 + b.abs()), "{fast:?} vs {f:?}");
        }
        let mut rep2 = DecodeRepairs::default();
        let want = est.transform.decode(&f, 64, crate::EXIT_THROUGHPUT_BOUND, &mut rep2);
        assert!(e.position.distance(want.position) < 1e-5 && e.direction.distance(want.direction) < 1e-5, "{e:?} {want:?}");
        assert!((e.throughput - want.throughput).abs().max_element() <= 1e-4 * (1.0 + want.throughput.max_element()));
        assert_eq!(e.bounces, want.bounces);
        assert_eq!(rep, rep2);
        // The fast decoder against the reference `Mlp` on many inputs, with
        // exact zeros (skipped inputs) among them.
        for k in 0..200 {
            let input: Vec<f32> = (0..7).map(|i| if (k + i) % 3 == 0 { 0.0 } else { ((k * 7 + i * 13) % 17) as f32 / 4.0 - 2.0 }).collect();
            let mut f = [0.0f32; EXIT_FEATURES];
            est.decoder.forward_batch(&input, &mut f);
            let fast = s.decode_features(&input, &mut scratch);
            for (a, b) in fast.iter().zip(&f) {
                assert!((a - b).abs() <= 1e-5 * (1.0 + b.abs()), "{fast:?} vs {f:?}");
            }
        }
        let inputs: Vec<f32> = (0..7 * 50).map(|k| ((k * 31 % 23) as f32 - 11.0) / 5.0).collect();
        let mut a = vec![0.0f32; 13 * 50];
        let mut b = vec![0.0f32; 13 * 50];
        est.decoder.forward_batch(&inputs, &mut a);
        s.forward_batch(&inputs, &mut b);
        assert!(a.iter().zip(&b).all(|(x, y)| (x - y).abs() <= 1e-5 * (1.0 + x.abs())));
        // Batch = loop.
        let pairs = [pair, SpherePair([0.0, 0.0, 1.0, 0.5]), pair];
        let rs = [r, [0.0; 3], [1.0, 1.0, 1.0]].concat();
        let mut out = [Exit::default(); 3];
        let mut rep3 = DecodeRepairs::default();
        s.sample_batch(&pairs, &rs, &mut out, &mut rep3);
        assert_eq!(out[0], e);
        assert_eq!(out[1], s.sample(&pairs[1], &rs[3..6], &mut scratch, &mut rep));
        assert_eq!(out[2], s.sample(&pairs[2], &rs[6..9], &mut scratch, &mut rep));
        // The mask: hits is the sign of the interpolated logit.
        for p in [pair, pairs[1]] {
            assert_eq!(s.hits(&p), s.mask_logit(&p) > 0.0);
        }
    }

    #[test]
    fn stress_rays_give_valid_exits() {
        let s = EstimatorSampler::new(tiny_estimator(4, 2, 4));
        let mut scratch = SamplerScratch::new(&s);
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
            let e = s.sample_ray(ray, &[0.3, -0.2], &mut scratch, &mut rep).expect("ray hits sphere");
            assert_valid(&e, 64);
            let (pair, _) = SpherePair::from_ray(ray).unwrap();
            assert!(s.mask_logit(&pair).is_finite());
        }
        assert!(s.sample_ray(&Ray::new(Vec3::new(0.0, 2.0, -5.0), Vec3::Z), &[0.0, 0.0], &mut scratch, &mut rep).is_none());
        // Continuity across the v seam.
        let mut a = [0.0f32; 4];
        let mut b = [0.0f32; 4];
        s.latent(&SpherePair([0.4, 1.0 - 1e-6, 0.6, 0.3]), &mut a);
        s.latent(&SpherePair([0.4, 1e-6, 0.6, 0.3]), &mut b);
        assert!(a.iter().zip(&b).all(|(x, y)| (x - y).abs() < 1e-3));
        // Hostile pairs and noise.
        for p in [[f32::NAN; 4], [f32::INFINITY, -1.0, 2.0, f32::NEG_INFINITY], [1e30, -1e30, 0.5, 0.5]] {
            let e = s.sample(&SpherePair(p), &[f32::NAN, 1e30], &mut scratch, &mut rep);
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
        let mut scratch = SamplerScratch::new(&s);
        let mut rep = DecodeRepairs::default();
        let e = s.sample(&SpherePair([0.5; 4]), &[0.0, 0.0], &mut scratch, &mut rep);
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
