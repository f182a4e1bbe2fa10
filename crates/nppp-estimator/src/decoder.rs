//! The decoder seam: what turns rows of decoder inputs `[z, r]` into rows of
//! standardized exit features. [`CpuDecoder`] (plain Rust) is the default;
//! another backend (nppp-nn's Burn module on a CPU or GPU) implements
//! [`ExitDecoder`] and is attached with
//! [`EstimatorSampler::set_decoder`](crate::EstimatorSampler::set_decoder).
//! Everything else (latent lookup, noise, the inverse output transform, the
//! fallback when a backend fails) is [`crate::EstimatorSampler::sample_batch`]'s
//! and the same for every backend.

use crate::dense_kernel::{KernelIsa, PackedLayer};
use crate::exit::EXIT_FEATURES;
use crate::mlp::Mlp;

/// A decoder backend. The sampler calls it once per batch (a wavefront
/// step's entries, or bake's evaluation rays), so a GPU or Burn backend
/// amortizes its launch overhead over hundreds of rows.
pub trait ExitDecoder: Send + Sync {
    /// `input` holds `rows` rows of `latent_dim + noise_dim` floats; writes
    /// `rows` rows of [`EXIT_FEATURES`] floats to `output`. On an error the
    /// sampler answers the batch with its [`CpuDecoder`] and reports it.
    fn decode(&self, input: &[f32], rows: usize, output: &mut [f32]) -> Result<(), String>;
    /// A short name for reports ("cpu", "burn-wgpu", ...).
    fn name(&self) -> &str;
}

thread_local! {
    /// [`CpuDecoder::forward`]'s two activation buffers, one pair per
    /// thread for every decoder it runs: a render calls it once per
    /// wavefront step, and allocating and zeroing them each time was 0.4%
    /// of a cornell-glass render's samples in perf (`memset`, `malloc`).
    /// They keep the largest batch's size: under 100 KiB for a render's
    /// batches of a few hundred rows, 8 MiB for `nppp bake`'s of 16 k.
    static SCRATCH: std::cell::RefCell<(Vec<f32>, Vec<f32>)> = const { std::cell::RefCell::new((Vec::new(), Vec::new())) };
}

/// The decoder in plain Rust: each layer one blocked matrix product
/// ([`crate::dense_kernel`]) on weights packed when the estimator loads.
#[derive(Clone, Debug)]
pub struct CpuDecoder {
    layers: Vec<PackedLayer>,
    inputs: usize,
    outputs: usize,
    /// The widest padded row any layer writes.
    stride: usize,
    isa: KernelIsa,
}

impl CpuDecoder {
    /// `mlp` must pass [`Mlp::validate`] (the sampler checks it first).
    /// Runs on the widest instruction set this CPU has.
    pub fn new(mlp: &Mlp) -> Self {
        Self::with_isa(mlp, KernelIsa::detect())
    }

    /// On a given instruction set (one of [`KernelIsa::available`]): for
    /// tests and benchmarks.
    pub fn with_isa(mlp: &Mlp, isa: KernelIsa) -> Self {
        let last = mlp.layers.len().saturating_sub(1);
        let layers: Vec<PackedLayer> =
            mlp.layers.iter().enumerate().map(|(li, l)| PackedLayer::new(l.inputs, l.outputs, &l.weight, &l.bias, li < last)).collect();
        let stride = layers.iter().map(|l| l.padded).max().unwrap_or(0);
        Self { layers, inputs: mlp.inputs(), outputs: mlp.outputs(), stride, isa }
    }

    /// The instruction set its products run on.
    pub fn isa(&self) -> KernelIsa {
        self.isa
    }

    /// The decoder on the rows of `input` (as many as both slices hold:
    /// `inputs` floats in, the last layer's outputs out, per row).
    ///
    /// Every batch, however small, takes the same kernel, whose result for
    /// a row does not depend on the other rows of its batch nor on their
    /// number: a render's pixels are the same bits however its entries
    /// batch up (thread counts, render shards that split a tile's samples
    /// differently). Equal to [`Mlp::forward_batch`] within float rounding
    /// (fused multiply-adds where the CPU has them), not bit for bit.
    pub fn forward(&self, input: &[f32], output: &mut [f32]) {
        let (n, m) = (self.inputs, self.outputs);
        if n == 0 || m == 0 {
            return;
        }
        let rows = (input.len() / n).min(output.len() / m);
        if rows == 0 {
            return;
        }
        SCRATCH.with_borrow_mut(|(a, b)| {
            // Every layer writes all `rows x padded` floats of its output
            // before the next reads them: what a buffer held is never read,
            // so growing it is all the clearing it needs.
            for buf in [&mut *a, &mut *b] {
                if buf.len() < rows * self.stride {
                    buf.resize(rows * self.stride, 0.0);
                }
            }
            let (first, rest) = self.layers.split_first().expect("a validated decoder has layers");
            first.forward(self.isa, &input[..rows * n], n, rows, a);
            let mut a_stride = first.padded;
            for l in rest {
                l.forward(self.isa, a, a_stride, rows, b);
                a_stride = l.padded;
                std::mem::swap(a, b);
            }
            for (out, row) in output[..rows * m].chunks_exact_mut(m).zip(a.chunks_exact(a_stride)) {
                out.copy_from_slice(&row[..m]);
            }
        });
    }
}

impl ExitDecoder for CpuDecoder {
    fn decode(&self, input: &[f32], rows: usize, output: &mut [f32]) -> Result<(), String> {
        if input.len() < rows * self.inputs || output.len() < rows * EXIT_FEATURES {
            return Err(format!("decoder batch: {} inputs / {} outputs for {rows} rows", input.len(), output.len()));
        }
        self.forward(&input[..rows * self.inputs], &mut output[..rows * EXIT_FEATURES]);
        Ok(())
    }

    fn name(&self) -> &str {
        "cpu"
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::baked::tests::tiny_estimator;

    /// Each row gets the same bits whatever else is in its batch (renders
    /// stay deterministic however entries batch up), and the product agrees
    /// with the reference `Mlp` within float rounding.
    #[test]
    fn rows_do_not_depend_on_their_batch() {
        let mlp = tiny_estimator(4, 3, 8).decoder;
        let dec = CpuDecoder::new(&mlp);
        let n = mlp.inputs();
        let rows = 64;
        let input: Vec<f32> = (0..rows * n).map(|k| ((k * 37 % 29) as f32 - 14.0) / 6.0).collect();
        let mut all = vec![0.0f32; rows * EXIT_FEATURES];
        dec.forward(&input, &mut all);
        for (lo, hi) in [(10, 40), (0, 16), (47, 64), (0, 1), (5, 8), (63, 64)] {
            let mut part = vec![0.0f32; (hi - lo) * EXIT_FEATURES];
            dec.forward(&input[lo * n..hi * n], &mut part);
            assert_eq!(part, all[lo * EXIT_FEATURES..hi * EXIT_FEATURES], "rows {lo}..{hi}");
        }
        let mut want = vec![0.0f32; rows * EXIT_FEATURES];
        mlp.forward_batch(&input, &mut want);
        for (k, (a, b)) in all.iter().zip(&want).enumerate() {
            assert!((a - b).abs() <= 1e-5 * (1.0 + b.abs()), "value {k}: {a} vs {b}");
        }
        // Exact zeros among the inputs (ReLU zeros downstream) change nothing.
        let sparse: Vec<f32> = input.iter().enumerate().map(|(k, &x)| if k % 3 == 0 { 0.0 } else { x }).collect();
        dec.forward(&sparse, &mut all);
        mlp.forward_batch(&sparse, &mut want);
        assert!(all.iter().zip(&want).all(|(a, b)| (a - b).abs() <= 1e-5 * (1.0 + b.abs())));
    }

    #[test]
    fn decode_refuses_short_buffers() {
        let dec = CpuDecoder::new(&tiny_estimator(4, 3, 8).decoder);
        let mut out = vec![0.0f32; 2 * EXIT_FEATURES];
        assert!(dec.decode(&[0.0; 7], 2, &mut out).is_err());
        assert!(dec.decode(&[0.0; 14], 3, &mut out).is_err());
        assert!(dec.decode(&[0.0; 14], 2, &mut out).is_ok());
        assert_eq!(dec.name(), "cpu");
    }
}
