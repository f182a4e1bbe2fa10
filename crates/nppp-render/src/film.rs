//! The film: per-pixel sums of radiance samples, kept exactly.
//!
//! Each sample's f32 radiance is added to a 320-bit fixed-point integer
//! ([`ExactSum`]), so a pixel's sum does not depend on the order in which its
//! samples were added or on how they were grouped. That is what lets a render
//! split by sample range over machines (`nppp render --shard`) merge into the
//! same bits as one machine's render: integer addition is associative, f64
//! addition is not. It also means a long render cannot drift.
//!
//! No crate offers a fixed-size, order-independent accumulator for f32
//! (the superaccumulators, e.g. `xsum`, are f64-wide and several hundred bytes
//! per value); this one is 40 bytes and a few integer additions per sample.

use glam::Vec3;

/// Exponent of the unit of [`ExactSum`]: one unit is 2^-149, f32's
/// smallest subnormal, so every finite f32 is a whole number of units and
/// is added exactly. (A unit of 2^-95 dropped samples below 2.6e-29: a lamp
/// of radiance 1e-30, valid under the contract's arbitrary units, rendered
/// black.)
pub const EXACT_SUM_UNIT_EXP: i32 = -149;
/// 64-bit limbs of an [`ExactSum`].
pub const EXACT_SUM_LIMBS: usize = 5;

/// The sum of up to 2^32 f32 values as a 320-bit two's-complement integer in
/// units of 2^-149: f32's largest value (< 2^128) times 2^32 samples is
/// < 2^160 = 2^309 units, so no sum of a u32 count of finite samples
/// overflows. Limbs are little-endian.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct ExactSum(pub [u64; EXACT_SUM_LIMBS]);

impl ExactSum {
    /// Adds `x` exactly. `x` must be finite.
    #[inline]
    pub fn add_f32(&mut self, x: f32) {
        let bits = x.to_bits();
        let biased = ((bits >> 23) & 0xff) as i32;
        let fraction = u64::from(bits & 0x7f_ffff);
        // x = mantissa * 2^exp
        let (mantissa, exp) = if biased == 0 {
            (fraction, -149)
        } else {
            (fraction | 0x80_0000, biased - 150)
        };
        if mantissa == 0 {
            return;
        }
        // 0 <= shift <= 104 + 149 = 253: the 24-bit mantissa spans at most
        // two limbs, the upper one at most limb 4.
        let shift = (exp - EXACT_SUM_UNIT_EXP) as u32;
        let (limb, offset) = ((shift / 64) as usize, shift % 64);
        let wide = u128::from(mantissa) << offset;
        let mut v = [0u64; EXACT_SUM_LIMBS];
        v[limb] = wide as u64;
        v[limb + 1] = (wide >> 64) as u64;
        if bits >> 31 == 0 {
            self.add(&ExactSum(v));
        } else {
            self.add(&ExactSum(v).negated());
        }
    }

    /// Adds another sum (modulo 2^320, which the bound above never reaches).
    #[inline]
    pub fn add(&mut self, o: &ExactSum) {
        let mut carry = false;
        for (a, b) in self.0.iter_mut().zip(o.0) {
            let (s1, c1) = a.overflowing_add(b);
            let (s2, c2) = s1.overflowing_add(carry as u64);
            *a = s2;
            carry = c1 | c2;
        }
    }

    fn negated(mut self) -> ExactSum {
        for l in &mut self.0 {
            *l = !*l;
        }
        let mut one = ExactSum::default();
        one.0[0] = 1;
        self.add(&one);
        self
    }

    fn is_negative(&self) -> bool {
        self.0[EXACT_SUM_LIMBS - 1] >> 63 == 1
    }

    /// The sum as an f64: the top 128 significant bits rounded to nearest,
    /// a deterministic function of the integer.
    pub fn to_f64(&self) -> f64 {
        if self.is_negative() {
            return -self.negated().to_f64();
        }
        let Some(top) = (0..EXACT_SUM_LIMBS).rev().find(|&i| self.0[i] != 0) else {
            return 0.0;
        };
        let (wide, low_limb) = if top == 0 {
            (u128::from(self.0[0]), 0)
        } else {
            (
                (u128::from(self.0[top]) << 64) | u128::from(self.0[top - 1]),
                top - 1,
            )
        };
        // An exact power of two: the product only moves the exponent.
        wide as f64 * 2f64.powi(64 * low_limb as i32 + EXACT_SUM_UNIT_EXP)
    }
}

/// One pixel's accumulated samples: exact per-channel sums of the finite
/// samples, how many they were, and how many were dropped for being NaN or
/// infinite (counted so a user learns of them; never averaged in).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct PixelSum {
    pub sum: [ExactSum; 3],
    pub valid: u32,
    pub dropped: u32,
}

/// The image of a row-major film `width` pixels wide: every pixel's mean,
/// as [`crate::render()`] computes it.
pub fn film_image(width: u32, height: u32, film: &[PixelSum]) -> crate::Image {
    use rayon::prelude::*;
    let mut img = crate::Image::new(width, height);
    img.pixels
        .par_iter_mut()
        .zip(film)
        .for_each(|(o, p)| *o = p.mean());
    img
}

impl PixelSum {
    #[inline]
    pub fn add(&mut self, l: Vec3) {
        if l.is_finite() {
            self.sum[0].add_f32(l.x);
            self.sum[1].add_f32(l.y);
            self.sum[2].add_f32(l.z);
            self.valid += 1;
        } else {
            self.dropped += 1;
        }
    }

    /// Adds another pixel's samples (the same pixel of another sample range).
    pub fn merge(&mut self, o: &PixelSum) {
        for (a, b) in self.sum.iter_mut().zip(&o.sum) {
            a.add(b);
        }
        self.valid += o.valid;
        self.dropped += o.dropped;
    }

    /// The pixel's value: the mean of its finite samples (black if none).
    pub fn mean(&self) -> [f32; 3] {
        if self.valid == 0 {
            return [0.0; 3];
        }
        let n = f64::from(self.valid);
        self.sum.map(|s| (s.to_f64() / n) as f32)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn sum_of(xs: &[f32]) -> ExactSum {
        let mut s = ExactSum::default();
        for &x in xs {
            s.add_f32(x);
        }
        s
    }

    #[test]
    fn exact_where_f64_is_not() {
        // 1e30 + 1 - 1e30 in f64 is 0; the exact sum keeps the 1.
        let s = sum_of(&[1e30, 1.0, -1e30]);
        assert_eq!(s.to_f64(), 1.0);
        assert_eq!(sum_of(&[f32::MAX; 4]).to_f64(), 4.0 * f32::MAX as f64);
        assert_eq!(sum_of(&[-2.5, 0.5]).to_f64(), -2.0);
        assert_eq!(sum_of(&[]).to_f64(), 0.0);
        // Every f32 counts, the smallest subnormal included.
        let tiny = f32::from_bits(1);
        assert_eq!(sum_of(&[tiny]).to_f64(), 2f64.powi(-149));
        assert_eq!(sum_of(&[tiny, tiny, -tiny]).to_f64(), 2f64.powi(-149));
        assert_eq!(sum_of(&[2f32.powi(-90)]).to_f64(), 2f64.powi(-90));
        assert_eq!(sum_of(&[1e-30, 1e30, -1e30]).to_f64(), 1e-30f32 as f64);
    }

    #[test]
    fn the_largest_sum_does_not_overflow() {
        let mut s = ExactSum::default();
        let one = sum_of(&[f32::MAX]);
        // 2^32 - 1 samples at f32::MAX, added by doubling.
        let mut p = one;
        for _ in 0..32 {
            s.add(&p);
            let q = p;
            p.add(&q);
        }
        assert!(!s.is_negative());
        let want = f32::MAX as f64 * (2f64.powi(32) - 1.0);
        assert!((s.to_f64() / want - 1.0).abs() < 1e-15);
    }

    proptest! {
        /// Any split of the samples into groups, summed in any order, gives
        /// the same bits: what merging render shards relies on.
        #[test]
        fn grouping_and_order_do_not_matter(
            xs in prop::collection::vec(
                prop_oneof![-1e6f32..1e6, 0f32..1e-20, -1e-35f32..1e-35, -1e30f32..1e30,
                    Just(0.0f32)], 1..64),
            cut in 0usize..64,
        ) {
            let cut = cut.min(xs.len());
            let whole = sum_of(&xs);
            let mut a = sum_of(&xs[..cut]);
            let b = sum_of(&xs[cut..]);
            let mut rev: Vec<f32> = xs.clone();
            rev.reverse();
            prop_assert_eq!(sum_of(&rev), whole);
            let mut ba = b;
            ba.add(&a);
            a.add(&b);
            prop_assert_eq!(a, whole);
            prop_assert_eq!(ba, whole);
        }

        /// The f64 value is the true sum (exactly when it fits 53 bits).
        #[test]
        fn value_matches_f64_sum_of_integers(xs in prop::collection::vec(-1_000_000i32..1_000_000, 0..100)) {
            let fs: Vec<f32> = xs.iter().map(|&x| x as f32).collect();
            let want: f64 = fs.iter().map(|&x| x as f64).sum();
            prop_assert_eq!(sum_of(&fs).to_f64(), want);
        }

        #[test]
        fn pixel_merge_is_adding_the_samples(
            xs in prop::collection::vec(0f32..100.0, 0..40),
            cut in 0usize..40,
        ) {
            let cut = cut.min(xs.len());
            let mut whole = PixelSum::default();
            let (mut a, mut b) = (PixelSum::default(), PixelSum::default());
            for (i, &x) in xs.iter().enumerate() {
                let v = Vec3::new(x, x * 0.5, if i % 7 == 0 { f32::NAN } else { x });
                whole.add(v);
                if i < cut { a.add(v) } else { b.add(v) }
            }
            b.merge(&a);
            prop_assert_eq!(b, whole);
            prop_assert_eq!(b.mean(), whole.mean());
        }
    }
}
