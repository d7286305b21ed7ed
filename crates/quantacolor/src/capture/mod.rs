//! Capture format: a directory with `frames.npy`, `cfa.npy` (or a CFA PNG) and `capture.toml`.
//! See `docs/capture-format.md`.
//!
//! Binary frames stay bit-packed and memory-mapped; block sums come straight from the packed
//! bytes.

pub mod frames;
pub mod io;
pub mod npy;

pub use frames::BinaryFrames;

use crate::cfa::Cfa;
use crate::error::Result;
use ndarray::{Array2, Array3};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Contents of `capture.toml`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CaptureMeta {
    /// Exposure time of one binary frame, seconds.
    pub exposure_s: f64,
    /// Mean dark count rate, counts per second (default 0).
    #[serde(default)]
    pub dark_count_rate_hz: f64,
    /// W = wR·R + wG·G + wB·B (default [1, 1, 1]).
    #[serde(default = "default_w_weights")]
    pub w_weights: [f64; 3],
    /// Optional file name (relative to the capture directory) of a bool (H, W) hot-pixel mask.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub hot_pixels: Option<String>,
    /// Reference frame index (default T/2 rounded down).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reference_frame: Option<usize>,
}

fn default_w_weights() -> [f64; 3] {
    [1.0, 1.0, 1.0]
}

impl CaptureMeta {
    /// Dark counts per binary frame, `d` of paper Eq. 3.
    pub fn dark_counts_per_frame(&self) -> f64 {
        self.dark_count_rate_hz * self.exposure_s
    }
}

/// An opened capture.
#[derive(Debug)]
pub struct Capture {
    /// The capture directory.
    pub dir: PathBuf,
    /// Binary frames (memory-mapped).
    pub frames: BinaryFrames,
    /// Colour filter array, same (H, W) as the frames.
    pub cfa: Cfa,
    /// Metadata from `capture.toml`.
    pub meta: CaptureMeta,
    /// Hot-pixel mask (true = hot or dead), if the capture names one.
    pub hot_pixels: Option<Array2<bool>>,
}

impl Capture {
    /// Opens and validates the capture in `dir`.
    pub fn open(dir: impl AsRef<Path>) -> Result<Capture> {
        let _ = dir;
        todo!("capture helper")
    }

    /// The reference frame: `meta.reference_frame` or T/2 rounded down.
    pub fn reference_frame(&self) -> usize {
        self.meta
            .reference_frame
            .unwrap_or(self.frames.frame_count() / 2)
    }
}

/// Everything needed to write a capture directory.
#[derive(Debug, Clone)]
pub struct CaptureParts<'a> {
    /// Packed frames, uint8 (T, H, ceil(W/8)), MSB first.
    pub packed_frames: &'a Array3<u8>,
    /// Width W in pixels (the packed array pads it to a multiple of 8).
    pub width: usize,
    pub cfa: &'a Cfa,
    pub meta: &'a CaptureMeta,
    /// Written as `hot_pixels.npy` (and named in `capture.toml`) when given.
    pub hot_pixels: Option<&'a Array2<bool>>,
    /// Written as `ground_truth.npy`, float32 (H, W, 3), when given.
    pub ground_truth: Option<&'a Array3<f32>>,
}

/// Writes a capture directory atomically (a temporary sibling directory renamed into place).
pub fn write_capture(dir: impl AsRef<Path>, parts: &CaptureParts<'_>) -> Result<()> {
    let _ = (dir, parts);
    todo!("capture helper")
}
