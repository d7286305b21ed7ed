//! Converting real recordings into capture directories (`quantacolor convert`): a
//! [`FrameSource`] from [`crate::capture::readers`] streamed into a
//! [`CaptureWriter`], with the CFA, hot-pixel mask and metadata the capture needs.
#![forbid(unsafe_code)]

use crate::align::hot_pixels::{detect_hot_pixels, self_calibrate, HotPixelDetectConfig};
use crate::capture::readers::{open_source, FrameSource, RawFormat, SourceSpec};
use crate::capture::{Capture, CaptureMeta, CaptureWriter, FrameWindow};
use crate::cfa::colorspad::{colorspad_cfa, colorspad_hot_pixel_mask};
use crate::cfa::{Cfa, Channel};
use crate::error::{Error, Result};
use crate::progress::Progress;
use ndarray::Array2;
use std::path::Path;

/// Exposure of one binary frame written when none is given, seconds: about one frame period
/// of SwissSPAD2 (97.7 kfps) and SPAD512S (up to 100 kfps). It only scales
/// `dark_count_rate_hz`, which conversion leaves at 0, so the reconstruction (in detections
/// per frame) does not depend on it; `capture.toml` records that it was assumed.
pub const DEFAULT_EXPOSURE_S: f64 = 1e-5;

/// How `convert` chooses the hot-pixel mask.
#[derive(Debug, Clone, Default)]
pub enum HotPixelChoice {
    /// The colour SwissSPAD2's shipped mask with `--colorspad`, else detected from the frames.
    #[default]
    Auto,
    /// This mask.
    Mask(Array2<bool>),
    /// No mask.
    None,
}

/// Everything `quantacolor convert` was asked.
#[derive(Debug, Clone, Default)]
pub struct ConvertRequest {
    /// Input format and its options.
    pub source: SourceSpec,
    /// The capture's CFA; default: the colour SwissSPAD2 CFA with `--colorspad`, else all W
    /// (monochrome sensor). Required for RGB photon cubes.
    pub cfa: Option<Cfa>,
    pub hot_pixels: HotPixelChoice,
    /// Exposure of one binary frame, seconds (default [`DEFAULT_EXPOSURE_S`]).
    pub exposure_s: Option<f64>,
    /// Frames to convert.
    pub window: FrameWindow,
    /// Settings of hot-pixel detection.
    pub detect: HotPixelDetectConfig,
}

/// Opens `input`, converts it as `request` says into a capture directory at `out`, and says
/// what was written.
pub fn convert_input(
    input: &Path,
    out: &Path,
    request: &ConvertRequest,
    progress: &dyn Progress,
) -> Result<ConvertSummary> {
    let exposure_s = request.exposure_s.unwrap_or(DEFAULT_EXPOSURE_S);
    if !(exposure_s.is_finite() && exposure_s > 0.0) {
        return Err(Error::invalid(format!(
            "the exposure must be a positive number of seconds, got {exposure_s}"
        )));
    }
    let mut source = open_source(input, &request.source, request.cfa.as_ref())?;
    let (h, w) = (source.height(), source.width());
    let cfa = match (&request.cfa, request.source.colorspad) {
        (Some(c), _) => c.clone(),
        (None, true) => colorspad_cfa(),
        (None, false) => Cfa::uniform(h, w, Channel::W),
    };
    let (hot_pixels, origin) = match &request.hot_pixels {
        HotPixelChoice::Auto if request.source.colorspad => (
            HotPixels::Mask(colorspad_hot_pixel_mask()),
            "colorspad-calibration",
        ),
        HotPixelChoice::Auto => (HotPixels::Detect(request.detect.clone()), "detected"),
        HotPixelChoice::Mask(m) => (HotPixels::Mask(m.clone()), "given"),
        HotPixelChoice::None => (HotPixels::None, "none"),
    };
    let mut table = toml::Table::new();
    let format = request.source.format.map_or("none", |f| f.name());
    table.insert("format".into(), format.into());
    table.insert("input".into(), input.display().to_string().into());
    table.insert("description".into(), source.describe().into());
    table.insert(
        "exposure_assumed".into(),
        request.exposure_s.is_none().into(),
    );
    table.insert("hot_pixels".into(), origin.into());
    if request.source.colorspad {
        table.insert("colorspad".into(), true.into());
    }
    if request.source.format == Some(RawFormat::Spad512s) {
        let o = &request.source.spad512s;
        table.insert("trailer_bytes".into(), (o.trailer_bytes as i64).into());
        table.insert(
            "orientation".into(),
            format!("{:?}", o.orientation).to_lowercase().into(),
        );
    }
    let range = request
        .window
        .resolve(source.frame_count())
        .map_err(|e| Error::invalid(format!("{}: {e}", source.describe())))?;
    table.insert("first_frame".into(), (range.start as i64).into());
    table.insert("source_frames".into(), (source.frame_count() as i64).into());
    let mut extra = toml::Table::new();
    extra.insert("source".into(), toml::Value::Table(table));
    let options = ConvertOptions {
        window: request.window,
        cfa,
        meta: CaptureMeta::new(exposure_s),
        hot_pixels,
        extra_toml: Some(extra),
    };
    convert(source.as_mut(), out, &options, progress)
}

/// Where the converted capture's hot-pixel mask comes from.
#[derive(Debug, Clone)]
pub enum HotPixels {
    /// This mask (e.g. the colour SwissSPAD2's shipped inpaint mask).
    Mask(Array2<bool>),
    /// Detected from the converted frames ([`detect_hot_pixels`]).
    Detect(HotPixelDetectConfig),
    /// No mask.
    None,
}

/// Everything [`convert`] writes besides the frames.
#[derive(Debug, Clone)]
pub struct ConvertOptions {
    /// Frames to convert.
    pub window: FrameWindow,
    /// The capture's CFA (H, W of the frames).
    pub cfa: Cfa,
    /// The capture's metadata (`hot_pixels` is set by [`convert`]).
    pub meta: CaptureMeta,
    pub hot_pixels: HotPixels,
    /// Tables added to `capture.toml` (e.g. `[source]`).
    pub extra_toml: Option<toml::Table>,
}

/// What [`convert`] wrote.
#[derive(Debug, Clone, PartialEq)]
pub struct ConvertSummary {
    /// Frames written.
    pub frames: usize,
    /// First source frame written.
    pub first_frame: usize,
    pub height: usize,
    pub width: usize,
    /// Hot pixels in the written mask (`None` = no mask).
    pub hot_pixels: Option<usize>,
    /// Whether the mask was detected from the frames.
    pub hot_pixels_detected: bool,
}

/// Streams the frames of `options.window` from `source` into a capture directory at `out`
/// (atomically: nothing is left behind on error, an existing capture is replaced only when
/// the new one is complete), then writes the CFA, hot-pixel mask and metadata.
pub fn convert(
    source: &mut dyn FrameSource,
    out: &Path,
    options: &ConvertOptions,
    progress: &dyn Progress,
) -> Result<ConvertSummary> {
    let (h, w) = (source.height(), source.width());
    if options.cfa.codes().dim() != (h, w) {
        return Err(Error::invalid(format!(
            "the CFA is {}x{} (H x W), the frames of {} are {h}x{w}",
            options.cfa.height(),
            options.cfa.width(),
            source.describe()
        )));
    }
    if let HotPixels::Mask(m) = &options.hot_pixels {
        if m.dim() != (h, w) {
            return Err(Error::invalid(format!(
                "the hot-pixel mask is {:?}, the frames are ({h}, {w})",
                m.dim()
            )));
        }
    }
    let range = options
        .window
        .resolve(source.frame_count())
        .map_err(|e| Error::invalid(format!("{}: {e}", source.describe())))?;
    let mut writer = CaptureWriter::create(out, range.len(), h, w)?;
    let mut frame = vec![0u8; writer.frame_bytes()];
    progress.start("converting", range.len() as u64);
    for t in range.clone() {
        source.read_frame(t, &mut frame)?;
        writer.write_frame(&frame)?;
        progress.advance(1);
    }
    progress.finish();
    let (mask, detected) = match &options.hot_pixels {
        HotPixels::Mask(m) => (Some(m.clone()), false),
        HotPixels::Detect(config) => {
            let frames = writer.frames()?;
            let mask = detect_hot_pixels(&frames, &options.cfa, options.meta.w_weights, config)?;
            (Some(mask), true)
        }
        HotPixels::None => (None, false),
    };
    writer.finish(
        &options.cfa,
        &options.meta,
        mask.as_ref(),
        options.extra_toml.as_ref(),
    )?;
    Ok(ConvertSummary {
        frames: range.len(),
        first_frame: range.start,
        height: h,
        width: w,
        hot_pixels: mask.map(|m| m.iter().filter(|&&v| v).count()),
        hot_pixels_detected: detected,
    })
}

/// Opens a capture the way `reconstruct` and `align` read it: the frame window `frames`, then,
/// when the capture names no hot-pixel mask and `detect_hot_pixels` is set, a mask detected from
/// its own frames ([`self_calibrate`]).
pub fn open_capture(
    dir: &Path,
    frames: Option<&FrameWindow>,
    detect_hot_pixels: bool,
) -> Result<Capture> {
    let mut capture = Capture::open(dir)?;
    if let Some(window) = frames {
        capture = capture.window(window)?;
    }
    if detect_hot_pixels {
        self_calibrate(&mut capture, &HotPixelDetectConfig::default())?;
    }
    Ok(capture)
}
