//! The CPU decoder's one numeric kernel: a dense layer on a batch of rows,
//! `C = act(A W + b)`, with `W` packed once when the estimator loads.
//!
//! Written here rather than taken from `matrixmultiply` (which the decoder
//! used before) because the decoder's products are small and always the
//! same: a wavefront step's 70-130 rows against a 32- or 64-wide layer.
//! `matrixmultiply::sgemm` packs both operands on every call, and on these
//! shapes its packing was a third of the decoder's time (perf of a
//! cornell-glass render at P = 1: `pack_avx512` 1.6% of all samples beside
//! `sgemm_kernel` 3.1%); bias and ReLU then took another pass over the
//! output. This kernel reads the weights as packed at load, keeps a block
//! of rows' outputs in registers across the whole inner dimension, and
//! adds the bias and applies ReLU before storing (criterion,
//! `estimator_decoder_rows`; BENCHMARKS.md, "Cheaper entries").
//!
//! The instruction set is picked at run time: AVX-512F, AVX2 with FMA, or
//! on any other CPU `matrixmultiply` as before. Each output element is the
//! same sum in the same order (`b + x_0 w_0 + x_1 w_1 + ...`) whichever
//! block its row falls in, so a row's result does not depend on the other rows of
//! its batch nor on their number: a render's pixels are the same bits
//! however its entries batch up. Different instruction sets round
//! differently (fused or not), so results agree across machines within
//! float rounding, not bit for bit, as they did with `matrixmultiply`.

/// Floats in one column block of the packed weights (one AVX-512 register).
pub const LANES: usize = 16;

/// The instruction set the kernel runs on, detected once per decoder.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum KernelIsa {
    /// 32 registers of 16 floats: blocks of 4 rows x 64 outputs, or 8
    /// rows x 32 in a layer at most 32 wide.
    Avx512,
    /// 16 registers of 8 floats, fused multiply-add: 2 rows x 32 outputs.
    Avx2Fma,
    /// Any other CPU: `matrixmultiply`'s kernels (NEON on ARM, SSE2 on an
    /// older x86), the bias and ReLU in a second pass.
    Generic,
}

impl KernelIsa {
    /// The widest this CPU runs.
    pub fn detect() -> Self {
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx512f") {
                return Self::Avx512;
            }
            if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
                return Self::Avx2Fma;
            }
        }
        Self::Generic
    }

    /// Those that run on this CPU (for tests and benchmarks).
    pub fn available() -> Vec<Self> {
        let best = Self::detect();
        let mut list = vec![Self::Generic];
        if best != Self::Generic {
            list.push(Self::Avx2Fma);
        }
        if best == Self::Avx512 {
            list.push(Self::Avx512);
        }
        list
    }

    pub fn name(self) -> &'static str {
        match self {
            Self::Avx512 => "avx512",
            Self::Avx2Fma => "avx2-fma",
            Self::Generic => "matrixmultiply",
        }
    }
}

/// A dense layer packed for [`PackedLayer::forward`]: weights
/// `[inputs][padded]` (the transpose of [`crate::Dense`]'s, so that a
/// row's outputs are contiguous) and the bias, both zero-padded to a
/// multiple of [`LANES`] outputs.
#[derive(Clone, Debug)]
pub struct PackedLayer {
    pub inputs: usize,
    pub outputs: usize,
    /// `outputs` rounded up to a multiple of [`LANES`]: the row stride this
    /// layer writes.
    pub padded: usize,
    weight: Vec<f32>,
    bias: Vec<f32>,
    relu: bool,
}

impl PackedLayer {
    /// Packs `weight` (row-major `[outputs][inputs]`, as [`crate::Dense`]
    /// stores it) and `bias`.
    pub fn new(inputs: usize, outputs: usize, weight: &[f32], bias: &[f32], relu: bool) -> Self {
        let padded = outputs.div_ceil(LANES) * LANES;
        let mut packed = vec![0.0; inputs * padded];
        for o in 0..outputs {
            for i in 0..inputs {
                packed[i * padded + o] = weight[o * inputs + i];
            }
        }
        let mut b = vec![0.0; padded];
        b[..outputs].copy_from_slice(bias);
        Self { inputs, outputs, padded, weight: packed, bias: b, relu }
    }

    /// `c` (`rows` rows of stride `padded`, padding included) from `a`
    /// (`rows` rows of stride `a_stride`, the first `inputs` of each read).
    /// Panics if either is too short.
    pub fn forward(&self, isa: KernelIsa, a: &[f32], a_stride: usize, rows: usize, c: &mut [f32]) {
        assert!(a_stride >= self.inputs && (rows == 0 || a.len() >= (rows - 1) * a_stride + self.inputs));
        assert!(c.len() >= rows * self.padded);
        match isa {
            #[cfg(target_arch = "x86_64")]
            // SAFETY: the guard checked that this CPU has the features the
            // function is compiled for (`KernelIsa` is a public enum, so a
            // caller may name one it lacks: that falls through to the
            // generic product); the slices' sizes were checked above.
            KernelIsa::Avx512 if std::arch::is_x86_feature_detected!("avx512f") => unsafe { self.forward_avx512(a, a_stride, rows, c) },
            #[cfg(target_arch = "x86_64")]
            // SAFETY: as above.
            KernelIsa::Avx2Fma if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") => unsafe {
                self.forward_avx2(a, a_stride, rows, c)
            },
            _ => self.forward_generic(a, a_stride, rows, c),
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f")]
    fn forward_avx512(&self, a: &[f32], a_stride: usize, rows: usize, c: &mut [f32]) {
        // A layer of at most two column blocks (the 32-wide decoders, the
        // 13-wide heads) takes 8 rows at a time: 4 rows would leave 8 or 4
        // independent accumulators, too few to hide the fused
        // multiply-add's latency, where 8 rows keep 16 or 8 of the 32
        // registers busy (the knot's decoder, 128-row batches, the same
        // process alternating, best of 40 rounds on the 2-core Xeon: 41.4
        // ns a row against 45.1 idle, 108 against 126 with the other core
        // busy). The sums are the same, bit for bit.
        // SAFETY: this function runs only where AVX-512F is (see `forward`).
        unsafe {
            if self.padded <= 2 * LANES {
                self.forward_simd::<std::arch::x86_64::__m512, 8, 2>(a, a_stride, rows, c)
            } else {
                self.forward_simd::<std::arch::x86_64::__m512, 4, 4>(a, a_stride, rows, c)
            }
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    fn forward_avx2(&self, a: &[f32], a_stride: usize, rows: usize, c: &mut [f32]) {
        // SAFETY: this function runs only where AVX2 and FMA are.
        unsafe { self.forward_simd::<x86::Ymm2, 2, 2>(a, a_stride, rows, c) }
    }

    /// `matrixmultiply`'s product (its own kernels for the CPU: NEON on
    /// ARM, SSE2 on an x86 without AVX2), then the bias and ReLU.
    fn forward_generic(&self, a: &[f32], a_stride: usize, rows: usize, c: &mut [f32]) {
        let (k, m, p) = (self.inputs, self.outputs, self.padded);
        for row in c[..rows * p].chunks_exact_mut(p) {
            row.copy_from_slice(&self.bias);
        }
        // C (rows x m, row stride p) += A (rows x k, row stride a_stride)
        // * W (k x m, row stride p).
        // SAFETY: `forward` checked that `a` holds `rows` rows of `k` floats
        // at stride `a_stride` and `c` `rows` rows of `p`; `weight` holds
        // `k` rows of `p >= m`; `c` aliases neither.
        unsafe {
            matrixmultiply::sgemm(
                rows,
                k,
                m,
                1.0,
                a.as_ptr(),
                a_stride as isize,
                1,
                self.weight.as_ptr(),
                p as isize,
                1,
                1.0,
                c.as_mut_ptr(),
                p as isize,
                1,
            );
        }
        if self.relu {
            c[..rows * p].iter_mut().for_each(|v| *v = v.max(0.0));
        }
    }

    /// Walks the output in blocks of `R` rows x up to `V` column blocks
    /// (`V * LANES` outputs), the rows left over four at a time (where `R`
    /// is more) and then one at a time, and a narrow layer's last columns
    /// in fewer blocks. Every element is computed by
    /// [`x86::block`] with the same sum order, so a row's result does not
    /// depend on the block it falls in.
    ///
    /// # Safety
    /// The CPU must have the features `G`'s operations are compiled for;
    /// the caller is a `#[target_feature]` function that enables them, into
    /// which this and the blocks inline.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    unsafe fn forward_simd<G: x86::Lanes16, const R: usize, const V: usize>(&self, a: &[f32], a_stride: usize, rows: usize, c: &mut [f32]) {
        let col_blocks = self.padded / LANES;
        let mut col = 0;
        while col < col_blocks {
            let nv = (col_blocks - col).min(V);
            let mut row = 0;
            // SAFETY (all blocks): the caller's features; `block` checks
            // the slices.
            while row + R <= rows {
                unsafe { x86::block_v::<G, R, V>(nv, self, a, a_stride, row, col, c) };
                row += R;
            }
            while R > 4 && row + 4 <= rows {
                unsafe { x86::block_v::<G, 4, V>(nv, self, a, a_stride, row, col, c) };
                row += 4;
            }
            while row < rows {
                unsafe { x86::block_v::<G, 1, V>(nv, self, a, a_stride, row, col, c) };
                row += 1;
            }
            col += nv;
        }
    }
}

/// The x86 blocks: `R` rows x `V` column blocks of [`LANES`] outputs, the
/// accumulators in registers from the bias to the store (ReLU applied
/// there), one fused multiply-add per input and register in input order.
/// One generic block serves both instruction sets through [`Lanes16`]: a
/// column block is one AVX-512 register or two AVX2 ones.
#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::{LANES, PackedLayer};
    use std::arch::x86_64::*;

    /// [`LANES`] floats in registers, and the five operations a block does
    /// on them. Every method must be called only where its instruction set
    /// is enabled (see [`PackedLayer::forward_simd`]).
    pub(super) trait Lanes16: Copy {
        /// # Safety
        /// `p` is valid for reading [`LANES`] floats.
        unsafe fn load(p: *const f32) -> Self;
        unsafe fn splat(x: f32) -> Self;
        /// `x * w + acc`, fused.
        unsafe fn fmadd(x: Self, w: Self, acc: Self) -> Self;
        unsafe fn relu(self) -> Self;
        /// # Safety
        /// `p` is valid for writing [`LANES`] floats.
        unsafe fn store(self, p: *mut f32);
    }

    impl Lanes16 for __m512 {
        #[inline(always)]
        unsafe fn load(p: *const f32) -> Self {
            unsafe { _mm512_loadu_ps(p) }
        }
        #[inline(always)]
        unsafe fn splat(x: f32) -> Self {
            unsafe { _mm512_set1_ps(x) }
        }
        #[inline(always)]
        unsafe fn fmadd(x: Self, w: Self, acc: Self) -> Self {
            unsafe { _mm512_fmadd_ps(x, w, acc) }
        }
        #[inline(always)]
        unsafe fn relu(self) -> Self {
            unsafe { _mm512_max_ps(self, _mm512_setzero_ps()) }
        }
        #[inline(always)]
        unsafe fn store(self, p: *mut f32) {
            unsafe { _mm512_storeu_ps(p, self) }
        }
    }

    /// Two AVX2 registers: a column block of [`LANES`] floats.
    #[derive(Clone, Copy)]
    pub(super) struct Ymm2([__m256; 2]);

    impl Lanes16 for Ymm2 {
        #[inline(always)]
        unsafe fn load(p: *const f32) -> Self {
            unsafe { Ymm2([_mm256_loadu_ps(p), _mm256_loadu_ps(p.add(8))]) }
        }
        #[inline(always)]
        unsafe fn splat(x: f32) -> Self {
            unsafe { Ymm2([_mm256_set1_ps(x); 2]) }
        }
        #[inline(always)]
        unsafe fn fmadd(x: Self, w: Self, acc: Self) -> Self {
            unsafe { Ymm2([_mm256_fmadd_ps(x.0[0], w.0[0], acc.0[0]), _mm256_fmadd_ps(x.0[1], w.0[1], acc.0[1])]) }
        }
        #[inline(always)]
        unsafe fn relu(self) -> Self {
            unsafe { Ymm2(self.0.map(|v| _mm256_max_ps(v, _mm256_setzero_ps()))) }
        }
        #[inline(always)]
        unsafe fn store(self, p: *mut f32) {
            unsafe {
                _mm256_storeu_ps(p, self.0[0]);
                _mm256_storeu_ps(p.add(8), self.0[1]);
            }
        }
    }

    /// [`block`] with `v <= V` column blocks, monomorphized per width.
    ///
    /// # Safety
    /// As [`Lanes16`]'s methods.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    pub(super) unsafe fn block_v<G: Lanes16, const R: usize, const V: usize>(
        v: usize,
        l: &PackedLayer,
        a: &[f32],
        a_stride: usize,
        row: usize,
        col: usize,
        c: &mut [f32],
    ) {
        // SAFETY: the caller's features.
        unsafe {
            match v {
                4 if V >= 4 => block::<G, R, 4>(l, a, a_stride, row, col, c),
                3 if V >= 3 => block::<G, R, 3>(l, a, a_stride, row, col, c),
                2 if V >= 2 => block::<G, R, 2>(l, a, a_stride, row, col, c),
                _ => block::<G, R, 1>(l, a, a_stride, row, col, c),
            }
        }
    }

    /// Rows `row..row + R`, column blocks `col..col + V`.
    ///
    /// # Safety
    /// As [`Lanes16`]'s methods; the slices are checked here.
    #[inline(always)]
    unsafe fn block<G: Lanes16, const R: usize, const V: usize>(
        l: &PackedLayer,
        a: &[f32],
        a_stride: usize,
        row: usize,
        col: usize,
        c: &mut [f32],
    ) {
        assert!(a.len() >= (row + R - 1) * a_stride + l.inputs);
        assert!((col + V) * LANES <= l.padded && c.len() >= (row + R) * l.padded);
        assert!(l.weight.len() == l.inputs * l.padded && l.bias.len() == l.padded);
        let (p, c0) = (l.padded, col * LANES);
        // SAFETY: the asserts bound every offset below: bias and weight
        // rows hold `padded` floats and `c0 + V * LANES <= padded`; rows
        // `row..row + R` of `a` hold `inputs` floats from `r * a_stride`;
        // those of `c` hold `padded` floats from `r * padded`.
        unsafe {
            let bias = l.bias.as_ptr().add(c0);
            let bias: [G; V] = std::array::from_fn(|v| G::load(bias.add(v * LANES)));
            let mut acc: [[G; V]; R] = [bias; R];
            let x0 = a.as_ptr().add(row * a_stride);
            let w0 = l.weight.as_ptr().add(c0);
            for i in 0..l.inputs {
                let w_i = w0.add(i * p);
                let w: [G; V] = std::array::from_fn(|v| G::load(w_i.add(v * LANES)));
                for (r, acc_r) in acc.iter_mut().enumerate() {
                    let x = G::splat(*x0.add(r * a_stride + i));
                    for (s, &w_v) in acc_r.iter_mut().zip(&w) {
                        *s = G::fmadd(x, w_v, *s);
                    }
                }
            }
            let out0 = c.as_mut_ptr().add(row * p + c0);
            for (r, acc_r) in acc.iter().enumerate() {
                for (v, &s) in acc_r.iter().enumerate() {
                    let y = if l.relu { s.relu() } else { s };
                    y.store(out0.add(r * p + v * LANES));
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn layer(inputs: usize, outputs: usize, relu: bool, seed: u32) -> (PackedLayer, Vec<f32>, Vec<f32>) {
        let w: Vec<f32> =
            (0..inputs * outputs).map(|k| (((k as u32).wrapping_mul(2654435761) ^ seed) % 1000) as f32 / 500.0 - 1.0).collect();
        let b: Vec<f32> = (0..outputs).map(|k| (k as f32 * 0.37).sin()).collect();
        (PackedLayer::new(inputs, outputs, &w, &b, relu), w, b)
    }

    fn reference(w: &[f32], b: &[f32], inputs: usize, x: &[f32], relu: bool) -> Vec<f32> {
        b.iter()
            .enumerate()
            .map(|(o, &bo)| {
                let y = bo + (0..inputs).map(|i| w[o * inputs + i] as f64 * x[i] as f64).sum::<f64>() as f32;
                if relu { y.max(0.0) } else { y }
            })
            .collect()
    }

    /// Every instruction set, every width the blocks split into (16 to
    /// 80 outputs, a 13-wide head) and row counts around the block sizes:
    /// the product within float rounding, padding zero, and each row the
    /// same bits alone as in any batch.
    #[test]
    fn matches_the_product_on_every_isa_and_shape() {
        for isa in KernelIsa::available() {
            for (inputs, outputs, relu) in
                [(32, 64, true), (64, 13, false), (7, 80, true), (64, 48, true), (3, 16, false), (32, 32, true), (32, 13, false)]
            {
                let (l, w, b) = layer(inputs, outputs, relu, 7);
                let stride = inputs + 3;
                for rows in [0usize, 1, 2, 3, 4, 5, 8, 9, 17, 70] {
                    let a: Vec<f32> = (0..rows * stride).map(|k| ((k * 37 % 29) as f32 - 14.0) / 6.0).collect();
                    let mut c = vec![f32::NAN; rows * l.padded];
                    l.forward(isa, &a, stride, rows, &mut c);
                    for r in 0..rows {
                        let want = reference(&w, &b, inputs, &a[r * stride..], relu);
                        let got = &c[r * l.padded..(r + 1) * l.padded];
                        for (o, (&g, &e)) in got.iter().zip(&want).enumerate() {
                            assert!(
                                (g - e).abs() <= 1e-5 * (1.0 + e.abs() * inputs as f32),
                                "{isa:?} {inputs}x{outputs} row {r} out {o}: {g} vs {e}"
                            );
                        }
                        assert!(got[outputs..].iter().all(|&g| g == 0.0), "{isa:?}: padding not zero");
                        let mut alone = vec![0.0; l.padded];
                        l.forward(isa, &a[r * stride..(r + 1) * stride], stride, 1, &mut alone);
                        assert_eq!(alone, got, "{isa:?} {inputs}x{outputs}: row {r} of {rows} differs alone");
                    }
                }
            }
        }
    }

    #[test]
    #[should_panic]
    fn refuses_a_short_output() {
        let (l, _, _) = layer(4, 20, true, 1);
        let mut c = vec![0.0; 20];
        l.forward(KernelIsa::Generic, &[0.0; 8], 4, 2, &mut c);
    }
}
