//! The decoder seam: what turns rows of decoder inputs `[z, r]` into rows of
//! standardized exit features. [`CpuDecoder`] (plain Rust) is the default;
//! another backend (nppp-nn's Burn module on a CPU or GPU) implements
//! [`ExitDecoder`] and is attached with
//! [`EstimatorSampler::set_decoder`](crate::EstimatorSampler::set_decoder).
//! Everything else (latent lookup, noise, the inverse output transform, the
//! fallback when a backend fails) is [`EstimatorSampler::sample_batch`]'s
//! and the same for every backend.

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

/// The decoder in plain Rust: each layer one matrix product.
#[derive(Clone, Debug)]
pub struct CpuDecoder {
    layers: Vec<CpuLayer>,
    inputs: usize,
    /// The widest row any layer reads or writes.
    width: usize,
}

/// A decoder layer stored `[inputs][outputs]` (the transpose of
/// [`crate::Dense`]): row-major for `C = A * W^T` with no transposition in
/// the product.
#[derive(Clone, Debug)]
struct CpuLayer {
    inputs: usize,
    outputs: usize,
    weight_t: Vec<f32>,
    bias: Vec<f32>,
    relu: bool,
}

impl CpuDecoder {
    /// `mlp` must pass [`Mlp::validate`] (the sampler checks it first).
    pub fn new(mlp: &Mlp) -> Self {
        let last = mlp.layers.len().saturating_sub(1);
        let layers: Vec<CpuLayer> = mlp
            .layers
            .iter()
            .enumerate()
            .map(|(li, l)| {
                let mut weight_t = vec![0.0; l.inputs * l.outputs];
                for o in 0..l.outputs {
                    for i in 0..l.inputs {
                        weight_t[i * l.outputs + o] = l.weight[o * l.inputs + i];
                    }
                }
                CpuLayer { inputs: l.inputs, outputs: l.outputs, weight_t, bias: l.bias.clone(), relu: li < last }
            })
            .collect();
        let inputs = mlp.inputs();
        let width = layers.iter().map(|l| l.outputs).max().unwrap_or(0).max(inputs);
        Self { layers, inputs, width }
    }

    /// The decoder on the rows of `input` (as many as both slices hold).
    ///
    /// Each layer runs as one matrix product (`matrixmultiply`, which picks
    /// AVX/FMA kernels at run time): several times faster than row by row on
    /// the wavefront's batches of hundreds of entries. Every batch, however
    /// small, takes this path, so each row's result does not depend on the
    /// other rows of its batch nor on their number: a render's pixels are
    /// the same bits however its entries batch up (thread counts, render
    /// shards that split a tile's samples differently). Equal to
    /// [`Mlp::forward_batch`] within float rounding (the sums run in another
    /// order), not bit for bit.
    pub fn forward(&self, input: &[f32], output: &mut [f32]) {
        let n = self.inputs;
        if n == 0 {
            return;
        }
        let rows = (input.len() / n).min(output.len() / EXIT_FEATURES);
        if rows == 0 {
            return;
        }
        let mut a = vec![0.0f32; rows * self.width];
        let mut b = vec![0.0f32; rows * self.width];
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
