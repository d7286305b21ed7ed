//! Temporal blocks of binary frames (supplement §1.1; Ma et al. 2020 §4).
//!
//! Alignment works on block sums: T binary frames are cut into consecutive blocks of B frames
//! whose sums are multi-bit images with enough photons to match patches, while motion within a
//! block stays a fraction of a pixel. The reference block is the one holding the reference frame.
#![forbid(unsafe_code)]

use crate::capture::BinaryFrames;
use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};
use std::ops::Range;

/// How to choose the block size B.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct BlockConfig {
    /// Fixed block size in frames; `None` chooses it from T and the light level.
    pub block_size: Option<usize>,
    /// Smallest automatic block size, frames (supplement §1.1: 100–1000).
    pub min_block_size: usize,
    /// Largest automatic block size, frames.
    pub max_block_size: usize,
    /// Mean detections per pixel a block should collect, counts: B ≈ target / (mean detections
    /// per pixel per frame). 30 counts give a per-pixel SNR of about 5 before aggregation.
    pub target_counts: f64,
    /// Fewest blocks an automatic plan may have (B <= T / `min_blocks`): the motion must be
    /// sampled along the burst, so short captures get blocks below `min_block_size`.
    pub min_blocks: usize,
    /// Floor of the automatic block size when `min_blocks` shortens it, frames.
    pub min_short_block_size: usize,
    /// Most blocks an automatic plan may have: a longer recording gets longer blocks (past
    /// `max_block_size` if need be), as one grey image per block is kept for the whole
    /// reconstruction (0.5 MB at 496x254: 1,000 blocks hold 500 MB). This project's bound.
    pub max_blocks: usize, // 1000
    /// Most steady-pan motion (px at the image corners) one automatic block may collect; a
    /// longer block is re-planned shorter after a first alignment (`burst::estimate_motion`),
    /// as block images smear along a pan. 0 = never. This project's heuristic.
    pub max_steady_smear_px: f64, // 4 px
}

impl Default for BlockConfig {
    fn default() -> Self {
        BlockConfig {
            block_size: None,
            min_block_size: 100,
            max_block_size: 1000,
            target_counts: 30.0,
            min_blocks: 8,
            min_short_block_size: 32,
            max_blocks: 1000,
            max_steady_smear_px: 4.0,
        }
    }
}

impl BlockConfig {
    /// The shortest automatic block of a recording of `frames` frames: no more than
    /// [`Self::max_blocks`] blocks (a plan centred on its reference frame may cut one block
    /// more than T / B), and at least one frame.
    pub fn shortest_for(&self, frames: usize) -> usize {
        frames
            .div_ceil(self.max_blocks.saturating_sub(1).max(1))
            .max(1)
    }
}

/// The cut of T frames into blocks.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BlockPlan {
    /// Nominal block size B, frames (end blocks may be up to 1.5 B or down to B/2, and the
    /// reference block is shorter when the reference frame is within B/2 of an end).
    pub block_size: usize,
    /// Frame ranges of the blocks, in time order, covering 0..T without gaps.
    pub blocks: Vec<Range<usize>>,
    /// Index of the block holding the reference frame.
    pub reference_block: usize,
    /// The reference frame.
    pub reference_frame: usize,
}

impl BlockPlan {
    /// Cuts `frame_count` frames into blocks of `block_size`, placing the reference block so
    /// that `reference_frame` sits at its centre, then tiling outward; a leftover shorter than
    /// B/2 at either end joins its neighbour, a longer one becomes a block of its own.
    pub fn new(frame_count: usize, block_size: usize, reference_frame: usize) -> Result<Self> {
        if frame_count == 0 {
            return Err(Error::invalid("cannot plan blocks for zero frames"));
        }
        if block_size == 0 {
            return Err(Error::invalid("block size must be at least 1 frame"));
        }
        if reference_frame >= frame_count {
            return Err(Error::invalid(format!(
                "reference frame {reference_frame} is outside 0..{frame_count}"
            )));
        }
        let b = block_size.min(frame_count);
        let ref_start = reference_frame.saturating_sub(b / 2);
        let ref_end = (ref_start + b).min(frame_count);
        // Boundaries before the reference block, walking backward.
        let mut starts_before = Vec::new();
        let mut s = ref_start;
        while s > 0 {
            let prev = s.saturating_sub(b);
            starts_before.push(prev);
            s = prev;
        }
        starts_before.reverse();
        let mut bounds: Vec<usize> = starts_before;
        bounds.push(ref_start);
        let mut e = ref_end;
        while e < frame_count {
            bounds.push(e);
            e = (e + b).min(frame_count);
        }
        bounds.push(frame_count);
        let mut blocks: Vec<Range<usize>> = bounds.windows(2).map(|w| w[0]..w[1]).collect();
        // Merge short end blocks (never the reference block itself).
        let ref_of = |blocks: &[Range<usize>]| {
            blocks
                .iter()
                .position(|r| r.contains(&reference_frame))
                .expect("blocks cover every frame")
        };
        if blocks.len() > 1 && blocks[0].len() < b.div_ceil(2) && ref_of(&blocks) != 0 {
            let first = blocks.remove(0);
            blocks[0].start = first.start;
        }
        let n = blocks.len();
        if n > 1 && blocks[n - 1].len() < b.div_ceil(2) && ref_of(&blocks) != n - 1 {
            let last = blocks.pop().expect("n > 1");
            blocks[n - 2].end = last.end;
        }
        let reference_block = ref_of(&blocks);
        Ok(BlockPlan {
            block_size: b,
            blocks,
            reference_block,
            reference_frame,
        })
    }

    /// Plans blocks per `config`: its fixed size, or B = target_counts / (mean detections per
    /// pixel per frame) clamped to [min, max], the light level measured on up to 64 frames
    /// around the reference frame.
    pub fn choose(
        frames: &BinaryFrames,
        reference_frame: usize,
        config: &BlockConfig,
    ) -> Result<Self> {
        let t = frames.frame_count();
        if reference_frame >= t {
            return Err(Error::invalid(format!(
                "reference frame {reference_frame} is outside 0..{t}"
            )));
        }
        let b = match config.block_size {
            Some(b) => b,
            None => {
                if config.min_block_size == 0 || config.min_block_size > config.max_block_size {
                    return Err(Error::invalid(format!(
                        "block size bounds {}..={} are empty or zero",
                        config.min_block_size, config.max_block_size
                    )));
                }
                let n = t.min(64);
                let start = reference_frame.saturating_sub(n / 2).min(t - n);
                let sums = frames.sum_range(start..start + n);
                let total: u64 = sums.iter().map(|&c| c as u64).sum();
                let rate = total as f64 / (sums.len() as f64 * n as f64);
                let wanted = if rate > 0.0 {
                    (config.target_counts / rate).ceil()
                } else {
                    f64::INFINITY
                };
                let by_light = wanted
                    .clamp(config.min_block_size as f64, config.max_block_size as f64)
                    as usize;
                let by_count = (t / config.min_blocks.max(1)).max(config.min_short_block_size);
                by_light.min(by_count).max(config.shortest_for(t))
            }
        };
        BlockPlan::new(t, b, reference_frame)
    }

    /// Number of blocks.
    pub fn len(&self) -> usize {
        self.blocks.len()
    }

    /// Whether there are no blocks (never true for a constructed plan).
    pub fn is_empty(&self) -> bool {
        self.blocks.is_empty()
    }

    /// First frame of each block.
    pub fn start_frames(&self) -> Vec<usize> {
        self.blocks.iter().map(|r| r.start).collect()
    }

    /// Centre frame of each block, `(start + end − 1) / 2` (half-integers for even lengths):
    /// the time at which the block's motion is measured.
    pub fn center_frames(&self) -> Vec<f64> {
        self.blocks
            .iter()
            .map(|r| (r.start + r.end - 1) as f64 / 2.0)
            .collect()
    }
}
