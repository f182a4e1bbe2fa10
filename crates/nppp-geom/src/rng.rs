//! Per-sample random streams.
//!
//! Every camera sample owns a PCG32 stream keyed by (seed, pixel, sample
//! index), so the image does not depend on thread count, tile order or how
//! paths are batched.

use rand::{Rng, RngCore, SeedableRng};
use rand_pcg::Pcg32;

/// The random stream of one camera sample (or one training ray).
#[derive(Clone, Debug)]
pub struct SampleRng(Pcg32);

/// SplitMix64 finalizer: decorrelates nearby keys before they seed PCG.
pub fn mix64(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

impl SampleRng {
    /// The stream for sample `sample` of item `index` (a pixel, a ray) under `seed`.
    pub fn new(seed: u64, index: u64, sample: u64) -> Self {
        let state = mix64(seed ^ mix64(index.wrapping_mul(0x2545_F491_4F6C_DD1D) ^ sample));
        let stream = mix64(index ^ mix64(seed.wrapping_add(sample << 1)));
        Self(Pcg32::new(state, stream))
    }

    /// A stream from a single 64-bit seed (tests, tools).
    pub fn from_seed(seed: u64) -> Self {
        Self(Pcg32::seed_from_u64(seed))
    }

    /// Uniform in [0, 1): 24 random mantissa bits, never 1.0.
    #[inline]
    pub fn uniform(&mut self) -> f32 {
        (self.0.next_u32() >> 8) as f32 * (1.0 / 16_777_216.0)
    }

    #[inline]
    pub fn uniform2(&mut self) -> glam::Vec2 {
        let a = self.uniform();
        let b = self.uniform();
        glam::Vec2::new(a, b)
    }

    /// A standard normal variate: a ziggurat on one 32-bit draw almost
    /// every time ([`crate::ziggurat`]). Every estimator entry draws 16 of
    /// these per decoder row for the decoder's noise: Box-Muller (a
    /// logarithm, a square root and a cosine each) was 3% of a P = 0 render
    /// on cornell-glass, `rand_distr`'s 64-bit ziggurat 1.7% of a P = 1
    /// render of the default scene (perf).
    #[inline]
    pub fn normal(&mut self) -> f32 {
        crate::ziggurat::standard_normal(|| self.0.next_u32())
    }

    /// Fills `out` with standard normal variates, drawn together from one
    /// 64-bit draw of this stream ([`crate::ziggurat::fill_standard_normals`]):
    /// a decoder row's noise.
    #[inline]
    pub fn fill_normals(&mut self, out: &mut [f32]) {
        let key = self.next_u64();
        crate::ziggurat::fill_standard_normals(key, out);
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0.random()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uniform_is_in_unit_interval_and_mean_half() {
        let mut r = SampleRng::new(1, 2, 3);
        let n = 100_000;
        let mut sum = 0.0f64;
        for _ in 0..n {
            let u = r.uniform();
            assert!((0.0..1.0).contains(&u));
            sum += u as f64;
        }
        assert!((sum / n as f64 - 0.5).abs() < 0.01);
    }

    #[test]
    fn streams_differ_by_key() {
        let a = SampleRng::new(0, 0, 0).uniform();
        let b = SampleRng::new(0, 1, 0).uniform();
        let c = SampleRng::new(0, 0, 1).uniform();
        let d = SampleRng::new(1, 0, 0).uniform();
        assert!(a != b && a != c && a != d && b != c);
        assert_eq!(
            SampleRng::new(5, 6, 7).uniform(),
            SampleRng::new(5, 6, 7).uniform()
        );
    }

    #[test]
    fn normal_has_the_standard_normal_shape() {
        let mut r = SampleRng::from_seed(9);
        let n = 200_000;
        let (mut s, mut s2, mut s4) = (0.0f64, 0.0f64, 0.0f64);
        let (mut beyond_1, mut beyond_2) = (0usize, 0usize);
        for _ in 0..n {
            let x = r.normal() as f64;
            assert!(x.is_finite());
            s += x;
            s2 += x * x;
            s4 += x * x * x * x;
            beyond_1 += usize::from(x.abs() > 1.0);
            beyond_2 += usize::from(x.abs() > 2.0);
        }
        let nf = n as f64;
        let mean = s / nf;
        let var = s2 / nf - mean * mean;
        assert!(mean.abs() < 0.01, "{mean}");
        assert!((var - 1.0).abs() < 0.02, "{var}");
        // Kurtosis 3, and the tails of N(0, 1): P(|x| > 1) = 0.3173,
        // P(|x| > 2) = 0.0455 (standard errors 0.001 and 0.0005 here).
        assert!((s4 / nf - 3.0).abs() < 0.1, "{}", s4 / nf);
        assert!((beyond_1 as f64 / nf - 0.3173).abs() < 0.005);
        assert!((beyond_2 as f64 / nf - 0.0455).abs() < 0.0025);
    }
}
