//! The burst reconstruction (paper §4, Fig. 4): alignment of temporal blocks, sub-blocks whose
//! motion agrees to a fraction of a pixel, joint demosaic-merge, RGBW combination and MLE flux.
//!
//! Frames are never visited one at a time with a kernel: each block is cut into sub-blocks
//! short enough that the interpolated motion changes by at most `max_sub_block_motion_px`
//! inside them, their bits are summed straight from the packed words, and the merge treats
//! each sub-block sum as one multi-bit sample per pixel at the sub-block's centre-frame motion.

use crate::align::{align, flow_at, frame_flow, AlignConfig, Alignment, HotPixelCorrector};
use crate::capture::Capture;
use crate::error::Result;
use crate::merge::{
    kernel_field, reference_image, robustness, MergeAccumulator, MergeConfig, MergedBurst,
    SubBlock, SubBlockRobustness,
};
use crate::naive::combine_rgbw;
use crate::pipeline::StageTiming;
use crate::progress::Progress;
use ndarray::{s, Array2, Array3, Axis};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::ops::Range;

/// Configuration of the burst reconstruction.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct BurstConfig {
    pub align: AlignConfig,
    pub merge: MergeConfig,
    /// Largest change of the estimated motion inside one sub-block (px): the error of treating
    /// a sub-block's frames as one sample at its centre-frame motion. Default: infinite, i.e.
    /// one sub-block per alignment block. Measured (builtin chart, handheld, 0.1 photons/px/frame,
    /// 10,000 frames): with the simulator's true motion, cutting blocks into 16 sub-blocks gains
    /// ~4 dB; with the estimated motion it loses 0.7–3 dB, because frame-level interpolation
    /// between blocks spreads tile mismatches that whole blocks' robustness weights reject.
    pub max_sub_block_motion_px: f64, // inf px
    /// Shortest sub-block (frames): bounds the merge cost under very fast motion.
    pub min_sub_block_frames: usize, // 8 frames
}

impl Default for BurstConfig {
    fn default() -> Self {
        BurstConfig {
            align: AlignConfig::default(),
            merge: MergeConfig::default(),
            max_sub_block_motion_px: f64::INFINITY,
            min_sub_block_frames: 8,
        }
    }
}

/// Result of the burst reconstruction with its intermediate stages.
#[derive(Debug, Clone)]
pub struct BurstReconstruction {
    pub alignment: Alignment,
    pub merged: MergedBurst,
    /// Frame ranges of the sub-blocks that were merged.
    pub sub_blocks: Vec<Range<usize>>,
    /// Wall-clock time of each stage.
    pub timings: Vec<StageTiming>,
}

impl BurstReconstruction {
    /// Dense (H, W, 2) flow (dy, dx) that the merge used at (fractional) frame `t`: the scene
    /// point at p in the reference frame is at p + flow(p) in frame t (the convention of
    /// [`crate::simulate::Motion::dense_flow`], so the two compare directly).
    pub fn merge_flow(&self, t: f64) -> Array3<f32> {
        let (_, h, w) = self.alignment.grey.dim();
        let tile_flow = frame_flow(&self.alignment.flow, &self.alignment.plan, t);
        dense_flow(&tile_flow, &self.alignment.grid, h, w)
    }
}

/// Sub-blocks summed and merged at a time: bounds memory to a few (H, W) images per chunk.
const SUB_BLOCK_CHUNK: usize = 8;

/// Dense (H, W, 2) flow from tile flows by bilinear interpolation between tile centres.
pub fn dense_flow(
    tile_flow: &Array3<f32>,
    grid: &crate::align::TileGrid,
    h: usize,
    w: usize,
) -> Array3<f32> {
    let mut dense = Array3::<f32>::zeros((h, w, 2));
    dense
        .axis_iter_mut(Axis(0))
        .into_par_iter()
        .enumerate()
        .for_each(|(y, mut row)| {
            for x in 0..w {
                let f = flow_at(tile_flow, grid, y as f32, x as f32);
                row[[x, 0]] = f[0];
                row[[x, 1]] = f[1];
            }
        });
    dense
}

/// Largest displacement between the frame flows of frames `a` and `b` over all tiles (px).
fn motion_between(alignment: &Alignment, a: f64, b: f64) -> f64 {
    let fa = frame_flow(&alignment.flow, &alignment.plan, a);
    let fb = frame_flow(&alignment.flow, &alignment.plan, b);
    fa.lanes(Axis(2))
        .into_iter()
        .zip(fb.lanes(Axis(2)))
        .map(|(p, q)| (((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2)) as f64).sqrt())
        .fold(0.0, f64::max)
}

/// Cuts every block into equal sub-blocks so that the motion inside each changes by at most
/// `config.max_sub_block_motion_px` (measured between the block's ends from the frame-level
/// motion), never shorter than `config.min_sub_block_frames`.
pub fn plan_sub_blocks(alignment: &Alignment, config: &BurstConfig) -> Vec<(usize, Range<usize>)> {
    let mut out = Vec::new();
    for (b, range) in alignment.plan.blocks.iter().enumerate() {
        let len = range.len();
        let travel = motion_between(
            alignment,
            range.start as f64,
            (range.end.max(range.start + 1) - 1) as f64,
        );
        let pieces_for_motion = (travel / config.max_sub_block_motion_px.max(1e-6)).ceil() as usize;
        let max_pieces = (len / config.min_sub_block_frames.max(1)).max(1);
        let pieces = pieces_for_motion.clamp(1, max_pieces);
        for i in 0..pieces {
            let start = range.start + i * len / pieces;
            let end = range.start + (i + 1) * len / pieces;
            if end > start {
                out.push((b, start..end));
            }
        }
    }
    out
}

/// Runs alignment and the joint demosaic-merge on `capture` for `reference_frame`.
pub fn reconstruct_burst(
    capture: &Capture,
    reference_frame: usize,
    config: &BurstConfig,
    progress: &dyn Progress,
) -> Result<BurstReconstruction> {
    reconstruct_burst_with_motion(capture, reference_frame, config, None, progress)
}

/// Dense (H, W, 2) flow of (fractional) frame `t`: the scene point at p in the reference frame
/// is at p + flow(p) in frame t.
pub type MotionOracle<'a> = &'a (dyn Fn(f64) -> Array3<f32> + Sync);

/// [`reconstruct_burst`] with the merge driven by `motion` instead of the estimated flow when
/// given (e.g. a simulator's true motion: the quality benchmark's upper bound). Alignment still
/// runs for the block plan and the grey images.
pub fn reconstruct_burst_with_motion(
    capture: &Capture,
    reference_frame: usize,
    config: &BurstConfig,
    motion: Option<MotionOracle<'_>>,
    progress: &dyn Progress,
) -> Result<BurstReconstruction> {
    let frames = &capture.frames;
    let (h, w) = (frames.height(), frames.width());
    let hot = capture.hot_pixels.as_ref();
    let mut timings = Vec::new();
    let mut lap = {
        let mut last = std::time::Instant::now();
        move |stage: &str, timings: &mut Vec<StageTiming>| {
            timings.push(StageTiming {
                stage: stage.to_string(),
                seconds: last.elapsed().as_secs_f64(),
            });
            last = std::time::Instant::now();
        }
    };
    let alignment = align(
        frames,
        &capture.cfa,
        hot,
        reference_frame,
        &config.align,
        progress,
    )?;
    lap("align", &mut timings);

    // Reference image, kernels and per-block robustness (supplement §1.2–1.3).
    let grey_blocks: Vec<Array2<f32>> = alignment.grey.outer_iter().map(|g| g.to_owned()).collect();
    let block_flows: Vec<Array3<f32>> = (0..alignment.plan.len())
        .map(|b| match motion {
            Some(oracle) => oracle(alignment.plan.center_frames()[b]),
            None => {
                let tile_flow = alignment.flow.slice(s![b, .., .., ..]).to_owned();
                dense_flow(&tile_flow, &alignment.grid, h, w)
            }
        })
        .collect();
    let reference_block = alignment.plan.reference_block;
    let grey_trials = alignment.plan.block_size as f32;
    let merge_cfg = &config.merge;
    let reference = reference_image(
        &grey_blocks,
        &block_flows,
        reference_block,
        grey_trials,
        &merge_cfg.wiener,
    )?;
    let kernels = kernel_field(&reference, &merge_cfg.kernels)?;
    let robustness_maps = grey_blocks
        .iter()
        .zip(&block_flows)
        .enumerate()
        .map(|(k, (grey, flow))| {
            if k == reference_block {
                Ok(Array2::ones((h, w)))
            } else {
                robustness(&reference, grey, flow, grey_trials, &merge_cfg.robustness)
            }
        })
        .collect::<Result<Vec<_>>>()?;
    drop(block_flows);
    // A sub-block's flow interpolates the flows of the two blocks whose centres enclose it, so
    // it is only as reliable as both: its robustness is the minimum of the two blocks' maps
    // (index n_blocks + k for the segment between centres k and k + 1).
    let n_blocks = robustness_maps.len();
    let mut robustness_maps = robustness_maps;
    for k in 0..n_blocks.saturating_sub(1) {
        let pair = ndarray::Zip::from(&robustness_maps[k])
            .and(&robustness_maps[k + 1])
            .map_collect(|&a, &b| a.min(b));
        robustness_maps.push(pair);
    }
    let centers = alignment.plan.center_frames();
    let robustness_index = |block: usize, centre: f64| -> usize {
        if n_blocks < 2 || (centre - centers[block]).abs() < 0.5 {
            return block;
        }
        let k = centers
            .windows(2)
            .position(|w| centre < w[1])
            .unwrap_or(n_blocks - 2);
        n_blocks + k
    };
    lap("reference, kernels, robustness", &mut timings);

    // Joint demosaic-merge of sub-block sums, streamed in chunks (supplement §1.3).
    let corrector = hot
        .map(|m| {
            HotPixelCorrector::new(
                &capture.cfa,
                m,
                config.align.hot_pixels.k,
                config.align.hot_pixels.seed,
            )
        })
        .transpose()?;
    let ranges = plan_sub_blocks(&alignment, config);
    let mut accumulator = MergeAccumulator::new(&capture.cfa, &kernels, &merge_cfg.accumulate)?;
    progress.start("merge", ranges.len() as u64);
    for chunk in ranges.chunks(SUB_BLOCK_CHUNK) {
        let sub_blocks: Vec<SubBlock> = chunk
            .par_iter()
            .with_max_len(1)
            .map(|(block, range)| {
                let counts = match &corrector {
                    Some(c) => c.corrected_block_sum(frames, range.clone()),
                    None => frames.sum_range(range.clone()),
                };
                let centre = (range.start + range.end - 1) as f64 / 2.0;
                let flow = match motion {
                    Some(oracle) => oracle(centre),
                    None => {
                        let tile_flow = frame_flow(&alignment.flow, &alignment.plan, centre);
                        dense_flow(&tile_flow, &alignment.grid, h, w)
                    }
                };
                SubBlock {
                    counts,
                    frames: range.len() as u32,
                    flow,
                    robustness: SubBlockRobustness::Block(robustness_index(*block, centre)),
                }
            })
            .collect();
        accumulator.add(&sub_blocks, &robustness_maps)?;
        progress.advance(chunk.len() as u64);
    }
    progress.finish();
    let planes = accumulator.finish(capture.meta.dark_counts_per_frame(), capture.meta.w_weights);
    // RGBW combination (paper Eq. 8).
    let linear = combine_rgbw(&planes.flux, capture.meta.w_weights);
    lap("demosaic-merge", &mut timings);
    Ok(BurstReconstruction {
        alignment,
        merged: MergedBurst {
            linear,
            planes,
            reference,
            robustness: robustness_maps[..n_blocks].to_vec(),
            kernels,
        },
        sub_blocks: ranges.into_iter().map(|(_, r)| r).collect(),
        timings,
    })
}
