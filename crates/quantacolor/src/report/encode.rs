//! Compact export of linear images for the comparison page: IEEE half floats (binary16) after a
//! power-of-two scale, base64 in a JavaScript data file. Project format, not the paper's.
//!
//! The scale `2^k` is chosen so that the largest finite magnitude maps into [2^14, 2^15]; a
//! power of two changes no mantissa bit, so the only error is the rounding to 11 significant
//! bits: relative error at most 2^-11 down to 2^-14 · 2^-k (29 stops below the maximum), an
//! absolute error of at most 2^-25 · 2^-k below that (binary16 subnormals). `±∞` and NaN are
//! kept (the display pipeline maps them to 0 like non-finite input to `quantacolor display`).
#![forbid(unsafe_code)]

use half::f16;
use ndarray::{Array3, ArrayView3};

/// Largest finite magnitude after scaling (binary16's maximum is 65504).
const SCALED_MAX: f64 = 32768.0;

/// A linear image as binary16 samples of `value · 2^scale_log2`, row-major (H, W, 3).
#[derive(Debug, Clone, PartialEq)]
pub struct HalfImage {
    pub height: usize,
    pub width: usize,
    /// `k` of the module doc: samples hold `value · 2^k`.
    pub scale_log2: i32,
    /// binary16 bit patterns, (H, W, 3) row-major.
    pub bits: Vec<u16>,
}

/// The `k` that maps the largest finite magnitude of `values` into [2^14, 2^15] (0 when all
/// are zero or non-finite).
fn scale_log2(values: impl Iterator<Item = f32>) -> i32 {
    let max = values
        .filter(|v| v.is_finite())
        .fold(0.0f64, |m, v| m.max(v.abs() as f64));
    if max <= 0.0 {
        return 0;
    }
    ((SCALED_MAX / max).log2().floor() as i32).clamp(-120, 120)
}

/// Encodes a linear (H, W, 3) image (see the module doc).
pub fn encode_half(linear: ArrayView3<f32>) -> HalfImage {
    let (height, width, _) = linear.dim();
    let k = scale_log2(linear.iter().copied());
    let factor = 2f64.powi(k);
    let bits = linear
        .iter()
        .map(|&v| f16::from_f64(v as f64 * factor).to_bits())
        .collect();
    HalfImage {
        height,
        width,
        scale_log2: k,
        bits,
    }
}

/// The linear image a [`HalfImage`] holds (what the page decodes).
pub fn decode_half(img: &HalfImage) -> Array3<f32> {
    let factor = 2f64.powi(-img.scale_log2);
    let values = img
        .bits
        .iter()
        .map(|&b| (f16::from_bits(b).to_f64() * factor) as f32)
        .collect();
    Array3::from_shape_vec((img.height, img.width, 3), values).expect("H·W·3 samples")
}

/// Little-endian bytes of the samples (the page's `Uint16Array` on every platform it runs on).
pub fn half_bytes(img: &HalfImage) -> Vec<u8> {
    img.bits.iter().flat_map(|b| b.to_le_bytes()).collect()
}

const BASE64: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";

/// Standard base64 with padding (RFC 4648 §4), as the browser's `atob` reads it.
pub fn base64(bytes: &[u8]) -> String {
    let mut out = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for chunk in bytes.chunks(3) {
        let b = [
            chunk[0],
            *chunk.get(1).unwrap_or(&0),
            *chunk.get(2).unwrap_or(&0),
        ];
        let n = (b[0] as u32) << 16 | (b[1] as u32) << 8 | b[2] as u32;
        for i in 0..4 {
            if i <= chunk.len() {
                out.push(BASE64[(n >> (18 - 6 * i) & 63) as usize] as char);
            } else {
                out.push('=');
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn base64_matches_rfc4648_vectors() {
        for (input, expected) in [
            ("", ""),
            ("f", "Zg=="),
            ("fo", "Zm8="),
            ("foo", "Zm9v"),
            ("foob", "Zm9vYg=="),
            ("fooba", "Zm9vYmE="),
            ("foobar", "Zm9vYmFy"),
        ] {
            assert_eq!(base64(input.as_bytes()), expected, "{input}");
        }
        assert_eq!(base64(&[0xff, 0xfe, 0x00]), "//4A");
    }

    #[test]
    fn scale_puts_the_maximum_just_below_2_pow_15() {
        let img = Array3::from_shape_fn((2, 3, 3), |(y, x, c)| 0.001 * (1 + y + x + c) as f32);
        let enc = encode_half(img.view());
        let max_scaled = 0.006 * 2f64.powi(enc.scale_log2);
        assert!((16384.0..=32768.0).contains(&max_scaled), "{max_scaled}");
        assert_eq!(scale_log2([0.0f32, f32::NAN].into_iter()), 0);
        assert_eq!(scale_log2([1.0f32].into_iter()), 15);
        assert_eq!(scale_log2([1.5f32, -2.0, f32::INFINITY].into_iter()), 14);
    }

    #[test]
    fn non_finite_values_survive() {
        let img = Array3::from_shape_vec(
            (1, 2, 3),
            vec![f32::INFINITY, f32::NEG_INFINITY, f32::NAN, 0.5, -0.25, 0.0],
        )
        .unwrap();
        let dec = decode_half(&encode_half(img.view()));
        assert_eq!(dec[[0, 0, 0]], f32::INFINITY);
        assert_eq!(dec[[0, 0, 1]], f32::NEG_INFINITY);
        assert!(dec[[0, 0, 2]].is_nan());
        assert_eq!(dec[[0, 1, 0]], 0.5);
        assert_eq!(dec[[0, 1, 1]], -0.25);
        assert_eq!(dec[[0, 1, 2]], 0.0);
        assert_eq!(half_bytes(&encode_half(img.view())).len(), 12);
    }

    proptest! {
        /// The error bound of the module doc, over images spanning many decades.
        #[test]
        fn round_trip_error_is_within_the_bound(
            values in proptest::collection::vec(
                (-12.0f64..3.0, prop::bool::ANY).prop_map(|(e, neg)| {
                    let v = 10f64.powf(e) as f32;
                    if neg { -v } else { v }
                }),
                3..60,
            )
        ) {
            let n = values.len() / 3;
            let img = Array3::from_shape_vec((1, n, 3), values[..3 * n].to_vec()).unwrap();
            let enc = encode_half(img.view());
            let dec = decode_half(&enc);
            let unit = 2f64.powi(-enc.scale_log2);
            for (&v, &d) in img.iter().zip(dec.iter()) {
                let (v, d) = (v as f64, d as f64);
                let err = (d - v).abs();
                if v.abs() >= 2f64.powi(-14) * unit {
                    prop_assert!(err <= v.abs() * 2f64.powi(-11), "{v} -> {d}");
                } else {
                    prop_assert!(err <= 2f64.powi(-25) * unit * 1.0000001, "{v} -> {d}");
                }
            }
        }
    }
}
