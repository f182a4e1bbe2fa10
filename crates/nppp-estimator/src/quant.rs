//! Per-channel affine quantization of grid values to 8, 4 or 2 bits.
//!
//! The latent grid dominates an estimator's memory (32^4 nodes x 16 channels),
//! so it is stored as small integer codes plus one (scale, offset) pair per
//! channel: `value = code * scale + offset`. Min/max scaling keeps every value
//! representable, so the error of a round trip is at most half a step.
//!
//! Codes are a continuous little-endian bit stream: value `k` (node-major,
//! channels inner) occupies bits `k*bits .. (k+1)*bits`, i.e. for 4 and 2 bits
//! the first value of a byte is in its lowest bits.

use thiserror::Error;

/// Bit depths a grid may be stored with.
pub const SUPPORTED_BITS: [u8; 3] = [8, 4, 2];

#[derive(Debug, Error, Clone, PartialEq)]
pub enum QuantError {
    #[error("quantization to {0} bits is not supported (use 8, 4 or 2)")]
    Bits(u8),
    #[error("a grid needs at least one channel")]
    NoChannels,
    #[error("{values} values do not split into {channels} channels")]
    Ragged { values: usize, channels: usize },
    #[error("value {index} (channel {channel}) is not finite")]
    NonFinite { index: usize, channel: usize },
    #[error("packed data has {have} bytes, {need} needed for {values} values at {bits} bits")]
    PackedSize { have: usize, need: usize, values: usize, bits: u8 },
    #[error("channel {channel} spans more than f32 can represent ({lo} to {hi})")]
    Range { channel: usize, lo: f32, hi: f32 },
    #[error("{scales} scales and {offsets} offsets for {channels} channels")]
    ParamCount { scales: usize, offsets: usize, channels: usize },
}

pub fn check_bits(bits: u8) -> Result<(), QuantError> {
    if SUPPORTED_BITS.contains(&bits) { Ok(()) } else { Err(QuantError::Bits(bits)) }
}

/// Largest code at a bit depth (255, 15 or 3).
#[inline]
pub fn max_code(bits: u8) -> u32 {
    (1u32 << bits) - 1
}

/// Bytes needed for `values` codes, or `None` on overflow (absurd sizes from a
/// file header must not wrap around into a small, plausible number).
pub fn packed_len(values: usize, bits: u8) -> Option<usize> {
    values.checked_mul(bits as usize).map(|b| b.div_ceil(8))
}

/// Code number `k` of a packed stream. `bits` must be 8, 4 or 2 (then a code
/// never straddles a byte).
#[inline(always)]
pub fn get_code(packed: &[u8], k: usize, bits: u8) -> u8 {
    match bits {
        8 => packed[k],
        4 => (packed[k >> 1] >> ((k & 1) << 2)) & 0x0f,
        _ => (packed[k >> 2] >> ((k & 3) << 1)) & 0x03,
    }
}

#[inline]
fn put_code(packed: &mut [u8], k: usize, bits: u8, code: u8) {
    match bits {
        8 => packed[k] = code,
        4 => packed[k >> 1] |= (code & 0x0f) << ((k & 1) << 2),
        _ => packed[k >> 2] |= (code & 0x03) << ((k & 3) << 1),
    }
}

/// `(scale, offset, packed codes)` of a quantized array.
pub type Quantized = (Vec<f32>, Vec<f32>, Vec<u8>);

/// Quantizes `values` (items of `channels` values each) to `bits` bits with a
/// per-channel min/max affine map. Returns `(scale, offset, packed)`.
///
/// A channel whose values are all equal gets scale 0 and decodes exactly to
/// its offset. Non-finite values are rejected: a NaN in a latent grid would
/// silently poison every lookup that touches its node.
pub fn quantize(values: &[f32], channels: usize, bits: u8) -> Result<Quantized, QuantError> {
    check_bits(bits)?;
    if channels == 0 {
        return Err(QuantError::NoChannels);
    }
    if !values.len().is_multiple_of(channels) {
        return Err(QuantError::Ragged { values: values.len(), channels });
    }
    let mut lo = vec![f32::INFINITY; channels];
    let mut hi = vec![f32::NEG_INFINITY; channels];
    for (i, &x) in values.iter().enumerate() {
        let c = i % channels;
        if !x.is_finite() {
            return Err(QuantError::NonFinite { index: i, channel: c });
        }
        lo[c] = lo[c].min(x);
        hi[c] = hi[c].max(x);
    }
    let levels = max_code(bits) as f64;
    let mut scale = vec![0.0f32; channels];
    let mut offset = vec![0.0f32; channels];
    // Codes are computed in f64 against the f32 scale actually stored, so the
    // half-step bound holds for the decoder's arithmetic, not an idealized one.
    let mut inv = vec![0.0f64; channels];
    for c in 0..channels {
        if values.is_empty() {
            break;
        }
        offset[c] = lo[c];
        // In f64: hi - lo can overflow f32 for values near +-f32::MAX, and
        // then `code * scale + offset` would decode to infinity.
        if hi[c] as f64 - lo[c] as f64 > f32::MAX as f64 {
            return Err(QuantError::Range { channel: c, lo: lo[c], hi: hi[c] });
        }
        let s = ((hi[c] as f64 - lo[c] as f64) / levels) as f32;
        scale[c] = s;
        inv[c] = if s > 0.0 { 1.0 / s as f64 } else { 0.0 };
    }
    let mut packed = vec![0u8; packed_len(values.len(), bits).unwrap_or(0)];
    for (k, &x) in values.iter().enumerate() {
        let c = k % channels;
        let q = ((x as f64 - offset[c] as f64) * inv[c]).round().clamp(0.0, levels) as u8;
        put_code(&mut packed, k, bits, q);
    }
    Ok((scale, offset, packed))
}

/// Decodes `count` values (a multiple of `scale.len()` channels).
pub fn dequantize(scale: &[f32], offset: &[f32], packed: &[u8], bits: u8, count: usize) -> Result<Vec<f32>, QuantError> {
    check_bits(bits)?;
    let channels = scale.len();
    if channels == 0 {
        return Err(QuantError::NoChannels);
    }
    if offset.len() != channels {
        return Err(QuantError::ParamCount { scales: scale.len(), offsets: offset.len(), channels });
    }
    if !count.is_multiple_of(channels) {
        return Err(QuantError::Ragged { values: count, channels });
    }
    let need = packed_len(count, bits).unwrap_or(usize::MAX);
    if packed.len() < need {
        return Err(QuantError::PackedSize { have: packed.len(), need, values: count, bits });
    }
    Ok((0..count)
        .map(|k| {
            let c = k % channels;
            get_code(packed, k, bits) as f32 * scale[c] + offset[c]
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn check_bound(values: &[f32], channels: usize, bits: u8) -> Result<(), TestCaseError> {
        let (scale, offset, packed) = quantize(values, channels, bits).unwrap();
        prop_assert_eq!(packed.len(), packed_len(values.len(), bits).unwrap());
        let back = dequantize(&scale, &offset, &packed, bits, values.len()).unwrap();
        for (k, (&x, &y)) in values.iter().zip(&back).enumerate() {
            let c = k % channels;
            // Half a step, plus the f32 rounding of `code * scale + offset`.
            let eps = 4.0 * f32::EPSILON * (x.abs() + offset[c].abs() + scale[c] * max_code(bits) as f32);
            prop_assert!((x - y).abs() <= scale[c] * 0.5 + eps, "bits {} value {} -> {} (scale {})", bits, x, y, scale[c]);
        }
        Ok(())
    }

    proptest! {
        #[test]
        fn round_trip_error_is_at_most_half_a_step(
            channels in 1usize..5,
            raw in proptest::collection::vec(-1000.0f32..1000.0, 0..120),
            bits in prop_oneof![Just(8u8), Just(4u8), Just(2u8)],
        ) {
            let n = raw.len() / channels * channels;
            check_bound(&raw[..n], channels, bits)?;
        }

        #[test]
        fn extreme_magnitudes_stay_bounded(
            raw in proptest::collection::vec(prop_oneof![-1.5e38f32..1.5e38, -1e-30f32..1e-30], 1..40),
            bits in prop_oneof![Just(8u8), Just(4u8), Just(2u8)],
        ) {
            check_bound(&raw, 1, bits)?;
        }
    }

    #[test]
    fn zero_range_channel_decodes_exactly() {
        for bits in SUPPORTED_BITS {
            // Channel 0 constant, channel 1 varying.
            let values = [0.37f32, -1.0, 0.37, 2.0, 0.37, 0.5];
            let (scale, offset, packed) = quantize(&values, 2, bits).unwrap();
            assert_eq!(scale[0], 0.0);
            assert_eq!(offset[0], 0.37);
            let back = dequantize(&scale, &offset, &packed, bits, values.len()).unwrap();
            for k in [0, 2, 4] {
                assert_eq!(back[k], 0.37);
            }
            // The extremes of a channel are exact.
            assert_eq!(back[1], -1.0);
            assert!((back[3] - 2.0).abs() < 1e-6);
        }
    }

    #[test]
    fn packing_is_little_end_first() {
        let values = [0.0f32, 3.0, 1.0, 2.0];
        let (_, _, p2) = quantize(&values, 1, 2).unwrap();
        assert_eq!(p2, vec![0b10_01_11_00]);
        let (_, _, p4) = quantize(&values, 1, 4).unwrap();
        assert_eq!(p4, vec![0xf0, 0xa5]);
    }

    #[test]
    fn bad_arguments_are_errors() {
        assert_eq!(quantize(&[1.0], 1, 3), Err(QuantError::Bits(3)));
        assert_eq!(quantize(&[1.0], 1, 16), Err(QuantError::Bits(16)));
        assert_eq!(quantize(&[1.0], 0, 8), Err(QuantError::NoChannels));
        assert!(matches!(quantize(&[1.0, 2.0, 3.0], 2, 8), Err(QuantError::Ragged { .. })));
        assert!(matches!(quantize(&[1.0, f32::NAN], 1, 8), Err(QuantError::NonFinite { index: 1, .. })));
        assert!(matches!(dequantize(&[1.0], &[0.0], &[0u8; 1], 8, 2), Err(QuantError::PackedSize { .. })));
        assert!(matches!(quantize(&[-3e38, 3e38], 1, 8), Err(QuantError::Range { .. })));
        assert_eq!(packed_len(usize::MAX, 8), None);
    }
}
