//! Automatic exposure and sRGB quantisation of linear RGB images.
#![deny(unsafe_code)]

use crate::color::srgb::linear_to_srgb;
use ndarray::{s, Array3, ArrayView3, Axis};

/// Percentile of the per-pixel maximum channel that automatic exposure maps to white.
pub const AUTO_EXPOSURE_PERCENTILE: f64 = 99.5;

/// Value at percentile `p` (0–100) of the finite entries of `values` (nearest rank); lives in
/// [`crate::stats`].
pub use crate::stats::percentile;

/// Scale that maps the [`AUTO_EXPOSURE_PERCENTILE`] of the per-pixel maximum channel of
/// `linear` (H, W, 3) to 1. Returns 1 for an all-dark image.
pub fn auto_exposure_scale(linear: ArrayView3<f32>) -> f32 {
    let maxima = linear
        .lanes(Axis(2))
        .into_iter()
        .map(|px| px.iter().copied().fold(f32::NEG_INFINITY, f32::max));
    match percentile(maxima, AUTO_EXPOSURE_PERCENTILE) {
        Some(p) if p > 0.0 => 1.0 / p,
        _ => 1.0,
    }
}

/// `linear` × `scale`, clipped and sRGB-encoded to 8 bits.
pub fn encode_srgb8(linear: ArrayView3<f32>, scale: f32) -> Array3<u8> {
    linear.mapv(|v| {
        let v = if v.is_finite() { v * scale } else { 0.0 };
        (linear_to_srgb(v) * 255.0).round() as u8
    })
}

/// `linear` × `scale`, clipped and sRGB-encoded to 16 bits.
pub fn encode_srgb16(linear: ArrayView3<f32>, scale: f32) -> Array3<u16> {
    linear.mapv(|v| {
        let v = if v.is_finite() { v * scale } else { 0.0 };
        (linear_to_srgb(v) * 65535.0).round() as u16
    })
}

/// Places images of equal height side by side with `gap` pixels of `fill` between them.
pub fn hstack<T: Copy>(images: &[ArrayView3<T>], gap: usize, fill: T) -> Array3<T> {
    let h = images.iter().map(|i| i.dim().0).max().unwrap_or(0);
    let c = images.first().map(|i| i.dim().2).unwrap_or(3);
    let w: usize =
        images.iter().map(|i| i.dim().1).sum::<usize>() + gap * images.len().saturating_sub(1);
    let mut out = Array3::from_elem((h, w, c), fill);
    let mut x0 = 0;
    for img in images {
        let (ih, iw, _) = img.dim();
        out.slice_mut(s![..ih, x0..x0 + iw, ..]).assign(img);
        x0 += iw + gap;
    }
    out
}

/// Places images one above the other with `gap` rows of `fill` between them (left-aligned).
pub fn vstack<T: Copy>(images: &[ArrayView3<T>], gap: usize, fill: T) -> Array3<T> {
    let w = images.iter().map(|i| i.dim().1).max().unwrap_or(0);
    let c = images.first().map(|i| i.dim().2).unwrap_or(3);
    let h: usize =
        images.iter().map(|i| i.dim().0).sum::<usize>() + gap * images.len().saturating_sub(1);
    let mut out = Array3::from_elem((h, w, c), fill);
    let mut y0 = 0;
    for img in images {
        let (ih, iw, _) = img.dim();
        out.slice_mut(s![y0..y0 + ih, ..iw, ..]).assign(img);
        y0 += ih + gap;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn auto_exposure_maps_the_bright_percentile_to_white() {
        let img = Array3::from_shape_fn((10, 100, 3), |(_, x, c)| {
            (x as f32 + 1.0) * (c as f32 + 1.0) * 0.01
        });
        let scale = auto_exposure_scale(img.view());
        // Max channel is c = 2: values 0.03..3.0; the 99.5th percentile is near 3.0.
        assert!((1.0 / scale - 2.985).abs() < 0.02, "{}", 1.0 / scale);
        let enc = encode_srgb8(img.view(), scale);
        assert_eq!(enc[[0, 99, 2]], 255);
        assert!(enc[[0, 0, 0]] < 40);
        assert_eq!(
            auto_exposure_scale(Array3::<f32>::zeros((2, 2, 3)).view()),
            1.0
        );
    }

    #[test]
    fn hstack_places_images_with_gaps() {
        let a = Array3::<u8>::from_elem((2, 3, 3), 1);
        let b = Array3::<u8>::from_elem((2, 2, 3), 2);
        let out = hstack(&[a.view(), b.view()], 1, 0);
        assert_eq!(out.dim(), (2, 6, 3));
        assert_eq!(out[[0, 2, 0]], 1);
        assert_eq!(out[[0, 3, 0]], 0);
        assert_eq!(out[[1, 5, 2]], 2);
    }
}
