//! The display pipeline for linear reconstructions (paper §7, Fig. 14 and Fig. 20; supplement
//! §4): colour correction -> noise-aware low-light blend -> exposure -> tone map -> sRGB.
#![forbid(unsafe_code)]

use super::ccm::ColorMatrix;
use super::mesopic::{mesopic_blend, MesopicConfig, MesopicParams};
use super::tonemap::{tone_map, ToneMap};
use crate::capture::io;
use crate::color::srgb::linear_to_srgb;
use crate::error::{Error, Result};
use ndarray::{Array3, Array4, ArrayView3, ArrayView4, Axis};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Options of [`render`].
///
/// The default tone map is the global Reinhard operator ([`ToneMap::Global`]), also for HDR
/// reconstructions: it needs no exposure guess (key 0.18 on the log-average luminance), keeps
/// HDR highlights below white and shows the least noise. Mantiuk06, which the paper's HDR
/// figures use, is one option away ([`ToneMap::Mantiuk06`]); it now matches the reference
/// `pfstmo_mantiuk06` closely (tests/mantiuk_crosscheck.rs), and like the reference it raises
/// the small contrasts of the shadows, where a photon-limited reconstruction keeps its noise
/// (side by side on simulated HDR reconstructions: more local contrast, visibly noisier
/// skies and walls), so it is not the default. [`ToneMap::None`] gives a plain
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
    /// The noise-aware low-light blend (supplement Eq. 9–10, see [`super::mesopic`]); `None` =
    /// off.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mesopic: Option<MesopicConfig>,
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

fn check_image(linear: ArrayView3<f32>) -> Result<()> {
    let (h, w, c) = linear.dim();
    if c != 3 || h == 0 || w == 0 {
        return Err(Error::invalid(format!(
            "expected a non-empty (H, W, 3) RGB image, got shape {:?}",
            linear.dim()
        )));
    }
    Ok(())
}

/// The low-light blend's parameters for `linear` under `options` (`None` when it is off); with
/// `--mesopic auto` this measures the noise ([`MesopicConfig::resolve`]).
pub fn mesopic_params(
    linear: ArrayView3<f32>,
    options: &RenderOptions,
) -> Result<Option<MesopicParams>> {
    check_image(linear)?;
    options
        .mesopic
        .as_ref()
        .map(|m| m.resolve(linear, options.w_weights))
        .transpose()
}

/// Renders a linear reconstruction (H, W, 3), in detections per frame, to display-referred
/// linear RGB in [0, 1] (before the sRGB transfer function and quantisation).
pub fn render(linear: ArrayView3<f32>, options: &RenderOptions) -> Result<Array3<f32>> {
    let params = mesopic_params(linear, options)?;
    render_with(linear, options, params.as_ref())
}

/// [`render`] with the low-light blend's parameters already resolved.
fn render_with(
    linear: ArrayView3<f32>,
    options: &RenderOptions,
    mesopic: Option<&MesopicParams>,
) -> Result<Array3<f32>> {
    check_image(linear)?;
    let corrected = match &options.color_matrix {
        Some(m) => m.apply(linear)?,
        None => linear.to_owned(),
    };
    let blended = match mesopic {
        Some(p) => mesopic_blend(corrected.view(), p, options.w_weights)?,
        None => corrected,
    };
    tone_map(blended.view(), options.exposure, &options.tonemap)
}

/// Renders a video stack (N, H, W, 3) frame by frame, so that the sequence does not flicker:
/// the low-light blend's parameters come from the whole stack, and the global operators
/// ([`ToneMap::Global`], [`ToneMap::None`]) take one exposure and white point from the whole
/// stack (they see it as one (N·H, W, 3) image, which is the same pixels). Mantiuk06 is local,
/// so each frame is tone mapped on its own.
pub fn render_stack(stack: ArrayView4<f32>, options: &RenderOptions) -> Result<Array4<f32>> {
    let (n, h, w, c) = stack.dim();
    if n == 0 || h == 0 || w == 0 || c != 3 {
        return Err(Error::invalid(format!(
            "expected a non-empty (N, H, W, 3) video stack, got shape {:?}",
            stack.dim()
        )));
    }
    let tall = stack
        .as_standard_layout()
        .into_owned()
        .into_shape_with_order((n * h, w, 3))
        .expect("standard layout");
    let mesopic = mesopic_params(tall.view(), options)?;
    match options.tonemap {
        ToneMap::Mantiuk06(_) => {
            let mut out = Array4::<f32>::zeros((n, h, w, 3));
            for (i, frame) in stack.axis_iter(Axis(0)).enumerate() {
                out.index_axis_mut(Axis(0), i).assign(&render_with(
                    frame,
                    options,
                    mesopic.as_ref(),
                )?);
            }
            Ok(out)
        }
        ToneMap::Global(_) | ToneMap::None => {
            Ok(render_with(tall.view(), options, mesopic.as_ref())?
                .into_shape_with_order((n, h, w, 3))
                .expect("same number of pixels"))
        }
    }
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

/// Whether `path` names a TIFF (else a PNG) for `bits`; an unknown extension or 8-bit TIFF is an
/// error naming `path`.
pub fn output_is_tiff(path: &Path, bits: BitDepth) -> Result<bool> {
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    match (ext.as_str(), bits) {
        ("png", _) => Ok(false),
        ("tif" | "tiff", BitDepth::Sixteen) => Ok(true),
        ("tif" | "tiff", BitDepth::Eight) => Err(Error::format(
            path,
            "TIFF output is 16-bit only (use --bits 16 or a .png name)",
        )),
        _ => Err(Error::format(
            path,
            format!("unknown image extension '{ext}' (expected .png, .tif or .tiff)"),
        )),
    }
}

/// The file of frame `index` of a video written as `path`: `OUT.png` -> `OUT_0007.png` (at
/// least four digits).
pub fn frame_path(path: &Path, index: usize) -> std::path::PathBuf {
    let stem = path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    let name = match path.extension() {
        Some(ext) => format!("{stem}_{index:05}.{}", ext.to_string_lossy()),
        None => format!("{stem}_{index:05}"),
    };
    path.with_file_name(name)
}

/// Writes display-referred linear RGB (from [`render`]) atomically to `path` as sRGB: `.png` (8
/// or 16 bit) or `.tif`/`.tiff` (16 bit only).
pub fn write_display(
    path: impl AsRef<Path>,
    display: ArrayView3<f32>,
    bits: BitDepth,
) -> Result<()> {
    let path = path.as_ref();
    let tiff = output_is_tiff(path, bits)?;
    match bits {
        BitDepth::Eight => io::write_png_rgb8(path, &quantise8(display)),
        BitDepth::Sixteen if tiff => io::write_tiff_rgb16(path, &quantise16(display)),
        BitDepth::Sixteen => io::write_png_rgb16(path, &quantise16(display)),
    }
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
    // Check the name before the (costly) rendering.
    output_is_tiff(path, bits)?;
    write_display(path, render(linear, options)?.view(), bits)
}
