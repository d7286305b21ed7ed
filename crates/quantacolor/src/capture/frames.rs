//! Binary frames: bit-packed (T, H, ceil(W/8)) or unpacked 0/1 (T, H, W), memory-mapped.

use crate::error::Result;
use ndarray::{Array2, Array3};
use std::ops::Range;
use std::path::Path;

/// A stack of T binary frames of H x W pixels.
#[derive(Debug)]
pub struct BinaryFrames {
    frame_count: usize,
    height: usize,
    width: usize,
}

impl BinaryFrames {
    /// Memory-maps `path` (a `.npy`), for frames `width` pixels wide.
    pub fn open(path: &Path, width: usize) -> Result<BinaryFrames> {
        let _ = (path, width);
        todo!("capture helper")
    }

    /// Wraps packed frames held in memory, uint8 (T, H, ceil(width/8)).
    pub fn from_packed(packed: Array3<u8>, width: usize) -> Result<BinaryFrames> {
        let _ = (packed, width);
        todo!("capture helper")
    }

    /// Number of frames T.
    pub fn frame_count(&self) -> usize {
        self.frame_count
    }

    /// Height H.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Width W.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Per-pixel count of ones over `frames`, (H, W).
    pub fn sum_range(&self, frames: Range<usize>) -> Array2<u32> {
        let _ = frames;
        todo!("capture helper")
    }

    /// One frame unpacked to 0/1, (H, W).
    pub fn frame(&self, t: usize) -> Array2<u8> {
        let _ = t;
        todo!("capture helper")
    }
}
