//! Standard normal variates from one 32-bit draw: the ziggurat method
//! (Marsaglia and Tsang 2000, "The Ziggurat Method for Generating Random
//! Variables"), 256 layers, with the layer index and the value taken from
//! separate bits of the draw (Doornik 2005, "An Improved Ziggurat Method to
//! Generate Normal Random Samples", which showed that reusing the bits
//! correlates them).
//!
//! Written here because `rand_distr` 0.5 has no 32-bit path: its
//! `StandardNormal` for `f32` samples an `f64` from a 64-bit draw (two
//! steps of the renderer's PCG32) and converts it (its source says "TODO:
//! use optimal 32-bit implementation"). Every estimator entry draws 16
//! normals per decoder row, 32 on the knots with their vertex head, and
//! those draws were 1.7% of a render of the default scene at P = 1 (perf).
//! This one takes 16 in 39 ns against 68 ns (`cargo bench --bench
//! estimator -- noise`).
//!
//! [`fill_standard_normals`] draws a decoder row's normals together: one
//! 64-bit key from the path's stream, the lanes' bits from a SplitMix64
//! sequence seeded with it, and the ziggurat's rectangle test on every lane
//! in one branch-free pass (the compiler vectorizes it); only the rare lane
//! outside its rectangle takes the scalar path, on a stream of its own.
//! Drawn one at a time through a `&mut` PCG state, an entry's 32 normals
//! were 1.6% of a render of the default scene at P = 1 with picked NEE
//! (perf: 4.8 ns a normal in the render, the state going through memory
//! after every draw).

use std::sync::LazyLock;

/// Layers of the ziggurat (the low 8 bits of a draw pick one).
const LAYERS: usize = 256;
/// Where the tail begins: the base layer's right edge for 256 layers of
/// equal area (Marsaglia and Tsang's `r`).
const TAIL: f64 = 3.654_152_885_361_009;
/// The area of each layer, the base layer's rectangle and tail together.
const AREA: f64 = 4.928_673_233_99e-3;

/// The layers' right edges `x[0] > x[1] = TAIL > ... > x[256] = 0` (x[0]
/// is the base layer's virtual width, its area over the density at TAIL)
/// and the unnormalized density `exp(-x^2 / 2)` at each.
struct Tables {
    x: [f32; LAYERS + 1],
    f: [f32; LAYERS + 1],
}

static TABLES: LazyLock<Tables> = LazyLock::new(|| {
    let pdf = |x: f64| (-0.5 * x * x).exp();
    let mut x = [0.0f64; LAYERS + 1];
    x[0] = AREA / pdf(TAIL);
    x[1] = TAIL;
    for i in 2..LAYERS {
        // Layer i - 1 spans x[i] <= x <= x[i - 1] in height and has area AREA.
        x[i] = (-2.0 * (AREA / x[i - 1] + pdf(x[i - 1])).ln()).sqrt();
    }
    x[LAYERS] = 0.0;
    Tables {
        x: x.map(|v| v as f32),
        f: x.map(|v| pdf(v) as f32),
    }
});

/// One standard normal variate from the 32-bit draws of `next_u32`: one
/// almost every time (98.8% of draws land inside their layer's rectangle),
/// more for the rare edge and tail draws.
#[inline]
pub fn standard_normal(mut next_u32: impl FnMut() -> u32) -> f32 {
    let first = next_u32();
    normal_from_draw(first, next_u32)
}

/// The ziggurat from its first draw `bits` on: `next_u32` supplies any
/// further draws (an edge or tail draw, or a restart).
#[inline]
fn normal_from_draw(mut bits: u32, mut next_u32: impl FnMut() -> u32) -> f32 {
    let t = &*TABLES;
    loop {
        let i = (bits & 0xff) as usize;
        // The high 24 bits as an odd integer in (-2^24, 2^24): exact in
        // f32, symmetric about 0, never 0.
        let u = ((bits >> 8) as i32 * 2 + 1 - (1 << 24)) as f32 * (1.0 / 16_777_216.0);
        let x = u * t.x[i];
        if x.abs() < t.x[i + 1] {
            return x;
        }
        if i == 0 {
            return tail(u, &mut next_u32);
        }
        // Between the layer's rectangle and the curve: accept with the
        // density's height over the layer's span of heights.
        let y = t.f[i] + uniform(&mut next_u32) * (t.f[i + 1] - t.f[i]);
        if y < (-0.5 * x * x).exp() {
            return x;
        }
        bits = next_u32();
    }
}

/// SplitMix64's increment (2^64 over the golden ratio).
const GOLDEN: u64 = 0x9E37_79B9_7F4A_7C15;
/// Lanes drawn together: a decoder row's 16 noise dimensions.
const LANES: usize = 16;
/// Keys the lanes' fallback streams apart from the lanes' own sequence.
const FALLBACK_KEY: u64 = 0xD1B5_4A32_D192_ED03;

/// Fills `out` with independent standard normal variates driven by one
/// 64-bit `key` (see the module doc). Lane `l` takes its first draw from
/// half `l % 2` of output `l / 2` of the SplitMix64 sequence seeded with
/// `key`; a lane whose draw leaves its layer's rectangle (1.2% of them)
/// goes on through the scalar ziggurat on a SplitMix64 stream of its own,
/// 2^32 outputs away from any other lane's.
pub fn fill_standard_normals(key: u64, out: &mut [f32]) {
    let t = &*TABLES;
    for (c, chunk) in out.chunks_mut(LANES).enumerate() {
        let first_output = (c * LANES / 2) as u64;
        let mut bits = [0u32; LANES];
        for (k, pair) in bits.chunks_exact_mut(2).enumerate() {
            let z =
                crate::rng::mix64(key.wrapping_add((first_output + k as u64).wrapping_mul(GOLDEN)));
            pair[0] = z as u32;
            pair[1] = (z >> 32) as u32;
        }
        // The rectangle test on every lane, without branches.
        let mut x = [0.0f32; LANES];
        let mut outside = 0u32;
        for l in 0..LANES {
            let i = (bits[l] & 0xff) as usize;
            let u = ((bits[l] >> 8) as i32 * 2 + 1 - (1 << 24)) as f32 * (1.0 / 16_777_216.0);
            x[l] = u * t.x[i];
            outside |= u32::from(x[l].abs() >= t.x[i + 1]) << l;
        }
        let n = chunk.len();
        match <&mut [f32; LANES]>::try_from(&mut *chunk) {
            // A whole row: stored as one vector (a slice copy calls memcpy).
            Ok(whole) => *whole = x,
            Err(_) => chunk.copy_from_slice(&x[..n]),
        }
        outside &= (1u32 << n) - 1;
        while outside != 0 {
            let l = outside.trailing_zeros() as usize;
            outside &= outside - 1;
            let lane = (c * LANES + l) as u64;
            let mut state = crate::rng::mix64(key ^ FALLBACK_KEY)
                .wrapping_add((lane << 32).wrapping_mul(GOLDEN));
            let next = || {
                let z = crate::rng::mix64(state);
                state = state.wrapping_add(GOLDEN);
                (z >> 32) as u32
            };
            chunk[l] = normal_from_draw(bits[l], next);
        }
    }
}

/// Uniform in [0, 1) from the high 24 bits of a draw.
#[inline]
fn uniform(next_u32: &mut impl FnMut() -> u32) -> f32 {
    (next_u32() >> 8) as f32 * (1.0 / 16_777_216.0)
}

/// A draw from the normal's tail beyond `TAIL` (Marsaglia 1964), on the
/// side of `u`'s sign.
#[cold]
fn tail(u: f32, next_u32: &mut impl FnMut() -> u32) -> f32 {
    let r = TAIL as f32;
    loop {
        // 1 - uniform is in (0, 1]: its logarithm is finite.
        let x = (1.0 - uniform(next_u32)).ln() / r;
        let y = (1.0 - uniform(next_u32)).ln();
        if -2.0 * y >= x * x {
            return if u < 0.0 { x - r } else { r - x };
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The layers tile the density: equal areas, the last edge at 0.
    #[test]
    fn layers_have_equal_area_and_end_at_zero() {
        let t = &*TABLES;
        for i in 1..LAYERS - 1 {
            let area = t.x[i] as f64 * (t.f[i + 1] as f64 - t.f[i] as f64);
            assert!((area / AREA - 1.0).abs() < 1e-4, "layer {i}: {area}");
        }
        // The recurrence lands next to 0 by itself: the constants match.
        let pdf = |x: f64| (-0.5 * x * x).exp();
        let second_last = t.x[LAYERS - 1] as f64;
        assert!((AREA / second_last + pdf(second_last) - 1.0).abs() < 1e-4);
        assert_eq!(t.x[LAYERS], 0.0);
    }

    /// Binned against the normal CDF: 2 million draws in 40 bins over
    /// [-5, 5] plus the two tails, a chi-square test at a level that a
    /// correct sampler fails once in 10^5 runs (and this one is seeded).
    #[test]
    fn draws_follow_the_normal_cdf() {
        let mut state = 0x853c_49e6_748f_ea9bu64;
        let mut next = move || {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (state >> 32) as u32
        };
        let draws: Vec<f32> = (0..2_000_000).map(|_| standard_normal(&mut next)).collect();
        assert_normal(&draws);
    }

    /// `draws` binned against the normal CDF (the chi-square test above),
    /// and their share beyond the ziggurat's base, drawn by `tail`.
    fn assert_normal(draws: &[f32]) {
        let n = draws.len();
        let bins = 40;
        let mut counts = vec![0u64; bins + 2];
        let mut beyond = 0u64;
        for &x in draws {
            let x = x as f64;
            assert!(x.is_finite());
            beyond += u64::from(x.abs() > TAIL);
            let k = if x < -5.0 {
                0
            } else if x >= 5.0 {
                bins + 1
            } else {
                1 + ((x + 5.0) / 10.0 * bins as f64) as usize
            };
            counts[k.min(bins + 1)] += 1;
        }
        let cdf = |x: f64| 0.5 * (1.0 + erf(x / std::f64::consts::SQRT_2));
        let mut chi2 = 0.0;
        for (k, &c) in counts.iter().enumerate() {
            let (lo, hi) = match k {
                0 => (f64::NEG_INFINITY, -5.0),
                k if k == bins + 1 => (5.0, f64::INFINITY),
                k => (
                    -5.0 + 10.0 * (k - 1) as f64 / bins as f64,
                    -5.0 + 10.0 * k as f64 / bins as f64,
                ),
            };
            let p = if hi.is_infinite() {
                1.0 - cdf(lo)
            } else if lo.is_infinite() {
                cdf(hi)
            } else {
                cdf(hi) - cdf(lo)
            };
            let e = p * n as f64;
            if e > 5.0 {
                chi2 += (c as f64 - e).powi(2) / e;
            }
        }
        // About 38 degrees of freedom (the bins expecting 5 or more): the
        // 0.99999 quantile of chi-square(38) is about 86.
        assert!(chi2 < 86.0, "chi-square {chi2}");
        // P(|x| > 3.654) = 2.58e-4: 516 of 2 M.
        let expected = 2.58e-4 * n as f64;
        assert!(
            (beyond as f64 - expected).abs() < 5.0 * expected.sqrt(),
            "{beyond} beyond the base, {expected:.0} expected"
        );
    }

    /// The batch sampler against the same CDF, over keys from a PCG
    /// stream and row lengths 16 (a decoder row) and 23 (a partial chunk),
    /// and with no correlation between lanes of a row or between rows of
    /// consecutive keys.
    #[test]
    fn batches_follow_the_normal_cdf_and_lanes_are_uncorrelated() {
        let mut rng = crate::SampleRng::from_seed(7);
        let mut draws = Vec::with_capacity(2_000_000);
        let mut prods = [0.0f64; 3];
        let mut rows = 0usize;
        for len in [16usize, 23] {
            let mut row = vec![0.0f32; len];
            let mut prev = vec![0.0f32; len];
            while draws.len() < 1_000_000 * (1 + (len == 23) as usize) {
                fill_standard_normals(rng.next_u64(), &mut row);
                // Neighbouring lanes, lanes 8 apart, and the same lane of
                // the row before.
                prods[0] += (row[0] * row[1]) as f64;
                prods[1] += (row[3] * row[11]) as f64;
                prods[2] += (row[5] * prev[5]) as f64;
                rows += 1;
                draws.extend_from_slice(&row);
                prev.copy_from_slice(&row);
            }
        }
        assert_normal(&draws);
        // Each mean product has standard deviation 1 / sqrt(rows).
        for p in prods {
            let z = p / (rows as f64).sqrt();
            assert!(z.abs() < 5.0, "lane correlation z = {z}");
        }
    }

    /// Abramowitz and Stegun 7.1.26 is too coarse for 2 M draws; this is
    /// the series/continued fraction pair, good to 1e-12 on the range used.
    fn erf(x: f64) -> f64 {
        if x.abs() < 2.5 {
            // Taylor series: erf x = 2/sqrt(pi) sum (-1)^n x^(2n+1) / (n! (2n+1)).
            let mut term = x;
            let mut sum = x;
            for n in 1..200 {
                term *= -x * x / n as f64;
                let add = term / (2 * n + 1) as f64;
                sum += add;
                if add.abs() < 1e-17 {
                    break;
                }
            }
            sum * 2.0 / std::f64::consts::PI.sqrt()
        } else {
            // erfc x = exp(-x^2)/sqrt(pi) / (x + 1/2/(x + 1/(x + 3/2/(x + ...)))).
            let ax = x.abs();
            let mut cf = ax;
            for k in (1..60).rev() {
                cf = ax + (k as f64 / 2.0) / cf;
            }
            let erfc = (-ax * ax).exp() / std::f64::consts::PI.sqrt() / cf;
            (1.0 - erfc).copysign(x)
        }
    }
}
