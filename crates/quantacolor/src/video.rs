//! Video: one reconstruction per reference frame of a sliding reference, with the motion
//! estimated once for the whole capture (this project's own stage; the papers' supplementary
//! videos reconstruct each reference frame from scratch).
//!
//! A reconstruction registers the whole burst to its reference frame r (paper §4, Fig. 4): the
//! merge needs the motion of every sub-block relative to r. Of the burst's stages
//! ([`crate::burst`]), only the guide (the Wiener reference image, its kernels and the
//! blocks' robustness, supplement §1.2–1.3), the joint demosaic-merge (supplement Eq. 1–3),
//! Eq. 6 and 8 and the denoiser (§4.3) depend on r in substance. The others are done once, at an
//! *anchor* reference frame a (the configured reference frame):
//!
//! - hot-pixel correction, block sums and grey block images, on the anchor's block grid (it does
//!   not move with r; r's block becomes the reference block);
//! - block alignment against the anchor's block and the sub-block camera motion
//!   (refinement, or fast-motion tracking and the photon trajectory), an affine map
//!   M_k: anchor → sub-block k per sub-block;
//! - the block and sub-block sums stay in [`crate::capture::BinaryFrames::shared_sum`]'s
//!   bounded cache from one video frame to the next.
//!
//! The motion relative to r is then the composition M_k ∘ M(r)⁻¹ ([`reanchor_motion`]), with
//! M(r) the camera at frame r interpolated between sub-block centres exactly as the burst
//! anchors its own motion at its reference frame ([`crate::align::refine_camera_motion`]).
//! For affine camera maps this is exact, not an approximation: it is the motion the
//! per-reference path measures, up to the photon noise of measuring it on a differently placed
//! block grid. The merge is the burst's own ([`crate::burst`]'s `merge_at_motion`): there is
//! one merge path.
//!
//! Limitation: local motion (moving objects, [`crate::align::FrameMotion::local`]) is measured
//! as tile flows on the anchor's grid at block granularity and does not compose as a map. When
//! the anchor's motion has a local residual, every frame falls back to the full per-reference
//! reconstruction ([`VideoReconstructor::fallback_reason`] says so), as does the naive method,
//! which has no motion to reuse.

use crate::align::{Alignment, FrameMotion};
use crate::burst::{config_for_capture, estimate_motion, merge_at_motion, BurstConfig};
use crate::capture::Capture;
use crate::error::{Error, Result};
use crate::pipeline::{
    burst_config_for, denoise_and_finish, reconstruct, Method, ReconstructConfig, Reconstruction,
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

/// `motion` (sub-block camera maps relative to its plan's reference frame a) relative to
/// `reference_frame` r instead: every sub-block's camera M_k becomes M_k ∘ M(r)⁻¹, where M(r) is
/// the camera at frame r ([`FrameMotion::camera_at`]); the block holding r becomes the
/// reference block. At r = a the motion is returned as it is (it is anchored there already).
///
/// Errors when `motion` has a local residual (moving objects: tile flows on a's grid that do not
/// compose as a map), when r is outside the burst or when M(r) cannot be inverted.
pub fn reanchor_motion(motion: &FrameMotion, reference_frame: usize) -> Result<FrameMotion> {
    let frames = motion.plan.blocks.last().map_or(0, |b| b.end);
    if reference_frame >= frames {
        return Err(Error::invalid(format!(
            "reference frame {reference_frame} is outside the burst's {frames} frames"
        )));
    }
    if motion.local.iter().any(|&v| v != 0.0) {
        return Err(Error::invalid(
            "motion with a local residual (moving objects) cannot be re-anchored",
        ));
    }
    let mut out = motion.clone();
    if reference_frame == motion.plan.reference_frame {
        return Ok(out);
    }
    let undo = motion
        .camera_at(reference_frame as f64)
        .inverse()
        .ok_or_else(|| {
            Error::invalid(format!(
                "the camera map at frame {reference_frame} cannot be inverted"
            ))
        })?;
    for camera in out.camera.iter_mut() {
        *camera = camera.after(&undo);
    }
    out.plan.reference_frame = reference_frame;
    out.plan.reference_block = out
        .plan
        .blocks
        .iter()
        .position(|b| b.contains(&reference_frame))
        .expect("the blocks cover the burst");
    Ok(out)
}

/// What every video frame of a burst reconstruction shares: the alignment (grey blocks) and
/// the sub-block motion relative to the anchor frame, and the burst configuration they were
/// made with.
struct SharedMotion {
    burst_config: BurstConfig,
    alignment: Alignment,
    motion: FrameMotion,
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
    /// alignment and sub-block camera motion. With the naive method, or when the capture has
    /// local motion, nothing is kept and every frame runs the full reconstruction.
    pub fn new(
        capture: &'a Capture,
        config: &ReconstructConfig,
        progress: &dyn Progress,
    ) -> Result<Self> {
        let anchor_frame = config
            .reference_frame
            .unwrap_or_else(|| capture.reference_frame());
        let t = capture.frames.frame_count();
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
        let burst_config = config_for_capture(capture, &burst_config_for(config));
        let mut laps = Laps::new();
        // The sums made here stay cached (bounded) for every frame's merge, until drop.
        capture.frames.forget_shared_sums();
        let (alignment, motion) =
            estimate_motion(capture, anchor_frame, &burst_config, None, &mut laps, progress)?;
        video.timings = laps.timings;
        if motion.local.iter().any(|&v| v != 0.0) {
            capture.frames.forget_shared_sums();
            video.fallback = Some(
                "the capture has local motion (moving objects), which does not compose \
                 between reference frames: every frame is reconstructed on its own"
                    .into(),
            );
            return Ok(video);
        }
        video.shared = Some(SharedMotion {
            burst_config,
            alignment,
            motion,
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

    /// The reconstruction registered to `reference_frame`: the merge guide, joint
    /// demosaic-merge and denoising at the shared motion re-anchored to that frame
    /// ([`reanchor_motion`]), or the full [`reconstruct`] when frames fall back. Its `burst`
    /// holds the anchor's alignment (the grey blocks and block flows the motion was measured
    /// from, relative to the anchor frame) and the re-anchored motion.
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
        let motion = reanchor_motion(&shared.motion, reference_frame)?;
        let burst = merge_at_motion(
            self.capture,
            shared.alignment.clone(),
            motion,
            None,
            &shared.burst_config,
            &mut laps,
            progress,
        )?;
        let timings = burst.timings.clone();
        denoise_and_finish(
            self.capture,
            &self.config,
            reference_frame,
            burst.merged.linear.clone(),
            t,
            Some(burst),
            timings,
        )
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
    let video = VideoReconstructor::new(capture, config, progress)?;
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
        assert_eq!(video_reference_frames(10, 1).unwrap(), (0..10).collect::<Vec<_>>());
        assert!(video_reference_frames(3, 8).unwrap().is_empty());
        assert!(video_reference_frames(100, 0).is_err());
    }
}
