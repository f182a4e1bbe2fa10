//! Where the entry mask's answer is known without interpolating it: a coarse
//! table of the mask grid's sign, built when an estimator is loaded.
//!
//! Every chord that reaches an estimator's sphere asks the mask whether it
//! would hit the object (`EstimatorSampler::hits`), and a full answer is a
//! quadrilinear interpolation of 16 grid nodes: 16 scattered reads in an
//! 8 MiB grid, cache misses for incoherent rays (`perf`: the grid lookups
//! were 5.7% of a render of cornell-glass at P = 1, the mask's included).
//! The interpolated logit is a convex combination of its cell's corners, so
//! where every corner of a cell has the same sign, so does every point in
//! it. This table records, per block of `FACTOR`^4 fine cells, whether all
//! of the block's nodes are hits, all misses, or mixed; a lookup reads one
//! byte of a table that stays in the cache (`FACTOR` 2 on the 64^4 mask:
//! 32^4 blocks, 2 bits each, 256 KiB) and interpolates only in mixed
//! blocks, near the mask's hit/miss boundary. The answer is the
//! interpolation's answer in every case: a block counts as certain only
//! with a margin far above the interpolation's rounding error.
//!
//! On cornell-glass at P = 1 the table answers 56% of the mask lookups
//! (a third of its blocks are mixed; with `FACTOR` 4, 16 KiB, it answered
//! only 22%). A hit test takes 44 ns instead of 88 (criterion,
//! `estimator_grid_lookup/mask_64^4_4bit`, uniform chords); renders keep
//! the same image and take 1-5% less time (BENCHMARKS.md, "cornell-glass").
//! Building the table takes about 25 ms on two cores for a 64^4 mask.

use crate::grid::{QuantizedGrid, cell_of};
use crate::quant::get_code;
use rayon::prelude::*;

/// Fine cells per block along each axis.
pub const FACTOR: usize = 2;

/// What the mask answers everywhere in a block of cells.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MaskSign {
    /// Every chord in the block hits (interpolated logit > 0).
    Hit,
    /// Every chord in the block misses.
    Miss,
    /// The block holds the hit/miss boundary: interpolate.
    Mixed,
}

const MIXED: u8 = 0;
const HIT: u8 = 1;
const MISS: u8 = 2;

/// The sign table of a one-channel grid (see the module doc).
#[derive(Clone, Debug)]
pub struct MaskSignTable {
    /// The mask grid's resolution.
    res: usize,
    /// Blocks per axis.
    blocks: usize,
    /// Two bits per block, block-major in the grid's axis order.
    packed: Vec<u8>,
}

impl MaskSignTable {
    /// Builds the table of `mask`'s sign (one channel; the hit test is
    /// `value > 0`, as `EstimatorSampler::hits` does).
    pub fn new(mask: &QuantizedGrid) -> Self {
        debug_assert_eq!(mask.channels, 1);
        let s = mask.res as usize;
        let blocks = s.div_ceil(FACTOR);
        // The smallest and largest code of each block's nodes. One task per
        // block of the first axis: the slabs of its nodes (s^3 codes each)
        // are reduced to one, then the other three axes are reduced one at a
        // time (separable), all within a few hundred KiB that stay in cache.
        let slab = s * s * s;
        let per_block = blocks * blocks * blocks;
        let mut lo = vec![0u8; blocks * per_block];
        let mut hi = vec![0u8; blocks * per_block];
        lo.par_chunks_mut(per_block).zip(hi.par_chunks_mut(per_block)).enumerate().for_each(|(j, (lo_out, hi_out))| {
            let mut slab_lo = vec![u8::MAX; slab];
            let mut slab_hi = vec![0u8; slab];
            let mut row = vec![0u8; s];
            for t in 0..=FACTOR {
                // The first axis (u1) is clamped.
                let node = (j * FACTOR + t).min(s - 1);
                for r in 0..s * s {
                    unpack_row(&mask.data, node * slab + r * s, mask.bits, &mut row);
                    let dst = r * s..(r + 1) * s;
                    for ((l, h), &c) in slab_lo[dst.clone()].iter_mut().zip(&mut slab_hi[dst]).zip(&row) {
                        *l = (*l).min(c);
                        *h = (*h).max(c);
                    }
                }
            }
            let mut dims = [1, s, s, s];
            for axis in [1, 2, 3] {
                let periodic = axis % 2 == 1;
                (slab_lo, slab_hi) = reduce_axis(&slab_lo, &slab_hi, &mut dims, axis, blocks, periodic);
            }
            lo_out.copy_from_slice(&slab_lo);
            hi_out.copy_from_slice(&slab_hi);
        });
        // A margin of 1/100 of a code step: the interpolation's own rounding
        // (a sum of 16 products of weights in [0, 1] with codes up to 255,
        // in f32, then scaled and offset) stays below 1/1000 of a step.
        let (scale, offset) = (mask.scale[0], mask.offset[0]);
        let margin = 1e-2 * scale.abs();
        let value = |code: u8| code as f32 * scale + offset;
        let mut packed = vec![0u8; (lo.len() * 2).div_ceil(8)];
        for (k, (&a, &b)) in lo.iter().zip(&hi).enumerate() {
            let (x, y) = (value(a), value(b));
            let (min, max) = (x.min(y), x.max(y));
            let sign = if min > margin {
                HIT
            } else if max < -margin {
                MISS
            } else {
                MIXED
            };
            packed[k >> 2] |= sign << ((k & 3) << 1);
        }
        Self { res: s, blocks, packed }
    }

    /// The mask's answer for a chord, where the table knows it.
    #[inline]
    pub fn sign(&self, pair: &nppp_geom::SpherePair) -> MaskSign {
        let [a, b, c, d] = cell_of(pair, self.res).map(|i| i / FACTOR);
        let k = ((a * self.blocks + b) * self.blocks + c) * self.blocks + d;
        match (self.packed[k >> 2] >> ((k & 3) << 1)) & 3 {
            HIT => MaskSign::Hit,
            MISS => MaskSign::Miss,
            _ => MaskSign::Mixed,
        }
    }

    /// The fraction of the blocks a chord can reach that are mixed (for
    /// tests and logs). On the clamped u axes cells go up to `res - 2`, so
    /// with an odd resolution the last block of those axes holds no cell.
    pub fn mixed_fraction(&self) -> f64 {
        let b = self.blocks;
        let bu = (self.res - 1).div_ceil(FACTOR);
        let (mut reachable, mut mixed) = (0usize, 0usize);
        for (a, v1, u2, v2) in
            (0..bu).flat_map(|a| (0..b).flat_map(move |v1| (0..bu).flat_map(move |u2| (0..b).map(move |v2| (a, v1, u2, v2)))))
        {
            let k = ((a * b + v1) * b + u2) * b + v2;
            reachable += 1;
            mixed += usize::from((self.packed[k >> 2] >> ((k & 3) << 1)) & 3 == MIXED);
        }
        mixed as f64 / reachable.max(1) as f64
    }

    pub fn memory_bytes(&self) -> usize {
        self.packed.len()
    }
}

/// The `out.len()` codes from code number `start` on.
fn unpack_row(packed: &[u8], start: usize, bits: u8, out: &mut [u8]) {
    match bits {
        8 => out.copy_from_slice(&packed[start..start + out.len()]),
        // 4 bits, a row starting on a byte: two codes per byte. Anything
        // else (odd resolutions, 2 bits) code by code.
        4 if start.is_multiple_of(2) && out.len().is_multiple_of(2) => {
            for (pair, &byte) in out.chunks_exact_mut(2).zip(&packed[start / 2..]) {
                pair[0] = byte & 0x0f;
                pair[1] = byte >> 4;
            }
        }
        _ => {
            for (k, c) in out.iter_mut().enumerate() {
                *c = get_code(packed, start + k, bits);
            }
        }
    }
}

/// Reduces one axis of the min/max arrays (shape `dims`, row-major in axis
/// order) from its length to `blocks`: block `j` takes the nodes a cell of
/// block `j` can touch, `j * FACTOR ..= j * FACTOR + FACTOR` (clamped to the
/// last node on a clamped axis, wrapping on a periodic one).
fn reduce_axis(lo: &[u8], hi: &[u8], dims: &mut [usize; 4], axis: usize, blocks: usize, periodic: bool) -> (Vec<u8>, Vec<u8>) {
    let len = dims[axis];
    let outer: usize = dims[..axis].iter().product();
    let inner: usize = dims[axis + 1..].iter().product();
    let mut out_lo = vec![u8::MAX; outer * blocks * inner];
    let mut out_hi = vec![0u8; outer * blocks * inner];
    for o in 0..outer {
        for j in 0..blocks {
            let dst = (o * blocks + j) * inner..(o * blocks + j + 1) * inner;
            for t in 0..=FACTOR {
                let node = j * FACTOR + t;
                let node = if periodic { node % len } else { node.min(len - 1) };
                let src = (o * len + node) * inner..(o * len + node + 1) * inner;
                for (d, &x) in out_lo[dst.clone()].iter_mut().zip(&lo[src.clone()]) {
                    *d = (*d).min(x);
                }
                for (d, &x) in out_hi[dst.clone()].iter_mut().zip(&hi[src]) {
                    *d = (*d).max(x);
                }
            }
        }
    }
    dims[axis] = blocks;
    (out_lo, out_hi)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nppp_geom::SpherePair;
    use proptest::prelude::*;

    /// A mask whose sign changes along a smooth surface through the grid
    /// (like a real mask's hit/miss boundary), plus noise.
    fn mask_grid(res: u32, bits: u8, shift: f32, noise: &[f32]) -> QuantizedGrid {
        let n = crate::grid::node_count(res);
        let values: Vec<f32> = (0..n)
            .map(|k| {
                let [u1, v1, u2, v2] = crate::grid::node_coords(res, k);
                let smooth =
                    (u1 - 0.5) * 8.0 + (v1 * std::f32::consts::TAU).sin() * 3.0 - u2 * 2.0 + (v2 * std::f32::consts::TAU).cos() + shift;
                smooth + noise[k % noise.len()]
            })
            .collect();
        QuantizedGrid::from_f32(res, 1, &values, bits).unwrap()
    }

    fn logit(g: &QuantizedGrid, p: [f32; 4]) -> f32 {
        let mut out = [0.0f32];
        g.interpolate(&SpherePair(p), &mut out);
        out[0]
    }

    /// The table only answers where the interpolation agrees, and it does
    /// answer somewhere (a table of nothing but mixed blocks would pass the
    /// first half vacuously).
    #[test]
    fn the_table_answers_where_every_corner_agrees() {
        for (res, bits) in [(8u32, 4u8), (9, 8), (12, 2), (16, 4)] {
            let g = mask_grid(res, bits, 0.3, &[0.0, 0.4, -0.3, 0.1, -0.2]);
            let t = MaskSignTable::new(&g);
            let mixed = t.mixed_fraction();
            assert!(mixed > 0.0 && mixed < 0.9, "res {res}: {mixed} of the blocks mixed");
            let mut known = 0;
            let mut rng = 12345u64;
            let mut next = || {
                rng = rng.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                ((rng >> 40) as f32 / (1u64 << 24) as f32) * 1.4 - 0.2
            };
            for _ in 0..20_000 {
                let p = [next(), next(), next(), next()];
                let l = logit(&g, p);
                match t.sign(&SpherePair(p)) {
                    MaskSign::Hit => assert!(l > 0.0, "res {res} {p:?}: table says hit, logit {l}"),
                    MaskSign::Miss => assert!(l <= 0.0, "res {res} {p:?}: table says miss, logit {l}"),
                    MaskSign::Mixed => continue,
                }
                known += 1;
            }
            assert!(known > 2_000, "res {res}: only {known} of 20,000 chords answered by the table");
        }
    }

    /// Constant grids: all hit, all miss, and exactly zero (which is a miss
    /// for `> 0`, so the table must leave it to the interpolation).
    #[test]
    fn constant_masks() {
        for (value, want) in [(3.0f32, MaskSign::Hit), (-3.0, MaskSign::Miss), (0.0, MaskSign::Mixed)] {
            let g = QuantizedGrid::from_f32(5, 1, &vec![value; 625], 4).unwrap();
            let t = MaskSignTable::new(&g);
            assert_eq!(t.sign(&SpherePair([0.3, 0.9, 0.5, 0.1])), want, "constant {value}");
        }
    }

    proptest! {
        /// Whatever the grid and chord (NaN and out-of-range coordinates
        /// included), a known sign is the interpolation's sign.
        #[test]
        fn a_known_sign_is_the_interpolated_sign(
            noise in proptest::collection::vec(-3.0f32..3.0, 1..40),
            shift in -4.0f32..4.0,
            res in 2u32..11,
            bits in prop_oneof![Just(8u8), Just(4u8), Just(2u8)],
            p in proptest::array::uniform4(prop_oneof![-0.5f32..1.5, Just(f32::NAN), Just(1.0f32), Just(0.0f32)]),
        ) {
            let g = mask_grid(res, bits, shift, &noise);
            let t = MaskSignTable::new(&g);
            let l = logit(&g, p);
            match t.sign(&SpherePair(p)) {
                MaskSign::Hit => prop_assert!(l > 0.0, "hit, logit {}", l),
                MaskSign::Miss => prop_assert!(l <= 0.0, "miss, logit {}", l),
                MaskSign::Mixed => {}
            }
        }
    }
}
