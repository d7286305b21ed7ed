//! The display pipeline for linear reconstructions (paper §7, Fig. 14 and Fig. 20; supplement
//! §4): colour correction -> noise-aware low-light blend -> exposure -> tone map -> sRGB.

use super::ccm::ColorMatrix;
use super::mesopic::mesopic_blend;
use super::srgb::linear_to_srgb;
use super::tonemap::{tone_map, ToneMap};
use crate::capture::io;
use crate::error::{Error, Result};
use ndarray::{Array3, ArrayView3};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Options of [`render`].
///
/// The default tone map is the global Reinhard operator ([`ToneMap::Global`]): it needs no
/// exposure guess (key 0.18 on the log-average luminance), keeps HDR highlights below white and
/// looks natural on low-light captures. Mantiuk06, which the paper's HDR figures use, is one
/// option away ([`ToneMap::Mantiuk06`]); with pfstmo's contrast factor 0.3 it renders the
/// simulated chart visibly flatter, so it is not the default. [`ToneMap::None`] gives a plain
/// exposure-and-clip view.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct RenderOptions {
    /// Exposure scale applied before tone mapping; `None` = automatic (see [`tone_map`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub exposure: Option<f32>,
    /// Colour correction matrix (paper Fig. 14); `None` = none.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub color_matrix: Option<ColorMatrix>,
    pub tonemap: ToneMap,
    /// Offset `L0` of the noise-aware low-light blend (supplement Eq. 9); `None` = off.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mesopic: Option<f32>,
    /// Luminance weights of the W pixel over R, G, B (capture.toml's `w_weights`), used by the
    /// low-light blend.
    pub w_weights: [f64; 3],
}

impl Default for RenderOptions {
    fn default() -> Self {
        RenderOptions {
            exposure: None,
            color_matrix: None,
            tonemap: ToneMap::default(),
            mesopic: None,
            w_weights: [1.0, 1.0, 1.0],
        }
    }
}

/// Renders a linear reconstruction (H, W, 3), in detections per frame, to display-referred
/// linear RGB in [0, 1] (before the sRGB transfer function and quantisation).
pub fn render(linear: ArrayView3<f32>, options: &RenderOptions) -> Result<Array3<f32>> {
    let (h, w, c) = linear.dim();
    if c != 3 || h == 0 || w == 0 {
        return Err(Error::invalid(format!(
            "expected a non-empty (H, W, 3) RGB image, got shape {:?}",
            linear.dim()
        )));
    }
    let corrected = match &options.color_matrix {
        Some(m) => m.apply(linear)?,
        None => linear.to_owned(),
    };
    let blended = match options.mesopic {
        Some(l0) => mesopic_blend(corrected.view(), l0 as f64, options.w_weights)?,
        None => corrected,
    };
    tone_map(blended.view(), options.exposure, &options.tonemap)
}

/// sRGB-encodes display-referred linear values (clamped to [0, 1]) to 8 bits.
pub fn quantise8(display: ArrayView3<f32>) -> Array3<u8> {
    display.mapv(|v| (linear_to_srgb(if v.is_finite() { v } else { 0.0 }) * 255.0).round() as u8)
}

/// sRGB-encodes display-referred linear values (clamped to [0, 1]) to 16 bits.
pub fn quantise16(display: ArrayView3<f32>) -> Array3<u16> {
    display.mapv(|v| (linear_to_srgb(if v.is_finite() { v } else { 0.0 }) * 65535.0).round() as u16)
}

/// [`render`] then 8-bit sRGB.
pub fn render_srgb8(linear: ArrayView3<f32>, options: &RenderOptions) -> Result<Array3<u8>> {
    Ok(quantise8(render(linear, options)?.view()))
}

/// [`render`] then 16-bit sRGB.
pub fn render_srgb16(linear: ArrayView3<f32>, options: &RenderOptions) -> Result<Array3<u16>> {
    Ok(quantise16(render(linear, options)?.view()))
}

/// Bit depth of a written image.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum BitDepth {
    Eight,
    Sixteen,
}

/// Renders `linear` and writes it atomically to `path`: `.png` (8 or 16 bit) or `.tif`/`.tiff`
/// (16 bit only). An unknown extension or 8-bit TIFF is an error naming `path`; nothing is
/// written on any error.
pub fn write_rendered(
    path: impl AsRef<Path>,
    linear: ArrayView3<f32>,
    options: &RenderOptions,
    bits: BitDepth,
) -> Result<()> {
    let path = path.as_ref();
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    // Check the name before the (costly) rendering.
    let tiff = match (ext.as_str(), bits) {
        ("png", _) => false,
        ("tif" | "tiff", BitDepth::Sixteen) => true,
        ("tif" | "tiff", BitDepth::Eight) => {
            return Err(Error::format(
                path,
                "TIFF output is 16-bit only (use --bits 16 or a .png name)",
            ))
        }
        _ => {
            return Err(Error::format(
                path,
                format!("unknown image extension '{ext}' (expected .png, .tif or .tiff)"),
            ))
        }
    };
    match bits {
        BitDepth::Eight => io::write_png_rgb8(path, &render_srgb8(linear, options)?),
        BitDepth::Sixteen if tiff => io::write_tiff_rgb16(path, &render_srgb16(linear, options)?),
        BitDepth::Sixteen => io::write_png_rgb16(path, &render_srgb16(linear, options)?),
    }
}
