//! The 4D grid over sphere pairs `(u1, v1, u2, v2)` that baking fills and the
//! renderer looks up.
//!
//! Node layout (shared by bake and lookup, so it lives in one place):
//! - u axes (`u = (1 + cos theta) / 2`): `S` nodes at `u = i / (S - 1)`, both
//!   poles included; lookups clamp u to [0, 1].
//! - v axes (`v = phi / 2 pi`): `S` nodes at `v = j / S`; v is periodic, so
//!   the cell after the last node wraps back to node 0 and there is no seam.
//! - node index `((i1 * S + j1) * S + i2) * S + j2`, values node-major with
//!   the channels of one node contiguous.

use crate::quant::{self, QuantError, get_code, packed_len};
use nppp_geom::SpherePair;
use thiserror::Error;

/// Smallest resolution: a u axis needs two nodes to interpolate between.
pub const MIN_RES: u32 = 2;

/// Number of nodes of a grid of resolution `res`, saturating at `usize::MAX`
/// so that an absurd resolution read from a file fails a size check instead
/// of wrapping around to a small number.
pub fn node_count(res: u32) -> usize {
    checked_node_count(res).unwrap_or(usize::MAX)
}

/// `res^4`, or `None` if it overflows `usize`.
pub fn checked_node_count(res: u32) -> Option<usize> {
    let s = res as usize;
    s.checked_mul(s)?.checked_mul(s)?.checked_mul(s)
}

/// u of node `i` on a u axis (poles included).
#[inline]
pub fn u_coord(res: u32, i: u32) -> f32 {
    if res < 2 { 0.0 } else { i as f32 / (res - 1) as f32 }
}

/// v of node `j` on a (periodic) v axis.
#[inline]
pub fn v_coord(res: u32, j: u32) -> f32 {
    if res == 0 { 0.0 } else { j as f32 / res as f32 }
}

/// Grid indices `[i1, j1, i2, j2]` of a node.
pub fn node_indices(res: u32, index: usize) -> [u32; 4] {
    let s = res.max(1) as usize;
    let j2 = index % s;
    let i2 = (index / s) % s;
    let j1 = (index / (s * s)) % s;
    let i1 = index / (s * s * s);
    [i1 as u32, j1 as u32, i2 as u32, j2 as u32]
}

/// Inverse of [`node_indices`].
pub fn node_index(res: u32, [i1, j1, i2, j2]: [u32; 4]) -> usize {
    let s = res as usize;
    ((i1 as usize * s + j1 as usize) * s + i2 as usize) * s + j2 as usize
}

/// `(u1, v1, u2, v2)` of node `index`: where bake evaluates the encoder.
pub fn node_coords(res: u32, index: usize) -> [f32; 4] {
    let [i1, j1, i2, j2] = node_indices(res, index);
    [u_coord(res, i1), v_coord(res, j1), u_coord(res, i2), v_coord(res, j2)]
}

#[derive(Debug, Error, Clone, PartialEq)]
pub enum GridError {
    #[error("grid resolution {0} is out of range (at least {MIN_RES}, and res^4 x channels must fit in memory)")]
    Res(u32),
    #[error("grid of resolution {res} with {channels} channels needs {expected} values, got {got}")]
    ValueCount { res: u32, channels: u32, expected: usize, got: usize },
    #[error("grid data has {got} bytes, {expected} expected")]
    DataSize { expected: usize, got: usize },
    #[error("grid quantization parameters are invalid: {0}")]
    Params(String),
    #[error(transparent)]
    Quant(#[from] QuantError),
}

/// Bytes of packed codes for a grid, or `None` if the size overflows `usize`
/// (lets callers check a header against a file length without allocating).
pub fn data_bytes(res: u32, channels: u32, bits: u8) -> Option<usize> {
    checked_node_count(res)?.checked_mul(channels as usize).and_then(|v| packed_len(v, bits))
}

/// A 4D grid stored as quantized codes with per-channel scale and offset.
///
/// The fields are public so the file reader and tests can build one, but
/// lookups trust them: anything built by hand should pass [`Self::validate`].
#[derive(Clone, Debug, PartialEq)]
pub struct QuantizedGrid {
    pub res: u32,
    pub channels: u32,
    pub bits: u8,
    pub scale: Vec<f32>,
    pub offset: Vec<f32>,
    pub data: Vec<u8>,
}

/// One axis of a lookup: the two bracketing node indices and their weights.
#[derive(Clone, Copy)]
struct Axis {
    i: [usize; 2],
    w: [f32; 2],
}

/// The 16 grid nodes a quadrilinear lookup blends and their weights
/// ([`QuantizedGrid::corners`]).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Corners {
    res: u32,
    nodes: [usize; 16],
    weights: [f32; 16],
}

/// Clamped axis; NaN is treated as 0 so a broken ray still gets a finite
/// answer instead of a panic or an out-of-bounds read.
#[inline(always)]
fn u_axis(u: f32, s: usize) -> Axis {
    let u = if u.is_nan() { 0.0 } else { u.clamp(0.0, 1.0) };
    let t = u * (s - 1) as f32;
    let i0 = (t as usize).min(s - 2);
    let f = (t - i0 as f32).clamp(0.0, 1.0);
    Axis { i: [i0, i0 + 1], w: [1.0 - f, f] }
}

/// Periodic axis. `v - floor(v)` can round up to exactly 1.0 for tiny
/// negative v, so the node index is reduced modulo S after flooring.
#[inline(always)]
fn v_axis(v: f32, s: usize) -> Axis {
    let v = if v.is_finite() { v - v.floor() } else { 0.0 };
    let t = v * s as f32;
    let fl = t.floor();
    let f = (t - fl).clamp(0.0, 1.0);
    let mut j0 = fl as usize;
    if j0 >= s {
        j0 -= s;
    }
    let j1 = if j0 + 1 >= s { 0 } else { j0 + 1 };
    Axis { i: [j0, j1], w: [1.0 - f, f] }
}

/// The cell of a resolution-`s` grid that [`QuantizedGrid::interpolate`]
/// reads for `pair`: its lowest node index on each axis (the cell's corners
/// are those and the next, wrapping on the periodic v axes).
#[inline(always)]
pub(crate) fn cell_of(pair: &SpherePair, s: usize) -> [usize; 4] {
    let [u1, v1, u2, v2] = pair.0;
    [u_axis(u1, s).i[0], v_axis(v1, s).i[0], u_axis(u2, s).i[0], v_axis(v2, s).i[0]]
}

impl QuantizedGrid {
    /// Quantizes a node-major f32 grid (`channels` values per node).
    pub fn from_f32(res: u32, channels: u32, values: &[f32], bits: u8) -> Result<Self, GridError> {
        quant::check_bits(bits)?;
        if channels == 0 {
            return Err(QuantError::NoChannels.into());
        }
        if res < MIN_RES {
            return Err(GridError::Res(res));
        }
        let expected = checked_node_count(res).and_then(|n| n.checked_mul(channels as usize)).ok_or(GridError::Res(res))?;
        if values.len() != expected {
            return Err(GridError::ValueCount { res, channels, expected, got: values.len() });
        }
        let (scale, offset, data) = quant::quantize(values, channels as usize, bits)?;
        Ok(Self { res, channels, bits, scale, offset, data })
    }

    /// Checks that the fields agree, so that lookups stay in bounds and
    /// decode to finite values.
    pub fn validate(&self) -> Result<(), GridError> {
        quant::check_bits(self.bits)?;
        if self.channels == 0 {
            return Err(QuantError::NoChannels.into());
        }
        if self.res < MIN_RES {
            return Err(GridError::Res(self.res));
        }
        let expected = data_bytes(self.res, self.channels, self.bits).ok_or(GridError::Res(self.res))?;
        if self.data.len() != expected {
            return Err(GridError::DataSize { expected, got: self.data.len() });
        }
        let c = self.channels as usize;
        if self.scale.len() != c || self.offset.len() != c {
            return Err(QuantError::ParamCount { scales: self.scale.len(), offsets: self.offset.len(), channels: c }.into());
        }
        for ch in 0..c {
            let (s, o) = (self.scale[ch], self.offset[ch]);
            if !(s.is_finite() && s >= 0.0 && o.is_finite()) {
                return Err(GridError::Params(format!("channel {ch}: scale {s}, offset {o}")));
            }
            if !(s * quant::max_code(self.bits) as f32 + o).is_finite() {
                return Err(GridError::Params(format!("channel {ch}: largest code decodes to infinity")));
            }
        }
        Ok(())
    }

    pub fn node_count(&self) -> usize {
        node_count(self.res)
    }

    /// Bytes held: codes plus the per-channel parameters.
    pub fn memory_bytes(&self) -> usize {
        self.data.len() + 4 * (self.scale.len() + self.offset.len())
    }

    /// Dequantized value of one node's channel.
    pub fn node_value(&self, node: usize, channel: usize) -> f32 {
        let code = get_code(&self.data, node * self.channels as usize + channel, self.bits);
        code as f32 * self.scale[channel] + self.offset[channel]
    }

    /// The whole grid dequantized, node-major.
    pub fn to_f32(&self) -> Vec<f32> {
        let c = self.channels as usize;
        (0..self.node_count() * c).map(|k| self.node_value(k / c, k % c)).collect()
    }

    /// Quadrilinear interpolation of all channels at `pair` into
    /// `out[..channels]` (panics if `out` is shorter).
    ///
    /// Interpolation is linear and dequantization affine, so the codes are
    /// blended first and scale/offset applied once per channel at the end:
    /// 16 x channels multiply-adds on small integers, nothing else per corner.
    /// u is clamped, v wraps, NaN counts as 0; out-of-range input never reads
    /// out of bounds.
    #[inline]
    pub fn interpolate(&self, pair: &SpherePair, out: &mut [f32]) {
        let corners = self.corners(pair);
        // All 16 corners first, so their cache lines can be fetched in
        // parallel: on a 16 MiB grid with incoherent rays, memory latency,
        // not arithmetic, is the cost of a lookup.
        self.prefetch(&corners);
        self.blend(&corners, out);
    }

    /// The 16 nodes a quadrilinear lookup at `pair` blends and their
    /// weights (u clamped, v wrapped, NaN counted as 0): the first half of
    /// [`Self::interpolate`], for callers that fetch a batch's corners
    /// before blending any ([`Self::prefetch`], [`Self::blend`]).
    #[inline]
    pub fn corners(&self, pair: &SpherePair) -> Corners {
        let s = self.res as usize;
        let [u1, v1, u2, v2] = pair.0;
        let (a1, b1, a2, b2) = (u_axis(u1, s), v_axis(v1, s), u_axis(u2, s), v_axis(v2, s));
        let (s2, s3) = (s * s, s * s * s);
        let mut c = Corners { res: self.res, nodes: [0; 16], weights: [0.0; 16] };
        let mut k = 0;
        for a in 0..2 {
            for b in 0..2 {
                let w_ab = a1.w[a] * b1.w[b];
                let n_ab = a1.i[a] * s3 + b1.i[b] * s2;
                for cc in 0..2 {
                    let w_abc = w_ab * a2.w[cc];
                    let n_abc = n_ab + a2.i[cc] * s;
                    for d in 0..2 {
                        c.weights[k] = w_abc * b2.w[d];
                        c.nodes[k] = n_abc + b2.i[d];
                        k += 1;
                    }
                }
            }
        }
        c
    }

    /// Starts fetching the cache lines of `corners`' nodes and returns at
    /// once.
    #[inline]
    pub fn prefetch(&self, corners: &Corners) {
        let (ch, bits) = (self.channels as usize, self.bits as usize);
        for &n in &corners.nodes {
            prefetch(&self.data, n * ch * bits / 8);
        }
    }

    /// The second half of [`Self::interpolate`]: `corners`' nodes blended
    /// into `out[..channels]`. Panics if `out` is shorter or `corners` are
    /// another resolution's.
    #[inline]
    pub fn blend(&self, corners: &Corners, out: &mut [f32]) {
        assert_eq!(corners.res, self.res, "corners of a grid of another resolution");
        let ch = self.channels as usize;
        let out = &mut out[..ch];
        let (nodes, ws) = (&corners.nodes, &corners.weights);
        let bits = self.bits as usize;
        if self.bits == 8 {
            // Common widths get a fixed-size accumulator that stays in
            // registers and a fully unrolled, vectorized inner loop.
            match ch {
                16 => return self.blend8::<16>(nodes, ws, out),
                8 => return self.blend8::<8>(nodes, ws, out),
                32 => return self.blend8::<32>(nodes, ws, out),
                1 => return self.blend8::<1>(nodes, ws, out),
                _ => {}
            }
        }
        if self.bits == 4 {
            // The default estimator's widths (16-channel latents, 1-channel
            // mask) at 4 bits, likewise.
            match ch {
                16 => return self.blend4::<16, 8>(nodes, ws, out),
                1 => return self.blend4_one(nodes, ws, out),
                _ => {}
            }
        }
        out.fill(0.0);
        let whole_bytes = (ch * bits).is_multiple_of(8);
        for (&node, &w) in nodes.iter().zip(ws) {
            match (self.bits, whole_bytes) {
                (8, _) => {
                    let codes = &self.data[node * ch..node * ch + ch];
                    for (o, &q) in out.iter_mut().zip(codes) {
                        *o += w * q as f32;
                    }
                }
                (4, true) => {
                    let nb = ch / 2;
                    let codes = &self.data[node * nb..node * nb + nb];
                    for (o, &q) in out.chunks_exact_mut(2).zip(codes) {
                        o[0] += w * (q & 0x0f) as f32;
                        o[1] += w * (q >> 4) as f32;
                    }
                }
                (2, true) => {
                    let nb = ch / 4;
                    let codes = &self.data[node * nb..node * nb + nb];
                    for (o, &q) in out.chunks_exact_mut(4).zip(codes) {
                        o[0] += w * (q & 3) as f32;
                        o[1] += w * ((q >> 2) & 3) as f32;
                        o[2] += w * ((q >> 4) & 3) as f32;
                        o[3] += w * (q >> 6) as f32;
                    }
                }
                _ => {
                    let k0 = node * ch;
                    for (c, o) in out.iter_mut().enumerate() {
                        *o += w * get_code(&self.data, k0 + c, self.bits) as f32;
                    }
                }
            }
        }
        for ((o, &sc), &off) in out.iter_mut().zip(&self.scale).zip(&self.offset) {
            *o = *o * sc + off;
        }
    }

    /// Stochastic filtering (Pharr, Wronski, Salvi, Fajardo 2024, "Filtering
    /// After Shading With Stochastic Texture Filtering"): instead of blending
    /// the 16 corners of the quadrilinear cell, picks one of them with
    /// probability equal to its interpolation weight (each axis
    /// independently, with `u[axis]` uniform in [0, 1)) and returns that
    /// node's values. In expectation over `u` this is the interpolated grid;
    /// a decoder fed with it samples the weighted mixture of the corners'
    /// distributions. One node read instead of 16: one cache miss per entry.
    #[inline]
    pub fn lookup_stochastic(&self, pair: &SpherePair, u: [f32; 4], out: &mut [f32]) {
        let s = self.res as usize;
        let ch = self.channels as usize;
        let out = &mut out[..ch];
        let [u1, v1, u2, v2] = pair.0;
        let pick = |a: Axis, u: f32| if u < a.w[0] { a.i[0] } else { a.i[1] };
        let node = pick(u_axis(u1, s), u[0]) * s * s * s
            + pick(v_axis(v1, s), u[1]) * s * s
            + pick(u_axis(u2, s), u[2]) * s
            + pick(v_axis(v2, s), u[3]);
        if self.bits == 4 && ch.is_multiple_of(2) {
            let nb = ch / 2;
            if let Some(codes) = self.data.get(node * nb..node * nb + nb) {
                for (((o, &q), sc), off) in
                    out.chunks_exact_mut(2).zip(codes).zip(self.scale.chunks_exact(2)).zip(self.offset.chunks_exact(2))
                {
                    o[0] = (q & 0x0f) as f32 * sc[0] + off[0];
                    o[1] = (q >> 4) as f32 * sc[1] + off[1];
                }
                return;
            }
        }
        if node >= self.node_count() {
            out.fill(0.0);
            return;
        }
        for (c, o) in out.iter_mut().enumerate() {
            *o = self.node_value(node, c);
        }
    }

    /// 8-bit blend of the 16 corners for exactly `N` channels.
    #[inline(always)]
    fn blend8<const N: usize>(&self, nodes: &[usize; 16], ws: &[f32; 16], out: &mut [f32]) {
        let mut acc = [0.0f32; N];
        for (&node, &w) in nodes.iter().zip(ws) {
            // Always present for a validated grid; a hand-built broken one
            // loses a corner instead of panicking in the renderer.
            if let Some(codes) = self.data.get(node * N..).and_then(|s| s.first_chunk::<N>()) {
                for (a, &q) in acc.iter_mut().zip(codes) {
                    *a += w * q as f32;
                }
            }
        }
        for (((o, a), &sc), &off) in out.iter_mut().zip(acc).zip(&self.scale).zip(&self.offset) {
            *o = a * sc + off;
        }
    }
}

impl QuantizedGrid {
    /// 4-bit blend of the 16 corners for exactly `N` channels (`B` = N / 2
    /// bytes per node, low nibble first, as `quant::get_code` packs them).
    #[inline(always)]
    fn blend4<const N: usize, const B: usize>(&self, nodes: &[usize; 16], ws: &[f32; 16], out: &mut [f32]) {
        debug_assert_eq!(2 * B, N);
        let mut acc = [0.0f32; N];
        for (&node, &w) in nodes.iter().zip(ws) {
            if let Some(codes) = self.data.get(node * B..).and_then(|s| s.first_chunk::<B>()) {
                for (pair, &q) in acc.chunks_exact_mut(2).zip(codes) {
                    pair[0] += w * (q & 0x0f) as f32;
                    pair[1] += w * (q >> 4) as f32;
                }
            }
        }
        for (((o, a), &sc), &off) in out.iter_mut().zip(acc).zip(&self.scale).zip(&self.offset) {
            *o = a * sc + off;
        }
    }

    /// 4-bit blend of one channel (two nodes per byte).
    #[inline(always)]
    fn blend4_one(&self, nodes: &[usize; 16], ws: &[f32; 16], out: &mut [f32]) {
        let mut acc = 0.0f32;
        for (&node, &w) in nodes.iter().zip(ws) {
            if let Some(&q) = self.data.get(node >> 1) {
                acc += w * ((q >> ((node & 1) << 2)) & 0x0f) as f32;
            }
        }
        out[0] = acc * self.scale[0] + self.offset[0];
    }
}

/// Hints the cache that `data[at]` is needed soon; a no-op where no stable
/// intrinsic exists.
#[inline(always)]
fn prefetch(data: &[u8], at: usize) {
    #[cfg(target_arch = "x86_64")]
    if at < data.len() {
        // SAFETY: SSE is part of the x86_64 baseline, and a prefetch never
        // faults or changes memory; the address is in bounds anyway.
        unsafe { std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(data.as_ptr().add(at) as *const i8) }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (data, at);
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// A small grid with smooth but non-trivial values per channel.
    fn test_grid(res: u32, channels: u32, bits: u8) -> (Vec<f32>, QuantizedGrid) {
        let n = node_count(res);
        let values: Vec<f32> = (0..n * channels as usize)
            .map(|k| {
                let [u1, v1, u2, v2] = node_coords(res, k / channels as usize);
                let c = (k % channels as usize) as f32;
                (u1 * 3.0 + c).sin() + (v1 * std::f32::consts::TAU).cos() * u2 - v2 * (c + 1.0) * 0.3
            })
            .collect();
        let g = QuantizedGrid::from_f32(res, channels, &values, bits).unwrap();
        g.validate().unwrap();
        (values, g)
    }

    /// A lookup split in two (corners of a batch first, blends after, as
    /// the renderer does) gives the interpolation's bits; corners of
    /// another resolution are refused.
    #[test]
    fn corners_then_blend_is_the_interpolation() {
        for (bits, channels) in [(4u8, 16u32), (4, 1), (8, 3), (2, 4)] {
            let (_, g) = test_grid(5, channels, bits);
            let pairs = [[0.37, 0.91, 0.62, 0.05], [0.0, 0.999, 1.0, 0.5], [f32::NAN, -0.2, 1.3, 7.25]];
            let corners: Vec<Corners> = pairs.iter().map(|p| g.corners(&SpherePair(*p))).collect();
            corners.iter().for_each(|c| g.prefetch(c));
            for (p, c) in pairs.iter().zip(&corners) {
                let (mut whole, mut split) = (vec![0.0f32; channels as usize], vec![0.0f32; channels as usize]);
                g.interpolate(&SpherePair(*p), &mut whole);
                g.blend(c, &mut split);
                assert_eq!(whole, split, "{bits} bits x {channels}");
            }
        }
        let (_, small) = test_grid(3, 1, 4);
        let (_, big) = test_grid(5, 1, 4);
        let foreign = big.corners(&SpherePair([0.9, 0.9, 0.9, 0.9]));
        let blended = std::panic::catch_unwind(|| small.blend(&foreign, &mut [0.0]));
        assert!(blended.is_err(), "corners of a 5^4 grid blended in a 3^4 one");
    }

    /// Stochastic filtering is unbiased: averaged over many draws it
    /// converges to the quadrilinear interpolation, and each draw is one of
    /// the cell's corners.
    #[test]
    fn stochastic_lookup_averages_to_the_interpolation() {
        for (bits, channels) in [(4u8, 16u32), (8, 3), (2, 4)] {
            let (_, g) = test_grid(5, channels, bits);
            let pair = SpherePair([0.37, 0.91, 0.62, 0.05]);
            let c = channels as usize;
            let mut exact = vec![0.0f32; c];
            g.interpolate(&pair, &mut exact);
            let mut rng = nppp_geom::SampleRng::new(7, 0, 0);
            let mut mean = vec![0.0f64; c];
            let mut one = vec![0.0f32; c];
            let n = 200_000;
            for _ in 0..n {
                let u = [rng.uniform(), rng.uniform(), rng.uniform(), rng.uniform()];
                g.lookup_stochastic(&pair, u, &mut one);
                let is_node = (0..g.node_count()).any(|k| (0..c).all(|ch| g.node_value(k, ch) == one[ch]));
                assert!(is_node, "{bits} bits: draw {one:?} is no node's value");
                for (m, v) in mean.iter_mut().zip(&one) {
                    *m += *v as f64 / n as f64;
                }
            }
            for ch in 0..c {
                let range = (0..g.node_count()).map(|k| g.node_value(k, ch)).fold(0.0f32, |a, v| a.max(v.abs())).max(1e-3);
                assert!(
                    (mean[ch] - exact[ch] as f64).abs() < 0.01 * range as f64,
                    "{bits} bits, channel {ch}: mean {} vs interpolated {}",
                    mean[ch],
                    exact[ch]
                );
            }
        }
    }

    #[test]
    fn node_coords_is_a_bijection() {
        for res in [2u32, 3, 5] {
            let n = node_count(res);
            let mut seen = std::collections::HashSet::new();
            for idx in 0..n {
                let ijkl = node_indices(res, idx);
                assert!(ijkl.iter().all(|&x| x < res));
                assert_eq!(node_index(res, ijkl), idx);
                let c = node_coords(res, idx);
                assert!(c.iter().all(|x| (0.0..=1.0).contains(x)));
                // v never reaches 1 (that is node 0 again).
                assert!(c[1] < 1.0 && c[3] < 1.0);
                assert!(seen.insert(c.map(f32::to_bits)));
            }
            assert_eq!(node_coords(res, node_index(res, [res - 1, 0, 0, 0]))[0], 1.0);
        }
    }

    #[test]
    fn sizes_follow_the_thesis_formula() {
        assert_eq!(node_count(32), 1 << 20);
        // 32^4 x 16 latents at 8 bits = 16 MiB; a 32^4 mask at 8 bits = 1 MiB.
        assert_eq!(data_bytes(32, 16, 8), Some(16 << 20));
        assert_eq!(data_bytes(32, 1, 8), Some(1 << 20));
        assert_eq!(data_bytes(32, 16, 4), Some(8 << 20));
        assert_eq!(data_bytes(32, 16, 2), Some(4 << 20));
        assert_eq!(data_bytes(1 << 31, 16, 8), None);
        assert_eq!(node_count(u32::MAX), usize::MAX);
        // And a real one, to check that the allocation matches the formula.
        let g = QuantizedGrid::from_f32(32, 16, &vec![0.5; 16 << 20], 8).unwrap();
        assert_eq!(g.data.len(), 16 << 20);
        assert_eq!(g.memory_bytes(), (16 << 20) + 2 * 16 * 4);
    }

    #[test]
    fn interpolation_at_nodes_returns_node_values() {
        for bits in [8u8, 4, 2] {
            let (values, g) = test_grid(4, 3, bits);
            let mut out = [0.0f32; 3];
            for node in 0..g.node_count() {
                g.interpolate(&SpherePair(node_coords(4, node)), &mut out);
                for c in 0..3 {
                    let exact = values[node * 3 + c];
                    let stored = g.node_value(node, c);
                    assert!((out[c] - stored).abs() < 1e-5, "bits {bits} node {node}: {} vs {stored}", out[c]);
                    assert!((out[c] - exact).abs() <= g.scale[c] * 0.5 + 1e-5);
                }
            }
        }
    }

    #[test]
    fn v_wraps_continuously_and_u_poles_work() {
        let (_, g) = test_grid(5, 2, 8);
        let mut a = [0.0f32; 2];
        let mut b = [0.0f32; 2];
        for &(u1, u2) in &[(0.0f32, 0.0f32), (1.0, 1.0), (0.3, 0.8), (0.0, 1.0)] {
            let eps = 1e-5;
            g.interpolate(&SpherePair([u1, 1.0 - eps, u2, 0.4]), &mut a);
            g.interpolate(&SpherePair([u1, eps, u2, 0.4]), &mut b);
            assert!((a[0] - b[0]).abs() < 1e-3 && (a[1] - b[1]).abs() < 1e-3, "{a:?} {b:?}");
            g.interpolate(&SpherePair([u1, 0.7, u2, 1.0 - eps]), &mut a);
            g.interpolate(&SpherePair([u1, 0.7, u2, eps]), &mut b);
            assert!((a[0] - b[0]).abs() < 1e-3 && (a[1] - b[1]).abs() < 1e-3, "{a:?} {b:?}");
            // v = 1 is v = 0.
            g.interpolate(&SpherePair([u1, 1.0, u2, 1.0]), &mut a);
            g.interpolate(&SpherePair([u1, 0.0, u2, 0.0]), &mut b);
            assert_eq!(a, b);
        }
    }

    #[test]
    fn hostile_inputs_do_not_panic() {
        for bits in [8u8, 4, 2] {
            let (_, g) = test_grid(3, 2, bits);
            let (lo, hi) =
                (0..g.node_count() * 2).map(|k| g.node_value(k / 2, k % 2)).fold((f32::MAX, f32::MIN), |(l, h), x| (l.min(x), h.max(x)));
            let bad = [f32::NAN, f32::INFINITY, f32::NEG_INFINITY, -1e-30, -1e30, 1e30, 1.0 + 1e-7, -0.0, 7.5, -7.5, f32::MIN_POSITIVE];
            let mut out = [0.0f32; 2];
            for &x in &bad {
                for slot in 0..4 {
                    let mut p = [0.5f32; 4];
                    p[slot] = x;
                    g.interpolate(&SpherePair(p), &mut out);
                    assert!(out.iter().all(|o| o.is_finite() && *o >= lo - 1e-5 && *o <= hi + 1e-5), "{p:?} -> {out:?}");
                }
                g.interpolate(&SpherePair([x; 4]), &mut out);
                assert!(out.iter().all(|o| o.is_finite()));
            }
        }
    }

    /// Straight from the definition: every corner's dequantized value times
    /// its weight, no shared code with `interpolate`.
    fn reference(g: &QuantizedGrid, p: [f32; 4], c: usize) -> f32 {
        let s = g.res as usize;
        let sf = g.res as f32;
        let mut total = 0.0f64;
        for corner in 0..16 {
            let mut idx = [0usize; 4];
            let mut w = 1.0f64;
            for (axis, x) in p.iter().enumerate() {
                let hi = corner >> (3 - axis) & 1;
                let (i0, f) = if axis % 2 == 0 {
                    let t = x.clamp(0.0, 1.0) * (sf - 1.0);
                    let i0 = (t.floor() as usize).min(s - 2);
                    (i0, t - i0 as f32)
                } else {
                    let t = x.rem_euclid(1.0) * sf;
                    (t.floor() as usize % s, t - t.floor())
                };
                idx[axis] = if axis % 2 == 0 { i0 + hi } else { (i0 + hi) % s };
                w *= if hi == 1 { f as f64 } else { 1.0 - f as f64 };
            }
            let node = ((idx[0] * s + idx[1]) * s + idx[2]) * s + idx[3];
            total += w * g.node_value(node, c) as f64;
        }
        total as f32
    }

    #[test]
    fn every_channel_width_and_depth_matches_the_definition() {
        let mut seed = 7u32;
        let mut rnd = move || {
            seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (seed >> 8) as f32 / (1 << 24) as f32
        };
        for ch in [1u32, 3, 8, 16, 32] {
            for bits in [8u8, 4, 2] {
                let (_, g) = test_grid(3, ch, bits);
                let mut out = vec![0.0f32; ch as usize];
                for _ in 0..50 {
                    let p = [rnd(), rnd(), rnd(), rnd()];
                    g.interpolate(&SpherePair(p), &mut out);
                    for (c, &o) in out.iter().enumerate() {
                        let want = reference(&g, p, c);
                        assert!((o - want).abs() < 1e-4, "ch {ch} bits {bits} {p:?} channel {c}: {o} vs {want}");
                    }
                }
            }
        }
    }

    #[test]
    fn zero_range_channel_interpolates_to_its_constant() {
        let n = node_count(3);
        let values: Vec<f32> = (0..n * 16).map(|k| if k % 16 == 5 { -0.625 } else { (k % 7) as f32 }).collect();
        let g = QuantizedGrid::from_f32(3, 16, &values, 8).unwrap();
        assert_eq!(g.scale[5], 0.0);
        let mut out = [0.0f32; 16];
        for p in [[0.1, 0.2, 0.3, 0.4], [0.0, 0.999, 1.0, 0.0], [f32::NAN; 4]] {
            g.interpolate(&SpherePair(p), &mut out);
            assert_eq!(out[5], -0.625);
        }
    }

    #[test]
    fn invalid_grids_are_rejected() {
        assert!(matches!(QuantizedGrid::from_f32(1, 1, &[0.0], 8), Err(GridError::Res(1))));
        assert!(matches!(QuantizedGrid::from_f32(2, 1, &[0.0; 15], 8), Err(GridError::ValueCount { .. })));
        assert!(matches!(QuantizedGrid::from_f32(2, 1, &[0.0; 16], 5), Err(GridError::Quant(QuantError::Bits(5)))));
        let (_, mut g) = test_grid(2, 2, 4);
        g.data.pop();
        assert!(matches!(g.validate(), Err(GridError::DataSize { .. })));
        let (_, mut g) = test_grid(2, 2, 4);
        g.scale[1] = f32::NAN;
        assert!(g.validate().is_err());
    }

    proptest! {
        #[test]
        fn interpolation_stays_within_corner_bounds(
            seed in proptest::collection::vec(-5.0f32..5.0, 81 * 2),
            p in proptest::array::uniform4(-0.2f32..1.2),
            bits in prop_oneof![Just(8u8), Just(4u8), Just(2u8)],
        ) {
            let g = QuantizedGrid::from_f32(3, 2, &seed, bits).unwrap();
            let mut out = [0.0f32; 2];
            g.interpolate(&SpherePair(p), &mut out);
            // The 16 corners, found independently of `interpolate`.
            let s = 3usize;
            let uc = |u: f32| { let t = u.clamp(0.0, 1.0) * 2.0; let i = (t as usize).min(1); [i, i + 1] };
            let vc = |v: f32| { let t = (v - v.floor()) * 3.0; let j = (t.floor() as usize) % 3; [j, (j + 1) % 3] };
            let (i1, j1, i2, j2) = (uc(p[0]), vc(p[1]), uc(p[2]), vc(p[3]));
            for (c, &o) in out.iter().enumerate() {
                let mut lo = f32::MAX;
                let mut hi = f32::MIN;
                for a in i1 { for b in j1 { for cc in i2 { for d in j2 {
                    let x = g.node_value(((a * s + b) * s + cc) * s + d, c);
                    lo = lo.min(x);
                    hi = hi.max(x);
                }}}}
                let eps = 1e-5 * (1.0 + lo.abs().max(hi.abs()));
                prop_assert!(o >= lo - eps && o <= hi + eps, "channel {} value {} outside [{}, {}]", c, o, lo, hi);
            }
        }
    }
}
