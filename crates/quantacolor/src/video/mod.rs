//! Video: one reconstruction per reference frame of a sliding reference, with the expensive
//! motion estimation done once for the whole capture (this project's own stage; the papers'
//! supplementary videos reconstruct each reference frame from scratch).
//!
//! A reconstruction registers the whole burst to its reference frame r (paper §4, Fig. 4). Of
//! the burst's stages ([`crate::burst`]) these are done once, at an *anchor* reference frame a
//! (the configured reference frame), on the anchor's block grid (r's block becomes the
//! reference block; the grid does not move with r):
//!
//! - hot-pixel correction, block sums and grey block images;
//! - the sub-block camera motion (block alignment's camera fit, then the refinement, or
//!   fast-motion tracking and the photon trajectory), an affine map M_k: a → sub-block k;
//! - the block and sub-block sums stay in [`crate::capture::BinaryFrames::shared_sum`]'s
//!   bounded cache from one video frame to the next.
//!
//! Per frame: the camera relative to r is the composition M_k ∘ M(r)⁻¹ ([`reanchor_cameras`]),
//! M(r) the camera at frame r interpolated between sub-block centres exactly as the burst
//! anchors its own motion ([`crate::align::refine_camera_motion`]). For affine camera maps this
//! is exact: it is the motion the per-reference path measures, up to the photon noise of
//! measuring it from another anchor. Local motion (moving objects) is block-granular tile flow
//! that does not compose as a map, so it is measured again: the tile alignment of the shared
//! grey blocks against r's block ([`crate::align::align_grey_blocks`], the cheap part of the
//! alignment) gives r's local residual ([`FrameMotion::from_alignment`]), as in the
//! per-reference path. Then the guide (Wiener reference, kernels, robustness; supplement
//! §1.2–1.3), the joint demosaic-merge (supplement Eq. 1–3, paper Eq. 6 and 8) and the
//! denoiser (§4.3) run at r through the burst's own merge (there is one merge path).
//!
//! Difference to the per-reference path: there r sits at the centre of its block; here at
//! most half a block away from it. The camera motion is unaffected (each block is warped by
//! its own motion relative to r), but the local residual is zero at the centre of r's block
//! rather than at r, so a moving object's position is off by its motion over that time.
//! The naive method has no motion to reuse: it runs per frame
//! ([`VideoReconstructor::fallback_reason`]).
#![forbid(unsafe_code)]

mod output;

pub use output::{
    assemble_parts, frame_file_name, part_path, reconstruct_frame, write_part, FrameProgress,
    VideoFrame, VideoPlan, VideoReport, VideoWriter,
};

use crate::align::{align_grey_blocks, AffineMotion, Alignment, BlockPlan, FrameMotion};
use crate::burst::{
    config_for_capture, estimate_motion, merge_at_motion, BurstConfig, EstimatedMotion,
};
use crate::capture::Capture;
use crate::error::{Error, Result};
use crate::pipeline::{
    burst_config_for, denoise_and_finish, reconstruct, Merged, Method, ReconstructConfig,
    Reconstruction,
};
use crate::progress::Progress;
use crate::timing::{Laps, StageTiming};
use ndarray::Array3;

/// Reference frames of a video over `frame_count` frames, one every `stride` frames from
/// `stride / 2` (each centred in its stretch of `stride` frames).
pub fn video_reference_frames(frame_count: usize, stride: usize) -> Result<Vec<usize>> {
    if stride == 0 {
        return Err(Error::invalid("video stride must be at least 1 frame"));
    }
    Ok((stride / 2..frame_count).step_by(stride).collect())
}

/// The sub-block camera maps of `motion` (relative to its plan's reference frame a) relative to
/// `reference_frame` r instead: M_k ∘ M(r)⁻¹ for every sub-block camera M_k, where M(r) is the
/// camera at frame r ([`FrameMotion::camera_at`]). At r = a the cameras are returned as they
/// are (anchored there already). Errors when r is outside the burst or M(r) cannot be
/// inverted.
pub fn reanchor_cameras(motion: &FrameMotion, reference_frame: usize) -> Result<Vec<AffineMotion>> {
    let frames = motion.plan.blocks.last().map_or(0, |b| b.end);
    if reference_frame >= frames {
        return Err(Error::invalid(format!(
            "reference frame {reference_frame} is outside the burst's {frames} frames"
        )));
    }
    if reference_frame == motion.plan.reference_frame {
        return Ok(motion.camera.clone());
    }
    let undo = motion
        .camera_at(reference_frame as f64)
        .inverse()
        .ok_or_else(|| {
            Error::invalid(format!(
                "the camera map at frame {reference_frame} cannot be inverted"
            ))
        })?;
    Ok(compose_cameras(motion, &undo))
}

/// Every sub-block camera M_k of `motion` composed with `to_anchor` W (a map from another
/// frame's coordinates to the anchor's): M_k ∘ W.
pub fn compose_cameras(motion: &FrameMotion, to_anchor: &AffineMotion) -> Vec<AffineMotion> {
    motion.camera.iter().map(|m| m.after(to_anchor)).collect()
}

/// The map W from a frame r's coordinates to the anchor's, from `block_cameras`: every block's
/// camera at its centre frame relative to r (the camera fits of r's tile alignment, which
/// makes them relative to r by the quadratic centre correction of
/// [`crate::align::block_centre_flow`]). Block b gives W_b = S(c_b)⁻¹ ∘ C_b, S(c_b) the shared
/// camera at b's centre frame; W is the component-wise median over blocks. A block image
/// integrates hundreds of frames and the median pools every block, so W is far less noisy
/// than the camera at the single frame r ([`reanchor_cameras`]; measured on a handheld chart
/// capture: 0.26–0.37 px off at single frames). `None` without blocks or when no shared camera
/// can be inverted.
pub fn frame_to_anchor_from_blocks(
    motion: &FrameMotion,
    block_cameras: &[AffineMotion],
) -> Option<AffineMotion> {
    let centres = motion.plan.center_frames();
    let estimates: Vec<[f64; 6]> = block_cameras
        .iter()
        .zip(&centres)
        .filter_map(|(c, &t)| {
            let w = motion.camera_at(t).inverse()?.after(c);
            Some([w.b[0], w.b[1], w.m[0][0], w.m[0][1], w.m[1][0], w.m[1][1]])
        })
        .collect();
    if estimates.is_empty() {
        return None;
    }
    let median = |i: usize| {
        let mut v: Vec<f64> = estimates.iter().map(|e| e[i]).collect();
        v.sort_by(f64::total_cmp);
        let n = v.len();
        if n % 2 == 1 {
            v[n / 2]
        } else {
            0.5 * (v[n / 2 - 1] + v[n / 2])
        }
    };
    Some(AffineMotion {
        b: [median(0), median(1)],
        m: [[median(2), median(3)], [median(4), median(5)]],
    })
}

/// The anchor frame and block size that put every one of `reference_frames` at the centre of
/// its block ([`VideoReconstructor::for_frames`]); `None` when they are not evenly spaced or
/// no block size within 2 % of the configured one divides their spacing.
fn centring_grid(
    capture: &Capture,
    anchor_frame: usize,
    reference_frames: &[usize],
    config: &BurstConfig,
) -> Result<Option<(usize, usize)>> {
    let Some(&nearest) = reference_frames
        .iter()
        .min_by_key(|&&r| (r.abs_diff(anchor_frame), r))
    else {
        return Ok(None);
    };
    let block_size = BlockPlan::choose(&capture.frames, nearest, &config.align.blocks)?.block_size;
    let spacing = match reference_frames {
        [_] => block_size,
        [a, b, ..] if b > a => b - a,
        _ => return Ok(None),
    };
    if reference_frames.windows(2).any(|w| w[1] != w[0] + spacing) {
        return Ok(None);
    }
    // B' = S / n nearest B; kept only within 2 % of B (measured: B 383 -> 500 costs more
    // than centring gains).
    let n = ((spacing as f64 / block_size as f64).round() as usize).max(1);
    let snapped = spacing / n;
    let near = 50 * snapped.abs_diff(block_size) <= block_size;
    Ok((spacing % n == 0 && near).then_some((nearest, snapped)))
}

/// What every video frame of a burst reconstruction shares: the alignment (grey blocks) and
/// the sub-block motion relative to the anchor frame, and the burst configuration they were
/// made with.
struct SharedMotion {
    burst_config: BurstConfig,
    alignment: Alignment,
    motion: FrameMotion,
    /// The camera was tracked as fast motion: block flows are streak matches, no local motion.
    tracked: bool,
}

/// Reconstructions of one capture at many reference frames, reusing the work that does not
/// depend on the reference frame (see the module documentation).
pub struct VideoReconstructor<'a> {
    capture: &'a Capture,
    config: ReconstructConfig,
    anchor_frame: usize,
    shared: Option<SharedMotion>,
    fallback: Option<String>,
    timings: Vec<StageTiming>,
}

impl<'a> VideoReconstructor<'a> {
    /// Estimates the motion of `capture` once, at the anchor frame (`config.reference_frame`,
    /// else the capture's reference frame): hot-pixel corrected block sums, grey images, block
    /// alignment and sub-block camera motion. With the naive method nothing is kept and every
    /// frame runs the full reconstruction.
    pub fn new(
        capture: &'a Capture,
        config: &ReconstructConfig,
        progress: &dyn Progress,
    ) -> Result<Self> {
        Self::build(capture, config, &[], progress)
    }

    /// [`Self::new`] for a video of evenly spaced `reference_frames` (as
    /// [`video_reference_frames`] makes). When the block size B (fixed, or chosen by light at
    /// the reference frame nearest the configured anchor, [`crate::align::BlockPlan::choose`])
    /// divides their spacing (within 2 %: B becomes S / round(S / B), S the spacing), the
    /// anchor becomes that nearest reference frame, so that every
    /// one of them sits at the centre of its block of the anchor's grid, as the per-reference
    /// path places its own reference frame: the grey blocks, hence the moving-object
    /// detections, are then the per-reference path's, and the local residual (zero at the
    /// centre of the reference block) is zero at the video frame itself. Otherwise the grid is
    /// [`Self::new`]'s. B moves by 2 % at most: changing it further to divide the spacing
    /// cost more than centring gains (`bench video`; docs/tuning.md). This placement is the
    /// project's own.
    pub fn for_frames(
        capture: &'a Capture,
        config: &ReconstructConfig,
        reference_frames: &[usize],
        progress: &dyn Progress,
    ) -> Result<Self> {
        Self::build(capture, config, reference_frames, progress)
    }

    fn build(
        capture: &'a Capture,
        config: &ReconstructConfig,
        reference_frames: &[usize],
        progress: &dyn Progress,
    ) -> Result<Self> {
        let mut anchor_frame = config
            .reference_frame
            .unwrap_or_else(|| capture.reference_frame());
        let t = capture.frames.frame_count();
        if let Some(&bad) = reference_frames.iter().find(|&&r| r >= t) {
            return Err(Error::invalid(format!(
                "reference frame {bad} is outside the capture's {t} frames"
            )));
        }
        if anchor_frame >= t {
            return Err(Error::invalid(format!(
                "reference frame {anchor_frame} is outside the capture's {t} frames"
            )));
        }
        let mut video = VideoReconstructor {
            capture,
            config: config.clone(),
            anchor_frame,
            shared: None,
            fallback: None,
            timings: Vec::new(),
        };
        if config.method != Method::Burst {
            video.fallback = Some(format!(
                "the {} method has no motion to reuse",
                config.method
            ));
            return Ok(video);
        }
        let mut burst_config = config_for_capture(capture, &burst_config_for(config));
        if let Some((anchor, block_size)) =
            centring_grid(capture, anchor_frame, reference_frames, &burst_config)?
        {
            anchor_frame = anchor;
            video.anchor_frame = anchor;
            burst_config.align.blocks.block_size = Some(block_size);
        }
        let mut laps = Laps::new();
        // The sums made here stay cached (bounded) for every frame's merge, until drop.
        capture.frames.forget_shared_sums();
        let EstimatedMotion {
            alignment,
            motion,
            tracked,
        } = estimate_motion(
            capture,
            anchor_frame,
            &burst_config,
            None,
            &mut laps,
            progress,
        )?;
        video.timings = laps.timings;
        video.shared = Some(SharedMotion {
            burst_config,
            alignment,
            motion,
            tracked,
        });
        Ok(video)
    }

    /// The frame the shared motion is anchored at.
    pub fn anchor_frame(&self) -> usize {
        self.anchor_frame
    }

    /// Why frames are reconstructed on their own instead of from the shared motion; `None`
    /// when they reuse it.
    pub fn fallback_reason(&self) -> Option<&str> {
        self.fallback.as_deref()
    }

    /// Wall-clock time of the shared stages (made once, in [`Self::new`]).
    pub fn shared_timings(&self) -> &[StageTiming] {
        &self.timings
    }

    /// The reconstruction registered to `reference_frame`: tile alignment for the local
    /// residual, the merge guide, joint demosaic-merge and denoising at the shared camera
    /// motion composed to that frame ([`reanchor_cameras`]), or the full [`reconstruct`] when
    /// frames fall back. Its `burst` holds the frame's alignment (the shared grey blocks on the
    /// anchor's block grid, tile flows relative to this frame's block) and motion.
    pub fn frame(&self, reference_frame: usize, progress: &dyn Progress) -> Result<Reconstruction> {
        let t = self.capture.frames.frame_count();
        if reference_frame >= t {
            return Err(Error::invalid(format!(
                "reference frame {reference_frame} is outside the capture's {t} frames"
            )));
        }
        let Some(shared) = &self.shared else {
            let config = ReconstructConfig {
                reference_frame: Some(reference_frame),
                ..self.config.clone()
            };
            return reconstruct(self.capture, &config, progress);
        };
        let mut laps = Laps::new();
        let (alignment, motion) = self.motion_at(shared, reference_frame, progress)?;
        laps.lap("tile alignment");
        let burst = merge_at_motion(
            self.capture,
            alignment,
            motion,
            None,
            &shared.burst_config,
            &mut laps,
            progress,
        )?;
        let merged = Merged {
            linear: burst.merged.linear.clone(),
            frames_used: t,
            timings: burst.timings.clone(),
            burst: Some(burst),
        };
        denoise_and_finish(
            self.capture,
            &self.config,
            reference_frame,
            merged,
            progress,
        )
    }
}

impl VideoReconstructor<'_> {
    /// The alignment and sub-block motion relative to `reference_frame`: the shared grey blocks
    /// tile-aligned to its block (for the local residual) and the shared cameras composed to it.
    fn motion_at(
        &self,
        shared: &SharedMotion,
        reference_frame: usize,
        progress: &dyn Progress,
    ) -> Result<(Alignment, FrameMotion)> {
        let config = &shared.burst_config;
        let mut plan = shared.alignment.plan.clone();
        plan.reference_frame = reference_frame;
        plan.reference_block = plan
            .blocks
            .iter()
            .position(|b| b.contains(&reference_frame))
            .expect("the blocks cover the capture");
        let (grid, flow) =
            align_grey_blocks(&shared.alignment.grey, &plan, &config.align, progress)?;
        let alignment = Alignment {
            plan,
            grid,
            flow,
            grey_method: shared.alignment.grey_method,
            grey: shared.alignment.grey.clone(),
        };
        // The local residual of r's own alignment, with the shared sub-blocks and their
        // cameras composed to r.
        let mut motion = FrameMotion::from_alignment(
            &alignment,
            config.align.affine_tolerance_px,
            config.refine.min_local_tiles,
            config.refine.local_consistency,
        );
        if !config.refine.keep_local_motion || shared.tracked {
            motion.drop_local_motion();
        }
        let to_anchor = if reference_frame == shared.motion.plan.reference_frame || shared.tracked {
            None
        } else {
            frame_to_anchor_from_blocks(&shared.motion, &motion.camera)
        };
        motion.camera = match to_anchor {
            Some(w) => compose_cameras(&shared.motion, &w),
            None => reanchor_cameras(&shared.motion, reference_frame)?,
        };
        motion.sub_blocks = shared.motion.sub_blocks.clone();
        motion.block_of = shared.motion.block_of.clone();
        Ok((alignment, motion))
    }
}

impl Drop for VideoReconstructor<'_> {
    fn drop(&mut self) {
        self.capture.frames.forget_shared_sums();
    }
}

/// A finished video ([`reconstruct_video`]).
#[derive(Debug, Clone)]
pub struct Video {
    /// Linear RGB (H, W, 3) of every reference frame, in the order asked (units of
    /// [`Reconstruction::linear`]).
    pub frames: Vec<Array3<f32>>,
    /// Why frames were reconstructed on their own ([`VideoReconstructor::fallback_reason`]).
    pub fallback_reason: Option<String>,
}

/// Reconstructs `capture` at every one of `reference_frames` with a [`VideoReconstructor`].
pub fn reconstruct_video(
    capture: &Capture,
    config: &ReconstructConfig,
    reference_frames: &[usize],
    progress: &dyn Progress,
) -> Result<Video> {
    let t = capture.frames.frame_count();
    if let Some(&bad) = reference_frames.iter().find(|&&r| r >= t) {
        return Err(Error::invalid(format!(
            "reference frame {bad} is outside the capture's {t} frames"
        )));
    }
    let video = VideoReconstructor::for_frames(capture, config, reference_frames, progress)?;
    let frames = reference_frames
        .iter()
        .map(|&r| video.frame(r, progress).map(|rec| rec.linear))
        .collect::<Result<_>>()?;
    Ok(Video {
        frames,
        fallback_reason: video.fallback_reason().map(str::to_string),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reference_frames_are_centred_in_their_stride() {
        assert_eq!(
            video_reference_frames(4000, 500).unwrap(),
            [250, 750, 1250, 1750, 2250, 2750, 3250, 3750]
        );
        assert_eq!(
            video_reference_frames(10, 1).unwrap(),
            (0..10).collect::<Vec<_>>()
        );
        assert!(video_reference_frames(3, 8).unwrap().is_empty());
        assert!(video_reference_frames(100, 0).is_err());
    }
}
