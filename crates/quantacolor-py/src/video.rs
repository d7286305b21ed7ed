//! The native steps of `quantacolor.batch.reconstruct_video`: a video of a long recording made
//! in pieces (`quantacolor::video`), whose assembled files are those of `quantacolor
//! reconstruct CAPTURE --video --stride S --window N` (per-frame motion).
//!
//! - `video_prepare`: the plan, and the hot-pixel mask of the whole recording saved beside the
//!   parts (every piece uses the one mask `reconstruct` detects at opening);
//! - `video_parts`: some video frames, each reconstructed from its window and saved as a part;
//! - `video_assemble`: every part streamed in order into the video directory.

#![forbid(unsafe_code)]

use crate::errors::{compute, lib_err};
use crate::reconstruct::{reconstruct_config, OverrideArgs};
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use quantacolor::capture::{io, Capture};
use quantacolor::pipeline::ReconstructConfig;
use quantacolor::progress::Silent;
use quantacolor::video::{
    assemble_parts, part_path, reconstruct_frame, write_part, VideoPlan, VideoReport,
};
use std::path::{Path, PathBuf};

/// The mask file inside a parts directory.
const PARTS_HOT_PIXELS: &str = "hot_pixels.npy";

/// The options a video frame takes (those of `reconstruct`, but its reference frame and
/// window, which the video sets).
const VIDEO_OPTIONS: &str =
    "method, denoise, scale, config, sigma_y, sigma_c, block_size, max_sub_block_motion";

/// The plan of a video of `frame_count` frames, as `stride` and `window` gave it.
fn plan(frame_count: usize, stride: i64, window: Option<i64>) -> PyResult<VideoPlan> {
    let stride = usize::try_from(stride)
        .map_err(|_| PyValueError::new_err(format!("stride must be >= 1, got {stride}")))?;
    let window = match window {
        Some(w) if w < 1 => {
            return Err(PyValueError::new_err(format!(
                "window must be >= 1, got {w}"
            )))
        }
        w => w.map(|w| w as usize),
    };
    VideoPlan::new(frame_count, stride, window).map_err(|e| {
        // The library names the CLI's flags; Python has keywords.
        let text = e
            .to_string()
            .replace("--stride", "stride")
            .replace("--window", "window");
        PyValueError::new_err(text)
    })
}

/// The reconstruction settings of every video frame: `options` (a dict of [`VIDEO_OPTIONS`])
/// with the video's window applied as `reconstruct --window` applies it.
fn frame_config(
    options: Option<&Bound<'_, PyDict>>,
    window: Option<i64>,
) -> PyResult<ReconstructConfig> {
    let (mut method, mut denoise): (Option<String>, Option<String>) = (None, None);
    let (mut scale, mut block_size): (Option<i64>, Option<i64>) = (None, None);
    let (mut sigma_y, mut sigma_c): (Option<f32>, Option<f32>) = (None, None);
    let mut max_sub_block_motion: Option<f64> = None;
    let mut config: Option<Bound<'_, PyAny>> = None;
    for (key, value) in options.into_iter().flat_map(|d| d.iter()) {
        let key: String = key.extract()?;
        let bad = |e: PyErr| PyTypeError::new_err(format!("{key}: {e}"));
        match key.as_str() {
            "method" => method = value.extract().map_err(bad)?,
            "denoise" => denoise = value.extract().map_err(bad)?,
            "scale" => scale = value.extract().map_err(bad)?,
            "block_size" => block_size = value.extract().map_err(bad)?,
            "sigma_y" => sigma_y = value.extract().map_err(bad)?,
            "sigma_c" => sigma_c = value.extract().map_err(bad)?,
            "max_sub_block_motion" => max_sub_block_motion = value.extract().map_err(bad)?,
            "config" => config = Some(value),
            other => {
                return Err(PyTypeError::new_err(format!(
                    "unknown option {other:?}; a video frame takes {VIDEO_OPTIONS}"
                )))
            }
        }
    }
    let overrides = OverrideArgs {
        method: method.as_deref(),
        denoise: denoise.as_deref(),
        scale,
        reference_frame: None,
        sigma_y,
        sigma_c,
        block_size,
        max_sub_block_motion,
        window,
    }
    .overrides()?;
    reconstruct_config(config.as_ref(), &overrides)
}

/// The capture as `reconstruct` reads it, with the mask saved by `video_prepare`.
fn open_with_parts_mask(capture_dir: &Path, parts_dir: &Path) -> quantacolor::Result<Capture> {
    let mut capture = quantacolor::convert::open_capture(capture_dir, None, false)?;
    let mask = parts_dir.join(PARTS_HOT_PIXELS);
    if mask.is_file() {
        capture.hot_pixels = Some(io::read_npy_2d::<bool>(&mask)?);
    }
    Ok(capture)
}

/// One video frame as Python sees it: (index, reference_frame, first_frame, end_frame, done).
type PlannedFrame = (usize, usize, usize, usize, bool);

/// Opens `capture_dir` as `reconstruct` does (hot pixels detected when it names no mask),
/// saves its mask into `parts_dir` (created) and returns the video's frames as
/// `(index, reference_frame, first_frame, end_frame, done)` tuples, `done` when the frame's
/// part is already in `parts_dir`.
#[pyfunction]
#[pyo3(signature = (capture_dir, parts_dir, stride, window=None))]
pub(crate) fn video_prepare(
    py: Python<'_>,
    capture_dir: PathBuf,
    parts_dir: PathBuf,
    stride: i64,
    window: Option<i64>,
) -> PyResult<Vec<PlannedFrame>> {
    compute(py, || {
        let capture = quantacolor::convert::open_capture(&capture_dir, None, true)
            .map_err(|e| lib_err("", e))?;
        let plan = plan(capture.frames.frame_count(), stride, window)?;
        std::fs::create_dir_all(&parts_dir)
            .map_err(|e| lib_err("", quantacolor::Error::io(&parts_dir, e)))?;
        if let Some(mask) = &capture.hot_pixels {
            io::write_npy(parts_dir.join(PARTS_HOT_PIXELS), mask).map_err(|e| lib_err("", e))?;
        }
        Ok(plan
            .frames
            .iter()
            .map(|f| {
                let done = part_path(&parts_dir, f.index).is_file();
                (
                    f.index,
                    f.reference_frame,
                    f.frames.start,
                    f.frames.end,
                    done,
                )
            })
            .collect())
    })
}

/// Reconstructs the video frames `indices` of `capture_dir` (each from its window, with the
/// options of `options`) and saves each as a part in `parts_dir`, atomically; returns the
/// seconds each took.
#[pyfunction]
#[pyo3(signature = (capture_dir, parts_dir, indices, stride, window=None, options=None))]
pub(crate) fn video_parts(
    py: Python<'_>,
    capture_dir: PathBuf,
    parts_dir: PathBuf,
    indices: Vec<usize>,
    stride: i64,
    window: Option<i64>,
    options: Option<&Bound<'_, PyDict>>,
) -> PyResult<Vec<f64>> {
    let config = frame_config(options, window)?;
    compute(py, || {
        let capture = open_with_parts_mask(&capture_dir, &parts_dir).map_err(|e| lib_err("", e))?;
        let plan = plan(capture.frames.frame_count(), stride, window)?;
        indices
            .iter()
            .map(|&i| {
                let start = std::time::Instant::now();
                let frame = plan.frames.get(i).ok_or_else(|| {
                    PyValueError::new_err(format!(
                        "indices: video frame {i} is not among the {} frames",
                        plan.frames.len()
                    ))
                })?;
                let rec = reconstruct_frame(&capture, &config, frame, &Silent)
                    .map_err(|e| lib_err("", e))?;
                write_part(&part_path(&parts_dir, i), rec.linear.view())
                    .map_err(|e| lib_err("", e))?;
                Ok(start.elapsed().as_secs_f64())
            })
            .collect()
    })
}

/// Streams every part in `parts_dir` into the video directory `out_dir` (written atomically),
/// with `video.toml` naming the capture as `capture_dir` was given; returns `out_dir`.
#[pyfunction]
#[pyo3(signature = (capture_dir, parts_dir, out_dir, stride, window=None, options=None))]
pub(crate) fn video_assemble(
    py: Python<'_>,
    capture_dir: PathBuf,
    parts_dir: PathBuf,
    out_dir: PathBuf,
    stride: i64,
    window: Option<i64>,
    options: Option<&Bound<'_, PyDict>>,
) -> PyResult<PathBuf> {
    let config = frame_config(options, window)?;
    let label = capture_dir.display().to_string();
    compute(py, || {
        let capture =
            quantacolor::capture::Capture::open(&capture_dir).map_err(|e| lib_err("", e))?;
        let plan = plan(capture.frames.frame_count(), stride, window)?;
        let report = VideoReport::new(label, &config, &plan);
        assemble_parts(&parts_dir, &out_dir, &plan, report).map_err(|e| lib_err("", e))
    })
}
