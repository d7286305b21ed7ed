//! The burst reconstruction (paper §4, Fig. 4) as a sequence of named stages:
//!
//! 1. [`align`]: block sums, grey images, hierarchical tile alignment (paper §4.1);
//! 2. [`FrameMotion::from_alignment`]: each block's motion as an affine camera motion plus a
//!    local motion where many tiles move alike (moving objects);
//! 3. [`plan_sub_blocks`] and [`refine_camera_motion`]: sub-blocks of tens of frames whose
//!    camera motion is re-measured against the other blocks' grey images (this project's own
//!    stage, see [`crate::align::refine`]; the paper interpolates block motion linearly in
//!    time);
//! 4. [`merge_guide`]: the Wiener-merged reference (supplement §1.2), its kernels and the
//!    blocks' robustness, from the refined block motion (blocks that their own frames smear
//!    are first remade from their sub-blocks, `sharpen_grey_blocks`, this project's step);
//! 5. the joint demosaic-merge of every sub-block at its own motion, streamed through the
//!    phase-bin [`MergeAccumulator`] (supplement Eq. 1–3), MLE flux (Eq. 6) and the RGBW
//!    combination (Eq. 8).
//!
//! Frames are never visited one at a time with a kernel: a sub-block's bits are summed straight
//! from the packed words and splatted once; the kernel regression runs once per image. A range
//! that is both a block and a sub-block is summed once for alignment, refinement and merge
//! ([`crate::capture::BinaryFrames::shared_sum`]). Memory is bounded in T: the frames' mapped
//! pages are released behind each sum, the only per-block images kept are the grey blocks, and
//! the reference image and robustness maps are made block by block.
//!
//! Multi-bit frames of a conventional sensor run through the same stages as the paper does it
//! (§6.1): every frame is its own block (and sub-block), there is no motion interpolation or
//! refinement inside blocks, and the grey-value noise and the flux inversion follow the
//! Gaussian–Poisson model of the capture ([`crate::model::PixelModel`]) instead of the binomial
//! one ([`config_for_capture`]).
#![forbid(unsafe_code)]

use crate::align::{
    align, fast_motion_spans, fit_photon_trajectory_over, plan_sub_blocks, refine_camera_motion,
    shortest_sub_block, split_for_merge_in, steady_block_smear, track_fast_camera_motion,
    track_span, tracking_channel, AlignConfig, Alignment, BlockConfig, FrameMotion, GreyMethod,
    RefineConfig, TrackConfig, TrajectoryConfig, TrajectorySpan,
};
use crate::align::{GreyImager, HotPixelCorrector};
use crate::capture::Capture;
use crate::error::{Error, Result};
use crate::merge::warp::relative_flow;
use crate::merge::{
    block_robustness, merge_guide_streamed, warp_to_reference, GreyNoise, MergeAccumulator,
    MergeConfig, MergeGuide, MergedBurst, ReferenceStats, RobustnessConfig, SubBlock,
    SubBlockMotion, SubBlockRobustness,
};
use crate::progress::Progress;
use crate::timing::{Laps, StageTiming};
use ndarray::{Array2, Array3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::ops::Range;

/// Configuration of the burst reconstruction.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct BurstConfig {
    pub align: AlignConfig,
    /// Sub-blocks and their camera motion at frame granularity.
    pub refine: RefineConfig,
    /// Fast camera motion tracked sub-block by sub-block.
    pub track: TrackConfig,
    /// The tracked camera trajectory fitted to every photon at single-frame resolution.
    pub trajectory: TrajectoryConfig,
    pub merge: MergeConfig,
}

impl BurstConfig {
    /// Checks the settings that motion estimation would otherwise reject only after the
    /// frames are read: refinement, tracking, the trajectory (when on) and the steady-pan
    /// smear bound.
    pub fn validate(&self) -> Result<()> {
        self.refine.validate()?;
        self.track.validate()?;
        if self.trajectory.enabled {
            self.trajectory.validate()?;
        }
        let max_smear = self.align.blocks.max_steady_smear_px;
        if !(max_smear.is_finite() && max_smear >= 0.0) {
            return Err(Error::invalid(format!(
                "[burst.align.blocks] max_steady_smear_px must be a non-negative number, got {max_smear}"
            )));
        }
        let sharpen = self.merge.sharpen_blocks_px;
        if sharpen.is_nan() || sharpen < 0.0 {
            return Err(Error::invalid(format!(
                "[burst.merge] sharpen_blocks_px must be a non-negative number or inf, got {sharpen}"
            )));
        }
        Ok(())
    }
}

/// Result of the burst reconstruction with its intermediate stages.
#[derive(Debug, Clone)]
pub struct BurstReconstruction {
    /// The block alignment the motion was estimated from (for a frame of a video, the anchor
    /// frame's: its plan and flows are relative to that frame, see [`crate::video`]).
    pub alignment: Alignment,
    /// The motion of every sub-block the merge used (unless driven by a motion oracle).
    pub motion: FrameMotion,
    pub merged: MergedBurst,
    /// Frame ranges of the sub-blocks that were merged.
    pub sub_blocks: Vec<Range<usize>>,
    /// How many grey block images were remade sharp for the merge guide (the alignment's
    /// `grey` holds them; see `[burst.merge] sharpen_blocks_px`).
    pub sharpened_blocks: usize,
    /// Wall-clock time of each stage.
    pub timings: Vec<StageTiming>,
    /// The noise of a grey block value and the robustness settings the merge used
    /// ([`Self::robustness_maps`]).
    grey_noise: GreyNoise,
    robustness: RobustnessConfig,
}

impl BurstReconstruction {
    /// Dense (H, W, 2) flow (dy, dx) of the estimated motion at (fractional) frame `t`: the
    /// scene point at p in the reference frame is at p + flow(p) in frame t (the convention of
    /// [`crate::simulate::Motion::dense_flow`], so the two compare directly).
    pub fn merge_flow(&self, t: f64) -> Array3<f32> {
        self.motion.flow_at_frame(t)
    }

    /// The (H, W) robustness map of every block (supplement Eq. 4–6), made again as the merge
    /// made them (which drops each once its block is merged: they would grow with T), from
    /// the grey blocks, the reference and the estimated block motion; a merge driven by a
    /// motion oracle used the oracle's flows instead.
    pub fn robustness_maps(&self) -> Result<Vec<Array2<f32>>> {
        let stats = ReferenceStats::new(&self.merged.reference);
        (0..self.alignment.plan.len())
            .into_par_iter()
            .map(|b| {
                block_robustness(
                    &stats,
                    &self.alignment.grey,
                    &self.motion.block_flow(b),
                    b,
                    self.motion.plan.reference_block,
                    self.grey_noise,
                    &self.robustness,
                )
            })
            .collect()
    }
}

/// The burst configuration for `capture`: `config` itself for binary frames; for multi-bit
/// frames (paper §6.1) blocks of one frame, and no sub-block refinement or fast-motion tracking
/// (a frame has no motion inside it to refine).
pub fn config_for_capture(capture: &Capture, config: &BurstConfig) -> BurstConfig {
    let mut config = config.clone();
    if capture.frames.is_multibit() {
        config.align.blocks.block_size = Some(1);
        config.refine.enabled = false;
    }
    config
}

/// Sub-blocks summed and merged at a time: bounds memory to a few (H, W) images per chunk.
const SUB_BLOCK_CHUNK: usize = 8;

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

/// [`reconstruct_burst`] with the merge driven by `motion` instead of the estimated motion when
/// given (e.g. a simulator's true motion: the quality benchmark's upper bound). Alignment still
/// runs for the block and sub-block plan and the grey images; refinement is skipped.
pub fn reconstruct_burst_with_motion(
    capture: &Capture,
    reference_frame: usize,
    config: &BurstConfig,
    oracle: Option<MotionOracle<'_>>,
    progress: &dyn Progress,
) -> Result<BurstReconstruction> {
    crate::cpu::on_pool(|| burst_on_pool(capture, reference_frame, config, oracle, progress))
}

fn burst_on_pool(
    capture: &Capture,
    reference_frame: usize,
    config: &BurstConfig,
    oracle: Option<MotionOracle<'_>>,
    progress: &dyn Progress,
) -> Result<BurstReconstruction> {
    let config = &config_for_capture(capture, config);
    let mut laps = Laps::new();
    // Block and sub-block sums are made once and shared by alignment, refinement and merge.
    capture.frames.forget_shared_sums();
    let EstimatedMotion {
        alignment, motion, ..
    } = estimate_motion(
        capture,
        reference_frame,
        config,
        oracle,
        &mut laps,
        progress,
    )?;
    let reconstruction = merge_at_motion(
        capture, alignment, motion, oracle, config, &mut laps, progress,
    );
    capture.frames.forget_shared_sums();
    reconstruction
}

/// What the motion estimation found ([`estimate_burst_motion`]).
pub struct EstimatedMotion {
    pub alignment: Alignment,
    pub motion: FrameMotion,
    /// Whether the camera was tracked as fast motion, throughout or in spans (the block
    /// flows' local residual was then dropped as streak matching, not motion, where tracked).
    pub tracked: bool,
}

/// Stages 1–3 of [`reconstruct_burst`] alone, for `quantacolor align` and the Python `align`:
/// the same motion estimation (block alignment, camera and local motion, sub-block refinement
/// or fast-motion tracking and the photon trajectory) with the same configuration
/// ([`config_for_capture`] applied), so `motion` is the motion [`reconstruct_burst`] would
/// merge at; the merge does not run. Its camera part per frame is
/// [`FrameMotion::camera_matrices`] (`camera.npy`, docs/motion.md).
pub fn estimate_burst_motion(
    capture: &Capture,
    reference_frame: usize,
    config: &BurstConfig,
    progress: &dyn Progress,
) -> Result<EstimatedMotion> {
    let frames = capture.frames.frame_count();
    if reference_frame >= frames {
        return Err(Error::invalid(format!(
            "reference frame {reference_frame} is outside the capture's {frames} frames"
        )));
    }
    crate::cpu::on_pool(|| {
        let config = &config_for_capture(capture, config);
        capture.frames.forget_shared_sums();
        let estimate = estimate_motion(
            capture,
            reference_frame,
            config,
            None,
            &mut Laps::new(),
            progress,
        );
        capture.frames.forget_shared_sums();
        estimate
    })
}

/// Stages 1–3: alignment to `reference_frame` and the motion of every sub-block (block motion,
/// sub-block plan, then refinement, or fast-motion tracking and the photon trajectory: of the
/// whole capture when it moves fast throughout, else of the spans of blocks that move fast
/// after the refinement of all, [`MotionSpans`]; with an `oracle`, only the plan). `config` is taken as it is (see [`config_for_capture`]); each
/// stage's time is recorded in `laps`.
pub(crate) fn estimate_motion(
    capture: &Capture,
    reference_frame: usize,
    config: &BurstConfig,
    oracle: Option<MotionOracle<'_>>,
    laps: &mut Laps,
    progress: &dyn Progress,
) -> Result<EstimatedMotion> {
    // Checked before alignment: the sub-block plan uses the refinement's settings even with
    // the refinement off.
    config.validate()?;
    let (alignment, mut motion) =
        align_blocks_replanned(capture, reference_frame, config, progress)?;
    laps.lap("align");

    let grey_blocks = &alignment.grey;
    let reference_block = alignment.plan.reference_block;
    let detections_per_frame = grey_blocks[reference_block].mean().unwrap_or(0.0) as f64;
    plan_sub_blocks(&mut motion, detections_per_frame, &config.refine);
    if let Some(oracle) = oracle {
        split_at_oracle_motion(&mut motion, oracle, config.refine.max_sub_block_motion_px);
    }
    // The fastest camera whose shortest sub-blocks stay within the refinement's bound.
    let followable_px_per_frame = config.refine.max_sub_block_motion_px
        / shortest_sub_block(detections_per_frame, &config.refine) as f64;
    let estimating = oracle.is_none() && config.refine.enabled;
    let spans = if estimating && tracking_channel(&capture.cfa, alignment.grey_method).is_some() {
        fast_motion_spans(&motion, &config.track, followable_px_per_frame)
    } else {
        Vec::new()
    };
    let throughout = spans.len() == 1 && spans[0] == (0..motion.plan.len());
    let mut tracked = throughout
        && follow_fast_motion(
            capture,
            alignment.grey_method,
            &mut motion,
            config,
            followable_px_per_frame,
            laps,
            progress,
        )?;
    if !tracked && estimating {
        refine_camera_motion(
            capture,
            alignment.grey_method,
            grey_blocks,
            &mut motion,
            &config.refine,
            progress,
        )?;
        laps.lap("motion refinement");
        if !throughout {
            let spans = MotionSpans {
                fast: FastSubBlocks {
                    capture,
                    grey_method: alignment.grey_method,
                    config,
                    followable_px_per_frame,
                },
                spans: &spans,
            };
            tracked = spans.follow(&mut motion, laps, progress)?;
        }
    }
    Ok(EstimatedMotion {
        alignment,
        motion,
        tracked,
    })
}

/// Stage 1 ([`align_blocks`]), made again in shorter blocks when a steady camera smears each
/// block by more than `max_steady_smear_px` ([`shorter_block_size`]).
fn align_blocks_replanned(
    capture: &Capture,
    reference_frame: usize,
    config: &BurstConfig,
    progress: &dyn Progress,
) -> Result<(Alignment, FrameMotion)> {
    let (mut alignment, mut motion) =
        align_blocks(capture, reference_frame, &config.align, config, progress)?;
    let steady_smear = steady_block_smear(&motion, config.track.steady_px);
    let blocks = &config.align.blocks;
    let shortest = blocks.shortest_for(capture.frames.frame_count());
    if let Some(block_size) = shorter_block_size(steady_smear, motion.plan.block_size, blocks)
        .map(|b| b.max(shortest))
        .filter(|&b| b < motion.plan.block_size)
    {
        let mut align_config = config.align.clone();
        align_config.blocks.block_size = Some(block_size);
        // The first alignment's grey blocks are not needed while the second is made.
        drop((alignment, motion));
        (alignment, motion) =
            align_blocks(capture, reference_frame, &align_config, config, progress)?;
    }
    Ok((alignment, motion))
}

/// Stage 2 under fast motion: when [`track_fast_camera_motion`] finds the camera too fast for
/// the refinement and tracks it, the block flows' local residual is dropped (streak matching,
/// not motion) and the photon trajectory is fitted where the tracked camera moves faster than
/// the refinement follows ([`FastSubBlocks::fit`]); returns whether it tracked. When no
/// sub-block moves that fast (long blocks of a slow hand: their cameras differ by more than
/// the trigger, yet each frame moves little), `motion` is given back as it was, for the
/// refinement. Each stage's time is recorded in `laps`.
fn follow_fast_motion(
    capture: &Capture,
    grey_method: GreyMethod,
    motion: &mut FrameMotion,
    config: &BurstConfig,
    followable_px_per_frame: f64,
    laps: &mut Laps,
    progress: &dyn Progress,
) -> Result<bool> {
    let untracked = motion.clone();
    if !track_fast_camera_motion(
        capture,
        grey_method,
        motion,
        &config.track,
        followable_px_per_frame,
        progress,
    )? {
        return Ok(false);
    }
    motion.drop_local_motion();
    laps.lap("fast motion tracking");
    let reference = motion.plan.reference_frame;
    let fast = FastSubBlocks {
        capture,
        grey_method,
        config,
        followable_px_per_frame,
    };
    if !fast.fit(motion, 0..motion.plan.len(), reference, laps, progress)? {
        *motion = untracked;
        return Ok(false);
    }
    Ok(true)
}

/// The photon trajectory of tracked blocks, over their sub-blocks that move faster than the
/// refinement follows ([`trajectory_sub_blocks`]).
struct FastSubBlocks<'a> {
    capture: &'a Capture,
    grey_method: GreyMethod,
    config: &'a BurstConfig,
    /// The fastest camera the refinement follows (px per frame at the image corners).
    followable_px_per_frame: f64,
}

impl FastSubBlocks<'_> {
    /// After the blocks `blocks` of `motion` were tracked (from `anchor_frame`, the frame whose
    /// tracked camera was kept), fits the photon trajectory over their sub-blocks that move
    /// faster than the refinement follows, or splits those sub-blocks for the merge when no
    /// trajectory is fitted. Returns `false`, fitting nothing, when none moves that fast.
    fn fit(
        &self,
        motion: &mut FrameMotion,
        blocks: Range<usize>,
        anchor_frame: usize,
        laps: &mut Laps,
        progress: &dyn Progress,
    ) -> Result<bool> {
        let max_motion_px = self.config.refine.max_sub_block_motion_px;
        let Some(sub_blocks) = trajectory_sub_blocks(motion, &blocks, self.followable_px_per_frame)
        else {
            return Ok(false);
        };
        let reference = motion.plan.reference_frame;
        let first = &motion.sub_blocks[sub_blocks.start];
        let frames = first.start..motion.sub_blocks[sub_blocks.end - 1].end;
        let anchor_frame = if frames.contains(&reference) && anchor_frame == reference {
            reference
        } else {
            (first.start + first.end - 1) / 2
        };
        let span = TrajectorySpan {
            sub_blocks,
            anchor_frame,
        };
        if fit_photon_trajectory_over(
            self.capture,
            self.grey_method,
            motion,
            &span,
            &self.config.trajectory,
            max_motion_px,
            progress,
        )? {
            laps.lap("photon trajectory");
        } else {
            split_for_merge_in(motion, blocks, max_motion_px);
        }
        Ok(true)
    }
}

/// Stage 2 where the camera moves fast in some spans of blocks only ([`fast_motion_spans`]):
/// after the refinement of every sub-block, each span is tracked ([`track_span`]) and its
/// photon trajectory fitted over its own frames ([`FastSubBlocks::fit`]); a span whose tracked
/// camera nowhere moves faster than the refinement follows keeps the refinement's motion. Time
/// and memory follow the spans, not the recording.
struct MotionSpans<'a> {
    fast: FastSubBlocks<'a>,
    spans: &'a [Range<usize>],
}

impl MotionSpans<'_> {
    /// Follows every span; returns whether any was tracked. Each stage's time is added up in
    /// `laps`.
    fn follow(
        &self,
        motion: &mut FrameMotion,
        laps: &mut Laps,
        progress: &dyn Progress,
    ) -> Result<bool> {
        let fast = &self.fast;
        let mut tracked = false;
        for blocks in self.spans {
            let refined = motion.clone();
            let Some(anchor_frame) = track_span(
                fast.capture,
                fast.grey_method,
                motion,
                blocks.clone(),
                &fast.config.track,
                progress,
            )?
            else {
                continue;
            };
            laps.lap("fast motion tracking");
            if fast.fit(motion, blocks.clone(), anchor_frame, laps, progress)? {
                tracked = true;
            } else {
                *motion = refined;
            }
        }
        Ok(tracked)
    }
}

/// Frames a photon trajectory is fitted to at least: its template is made of its own frames.
/// 256 against 512: the same PSNR, the trajectory's time halved, errors near a jolt 0.1–0.3 px
/// larger (docs/tuning.md).
const MIN_TRAJECTORY_FRAMES: usize = 256;

/// The sub-blocks of the blocks `blocks` of a tracked `motion` that the photon trajectory is
/// fitted to: from the first to the last whose tracked camera moves faster than
/// `followable_px_per_frame` inside it (a jolt, a burst of shake: faster than the refinement
/// follows), widened by slower sub-blocks on both sides to [`MIN_TRAJECTORY_FRAMES`] where the
/// blocks hold them; `None` when none moves that fast. This project's heuristic: the slower
/// sub-blocks keep their tracked cameras.
fn trajectory_sub_blocks(
    motion: &FrameMotion,
    blocks: &Range<usize>,
    followable_px_per_frame: f64,
) -> Option<Range<usize>> {
    let first = motion.block_of.partition_point(|&b| b < blocks.start);
    let last = motion.block_of.partition_point(|&b| b < blocks.end);
    let fast: Vec<usize> = (first..last)
        .filter(|&k| {
            let frames = motion.sub_blocks[k].len().max(1) as f64;
            motion.sub_block_travel(k) > followable_px_per_frame * frames
        })
        .collect();
    let (mut lo, mut hi) = (*fast.first()?, *fast.last()? + 1);
    let frames = |lo: usize, hi: usize| motion.sub_blocks[hi - 1].end - motion.sub_blocks[lo].start;
    while frames(lo, hi) < MIN_TRAJECTORY_FRAMES && (lo > first || hi < last) {
        lo = lo.saturating_sub(1).max(first);
        hi = (hi + 1).min(last);
    }
    Some(lo..hi)
}

/// Stage 1: the block alignment of `align_config` and the block motion it gives (camera and
/// kept local residual, per `config.refine`).
fn align_blocks(
    capture: &Capture,
    reference_frame: usize,
    align_config: &AlignConfig,
    config: &BurstConfig,
    progress: &dyn Progress,
) -> Result<(Alignment, FrameMotion)> {
    let alignment = align(
        &capture.frames,
        &capture.cfa,
        capture.hot_pixels.as_ref(),
        reference_frame,
        align_config,
        progress,
    )?;
    let mut motion = FrameMotion::from_alignment(
        &alignment,
        align_config.affine_tolerance_px,
        config.refine.min_local_tiles,
        config.refine.local_consistency,
    );
    if !config.refine.keep_local_motion {
        motion.drop_local_motion();
    }
    Ok((alignment, motion))
}

/// A shorter automatic block size than `current` when the camera moves steadily and one
/// block collects `steady_smear` px of its motion ([`steady_block_smear`]), more than
/// [`BlockConfig::max_steady_smear_px`]: the size at which it collects that much, at least
/// `min_block_size`. `None` when the block size is fixed, the rule is off or not needed.
/// A re-planned capture is aligned twice (about +0.2 s); measurements in docs/tuning.md.
fn shorter_block_size(
    steady_smear: Option<f64>,
    current: usize,
    blocks: &BlockConfig,
) -> Option<usize> {
    let limit = blocks.max_steady_smear_px;
    let smear = steady_smear?;
    if blocks.block_size.is_some() || limit <= 0.0 || smear <= limit {
        return None;
    }
    let wanted = (current as f64 * limit / smear).floor() as usize;
    let shorter = wanted.max(blocks.min_block_size.min(current));
    (shorter < current).then_some(shorter)
}

/// Stages 4–5 at the sub-block motion `motion` (or the `oracle`'s): the merge guide from the
/// grey blocks of `alignment` and the block motion, then the joint demosaic-merge of every
/// sub-block. The reference block is `motion.plan`'s (the grey images are `alignment`'s,
/// whose plan has the same blocks). Each stage's time is recorded in `laps`, whose timings the
/// result takes.
pub(crate) fn merge_at_motion(
    capture: &Capture,
    mut alignment: Alignment,
    motion: FrameMotion,
    oracle: Option<MotionOracle<'_>>,
    config: &BurstConfig,
    laps: &mut Laps,
    progress: &dyn Progress,
) -> Result<BurstReconstruction> {
    if motion.plan.blocks != alignment.plan.blocks {
        return Err(Error::invalid(
            "merge: the motion's blocks are not the alignment's",
        ));
    }
    let block_centres = motion.plan.center_frames();
    let sharpened_blocks = sharpen_grey_blocks(
        capture,
        &mut alignment,
        &motion,
        oracle.map(|oracle| (oracle, &block_centres[..])),
        config,
    )?;
    let grey_blocks = &alignment.grey;
    let grey_noise = GreyNoise {
        trials: alignment.plan.block_size as f32,
        model: capture.meta.pixel_model(),
    };
    let reference_block = motion.plan.reference_block;
    let block_flow = |b: usize| match oracle {
        Some(oracle) => oracle(block_centres[b]),
        None => motion.block_flow(b),
    };
    let guide = merge_guide_streamed(
        grey_blocks,
        &block_flow,
        reference_block,
        grey_noise,
        &config.merge,
    )?;
    laps.lap("merge guide (reference, kernels, robustness)");

    let robustness = BlockRobustness {
        grey_blocks,
        block_flow: &block_flow,
        reference_block,
        noise: grey_noise,
        config: &config.merge.robustness,
    };
    let merged = merge_sub_blocks(
        capture,
        &motion,
        oracle,
        &robustness,
        guide,
        &config.merge,
        progress,
    )?;
    laps.lap("demosaic-merge");
    Ok(BurstReconstruction {
        alignment,
        sub_blocks: motion.sub_blocks.clone(),
        sharpened_blocks,
        motion,
        merged,
        timings: std::mem::take(&mut laps.timings),
        grey_noise,
        robustness: config.merge.robustness.clone(),
    })
}

/// Remakes the grey images of the blocks whose frames smear them (this project's step; the
/// paper builds its reference from the block images as summed, §4.2): a block whose sub-block
/// cameras lie more than [`MergeConfig::sharpen_blocks_px`] from the block's camera
/// ([`FrameMotion::block_spread`]) becomes the frame-weighted mean of the grey images (hot
/// pixels corrected as in the alignment) of its runs of sub-blocks within half that distance
/// of each other ([`FrameMotion::block_runs`]), each resampled onto the block's grid at its
/// own motion ([`FrameMotion::flow_from_block`]; with an `oracle`, its flows at the run's and
/// the block's centre frame, `block_centres`). The merge guide then sees the scene as sharp as
/// the motion is known: a smeared block softened the Wiener reference, hence the kernels, and
/// the robustness compared every sub-block with a blurred scene (hand shake of 12 px over
/// 2,000 frames: +4.3 dB before denoising; docs/tuning.md). Block motion and the other blocks
/// stay as they are. Returns how many blocks were remade.
fn sharpen_grey_blocks(
    capture: &Capture,
    alignment: &mut Alignment,
    motion: &FrameMotion,
    oracle: Option<(MotionOracle<'_>, &[f64])>,
    config: &BurstConfig,
) -> Result<usize> {
    let limit = config.merge.sharpen_blocks_px;
    let blocks: Vec<usize> = (0..motion.plan.len())
        .filter(|&b| {
            motion.block_of.iter().filter(|&&of| of == b).count() > 1
                && motion.block_spread(b) > limit
        })
        .collect();
    if blocks.is_empty() {
        return Ok(0);
    }
    let imager = GreyImager::new(&capture.cfa, alignment.grey_method);
    let corrector = capture
        .hot_pixels
        .as_ref()
        .map(|mask| {
            let hot = &config.align.hot_pixels;
            HotPixelCorrector::new(&capture.cfa, mask, hot.k, hot.seed)
        })
        .transpose()?;
    // Runs of sub-blocks within half the limit of each other share one image.
    let tolerance_px = limit / 2.0;
    let sharp: Vec<Array2<f32>> = blocks
        .par_iter()
        .with_max_len(1)
        .map(|&b| {
            let mut sum = Array2::<f32>::zeros(alignment.grey[b].dim());
            let mut frames = 0usize;
            for (range, camera, centre) in motion.block_runs(b, tolerance_px) {
                let counts = match &corrector {
                    Some(c) => c.corrected_block_sum(&capture.frames, range.clone()),
                    None => capture.frames.shared_sum(range.clone()),
                };
                let image = imager.image(&counts, range.len())?;
                let flow = match oracle {
                    Some((oracle, block_centres)) => {
                        relative_flow(&oracle(block_centres[b]), &oracle(centre))?
                    }
                    None => motion.flow_from_block(b, &camera, centre)?,
                };
                sum.scaled_add(range.len() as f32, &warp_to_reference(&image, &flow)?);
                frames += range.len();
            }
            Ok(sum / frames.max(1) as f32)
        })
        .collect::<Result<_>>()?;
    for (&b, image) in blocks.iter().zip(sharp) {
        alignment.grey[b] = image;
    }
    Ok(blocks.len())
}

/// Cuts every sub-block of `motion` so that the `oracle`'s motion travels at most
/// `max_motion_px` inside each piece (largest over the image corners and centre, start to end;
/// down to single frames): a merge driven by the true motion must not blur fast motion either,
/// or it is no upper bound.
fn split_at_oracle_motion(motion: &mut FrameMotion, oracle: MotionOracle<'_>, max_motion_px: f64) {
    let travel = |range: &Range<usize>| -> f64 {
        let (a, b) = (oracle(range.start as f64), oracle((range.end - 1) as f64));
        let (h, w, _) = a.dim();
        [
            (0, 0),
            (0, w - 1),
            (h - 1, 0),
            (h - 1, w - 1),
            (h / 2, w / 2),
        ]
        .iter()
        .map(|&(y, x)| {
            let dy = (a[[y, x, 0]] - b[[y, x, 0]]) as f64;
            let dx = (a[[y, x, 1]] - b[[y, x, 1]]) as f64;
            dy.hypot(dx)
        })
        .fold(0.0, f64::max)
    };
    motion.split_sub_blocks(
        |_, range| (travel(range) / max_motion_px.max(1e-6)).ceil() as usize,
        |m, k, _| m.camera[k],
    );
}

/// What a block's robustness map is made from ([`block_robustness`]), for the merge to make
/// each map when it reaches the block's sub-blocks.
struct BlockRobustness<'a> {
    grey_blocks: &'a [Array2<f32>],
    block_flow: &'a (dyn Fn(usize) -> Array3<f32> + Sync),
    reference_block: usize,
    noise: GreyNoise,
    config: &'a RobustnessConfig,
}

impl BlockRobustness<'_> {
    fn map(&self, reference: &ReferenceStats, b: usize) -> Result<Array2<f32>> {
        block_robustness(
            reference,
            self.grey_blocks,
            &(self.block_flow)(b),
            b,
            self.reference_block,
            self.noise,
            self.config,
        )
    }
}

/// Joint demosaic-merge of every sub-block of `motion` at its own flow (or the `oracle`'s at
/// its centre frame), streamed in chunks through the phase-bin accumulator; hot pixels are
/// left out. Then MLE flux and Eq. 8. Each block's robustness map is made when the first
/// chunk that needs it comes and dropped after the last (sub-blocks run in time order, so a
/// chunk needs at most a few blocks' maps).
fn merge_sub_blocks(
    capture: &Capture,
    motion: &FrameMotion,
    oracle: Option<MotionOracle<'_>>,
    robustness: &BlockRobustness<'_>,
    guide: MergeGuide,
    config: &MergeConfig,
    progress: &dyn Progress,
) -> Result<MergedBurst> {
    let mut accumulator = MergeAccumulator::new(
        &capture.cfa,
        &guide.kernels,
        &config.accumulate,
        capture.meta.pixel_model(),
    )?;
    if let Some(hot) = &capture.hot_pixels {
        accumulator.exclude_sites(hot)?;
    }
    let reference_stats = ReferenceStats::new(&guide.reference);
    let indices: Vec<usize> = (0..motion.sub_blocks.len()).collect();
    // Robustness maps of the blocks the current chunk needs (`maps[i]` is block
    // `map_blocks[i]`'s).
    let mut map_blocks: Vec<usize> = Vec::new();
    let mut maps: Vec<Array2<f32>> = Vec::new();
    progress.start("merge", indices.len() as u64);
    for chunk in indices.chunks(SUB_BLOCK_CHUNK) {
        let mut needed: Vec<usize> = chunk.iter().map(|&k| motion.block_of[k]).collect();
        needed.sort_unstable();
        needed.dedup();
        let kept: Vec<(usize, Array2<f32>)> = map_blocks
            .drain(..)
            .zip(maps.drain(..))
            .filter(|(b, _)| needed.contains(b))
            .collect();
        let missing: Vec<usize> = needed
            .iter()
            .copied()
            .filter(|b| !kept.iter().any(|(have, _)| have == b))
            .collect();
        let made: Vec<Array2<f32>> = missing
            .par_iter()
            .map(|&b| robustness.map(&reference_stats, b))
            .collect::<Result<_>>()?;
        for (b, map) in kept.into_iter().chain(missing.into_iter().zip(made)) {
            map_blocks.push(b);
            maps.push(map);
        }
        let slot = |b: usize| {
            map_blocks
                .iter()
                .position(|&have| have == b)
                .expect("every needed map is made")
        };
        let sub_blocks: Vec<SubBlock> = chunk
            .par_iter()
            .with_max_len(1)
            .map(|&k| {
                let range = motion.sub_blocks[k].clone();
                let centre = (range.start + range.end - 1) as f64 / 2.0;
                SubBlock {
                    counts: capture.frames.shared_sum(range.clone()),
                    frames: range.len() as u32,
                    flow: match (oracle, motion.sub_block_reference_map(k)) {
                        (Some(oracle), _) => SubBlockMotion::Dense(oracle(centre)),
                        (None, Some((matrix, offset))) => SubBlockMotion::Affine { matrix, offset },
                        (None, None) => motion.sub_block_motion(k),
                    },
                    robustness: SubBlockRobustness::Block(slot(motion.block_of[k])),
                }
            })
            .collect();
        accumulator.add(&sub_blocks, &maps)?;
        // The pages the kernel mapped around the sums (fault-around) are handed back too.
        if let (Some(&first), Some(&last)) = (chunk.first(), chunk.last()) {
            capture
                .frames
                .release(motion.sub_blocks[first].start..motion.sub_blocks[last].end);
        }
        progress.advance(chunk.len() as u64);
    }
    progress.finish();
    let planes = accumulator.finish(capture.meta.w_weights);
    Ok(MergedBurst::from_planes(
        planes,
        guide,
        capture.meta.w_weights,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_steady_pan_that_smears_its_blocks_gets_shorter_ones() {
        let blocks = BlockConfig::default();
        assert_eq!(blocks.max_steady_smear_px, 4.0);
        // 8 px in 400 frames: 200-frame blocks collect 4 px.
        assert_eq!(shorter_block_size(Some(8.0), 400, &blocks), Some(200));
        assert_eq!(shorter_block_size(Some(6.0), 400, &blocks), Some(266));
        // Within the limit, or not steady: unchanged.
        assert_eq!(shorter_block_size(Some(4.0), 400, &blocks), None);
        assert_eq!(shorter_block_size(None, 400, &blocks), None);
        // Never below the smallest automatic block, nor longer than before.
        assert_eq!(shorter_block_size(Some(40.0), 400, &blocks), Some(100));
        assert_eq!(shorter_block_size(Some(40.0), 64, &blocks), None);
        // A fixed block size, or the rule off.
        let fixed = BlockConfig {
            block_size: Some(400),
            ..blocks.clone()
        };
        assert_eq!(shorter_block_size(Some(8.0), 400, &fixed), None);
        let off = BlockConfig {
            max_steady_smear_px: 0.0,
            ..blocks
        };
        assert_eq!(shorter_block_size(Some(8.0), 400, &off), None);
    }
}
