//! Settings of the frame-granular camera motion (`[burst.refine]`) and their checks.
#![forbid(unsafe_code)]

use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};

/// One coarse-to-fine level of the sub-block fit.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RefineLevel {
    /// Side of the square bins that photon counts are summed over (px).
    pub bin: usize, // px
    /// Gaussian σ the reference is smoothed with at this level (px): the capture range.
    pub sigma_px: f32, // px
}

/// Settings of the frame-granular camera motion
/// ([`refine_camera_motion`](super::refine_camera_motion)). The measurements behind the defaults
/// are in docs/tuning.md (`[burst.refine]`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct RefineConfig {
    /// Re-measure the camera motion of every sub-block; off = the paper's linear interpolation
    /// of block motion (sub-blocks are still cut and merged at their interpolated motion).
    pub enabled: bool, // true
    /// Largest camera displacement inside one sub-block (px, over the image corners): sets the
    /// sub-block length from the motion's speed (blur uniform over 0.35 px: σ = 0.10 px).
    pub max_sub_block_motion_px: f64, // 0.35 px
    /// Fewest mean detections per pixel a sub-block must collect: sets the shortest sub-block
    /// from the light level.
    pub min_sub_block_counts: f64, // 1 detection
    /// Shortest sub-block (frames).
    pub min_sub_block_frames: usize, // 8 frames
    /// Coarse-to-fine levels of the Gauss–Newton fit.
    pub levels: Vec<RefineLevel>,
    /// Gauss–Newton iterations per level but the finest (fewer when the update falls below
    /// 0.002 px): the coarse levels only bring the fit within the finest level's capture range.
    pub iterations: usize, // 3
    /// Gauss–Newton iterations at the finest level (fewer when the update falls below 0.002
    /// px), with the alternation damping of [`alternation_factor`](super::fit::alternation_factor).
    pub fine_iterations: usize, // 2
    /// The finest level's iterations but the last sum every 2^k-th group of eight bin rows
    /// only, k = min(this, iterations left after it); 0 = every bin in every iteration. This
    /// project's economy, not the paper's; off by default (it loses accuracy on weak texture).
    pub fine_thinning: usize, // 0 (every iteration over every bin)
    /// Share of the Fisher information about each affine parameter that the finest level's bins
    /// keep ([`most_informative_bins`](super::bins::most_informative_bins); 1 = every bin). This
    /// project's heuristic, not the paper's (its §4.1 aligns blocks only).
    pub fine_information: f64, // 1 (every bin)
    /// Most passes of template and fit: each pass rebuilds the templates from the block motion
    /// of the previous one (templates warped by a motion that is off are blurred and shifted).
    pub passes: usize, // 3
    /// Another pass runs while the last one moved the median sub-block by more than this (px,
    /// worst image corner).
    pub repeat_above_px: f64, // 0.5 px
    /// Half-width of the local quadratic fit along time (sub-blocks); 0 = no smoothing.
    pub smooth_radius: usize, // 0 sub-blocks
    /// Keep the tile flows that the block's camera fit does not explain (moving objects, but
    /// also tiles matched a texture period off) as a local motion on top of the camera's.
    pub keep_local_motion: bool, // true
    /// Fewest connected tiles moving alike for a local motion to be kept (16 px tiles at
    /// stride 8: 80 tiles cover about 70 x 70 px).
    pub min_local_tiles: usize, // 80 tiles
    /// Tolerance, as a fraction of the change a constant velocity predicts (at least 1 px), for
    /// a local group to recur in a neighbouring block; 0 = no such check
    /// ([`confirmed_in_time`](super::local::confirmed_in_time), this project's heuristic).
    pub local_consistency: f32, // 0.5
    /// A sub-block whose fit moves further than this from its starting motion (px, at the image
    /// corners) is deemed failed and takes the smoothed motion of its neighbours.
    pub max_correction_px: f64, // 4 px
    /// Prior σ (px, at the image's farther edge) of the camera's departure from a similarity
    /// (rotation, uniform scale, translation); 0 = none (free affine fits). Applied after
    /// every pass by [`similarity_posterior`](super::prior::similarity_posterior).
    pub similarity_prior_px: f64, // 0.1 px
}

/// Checks that coarse-to-fine `levels` (of the refinement or the tracking) are not empty and
/// each has a bin of at least 1 px and a positive σ; `what` names them in the error.
pub(in crate::align) fn validate_levels(levels: &[RefineLevel], what: &str) -> Result<()> {
    if levels.is_empty() || levels.iter().any(|l| l.bin == 0 || l.sigma_px <= 0.0) {
        return Err(Error::invalid(format!(
            "{what} need a bin of at least 1 px and a positive sigma"
        )));
    }
    Ok(())
}

impl RefineConfig {
    /// Checks that the levels and the pixel thresholds hold usable values.
    pub fn validate(&self) -> Result<()> {
        validate_levels(&self.levels, "motion refinement: levels")?;
        for (key, value) in [
            ("similarity_prior_px", self.similarity_prior_px),
            ("repeat_above_px", self.repeat_above_px),
            ("max_correction_px", self.max_correction_px),
            ("local_consistency", self.local_consistency as f64),
            ("min_sub_block_counts", self.min_sub_block_counts),
        ] {
            if !(value.is_finite() && value >= 0.0) {
                return Err(Error::invalid(format!(
                    "motion refinement: [burst.refine] {key} must be a non-negative number, got {value}"
                )));
            }
        }
        if !(self.max_sub_block_motion_px.is_finite() && self.max_sub_block_motion_px > 0.0) {
            return Err(Error::invalid(format!(
                "motion refinement: [burst.refine] max_sub_block_motion_px must be a positive \
                 number of pixels, got {}",
                self.max_sub_block_motion_px
            )));
        }
        if !(self.fine_information > 0.0 && self.fine_information <= 1.0) {
            return Err(Error::invalid(format!(
                "motion refinement: [burst.refine] fine_information must be a share in (0, 1], \
                 got {}",
                self.fine_information
            )));
        }
        for (key, value) in [
            ("min_sub_block_frames", self.min_sub_block_frames),
            ("iterations", self.iterations),
            ("fine_iterations", self.fine_iterations),
            ("passes", self.passes),
        ] {
            if value == 0 {
                return Err(Error::invalid(format!(
                    "motion refinement: [burst.refine] {key} must be at least 1 (enabled = false \
                     turns the refinement off)"
                )));
            }
        }
        Ok(())
    }
}

impl Default for RefineConfig {
    fn default() -> Self {
        RefineConfig {
            enabled: true,
            max_sub_block_motion_px: 0.35,
            min_sub_block_counts: 1.0,
            min_sub_block_frames: 8,
            levels: vec![
                RefineLevel {
                    bin: 4,
                    sigma_px: 2.0,
                },
                RefineLevel {
                    bin: 1,
                    sigma_px: 0.4,
                },
            ],
            iterations: 3,
            fine_iterations: 2,
            fine_thinning: 0,
            fine_information: 1.0,
            passes: 3,
            repeat_above_px: 0.5,
            smooth_radius: 0,
            max_correction_px: 4.0,
            similarity_prior_px: 0.1,
            keep_local_motion: true,
            min_local_tiles: 80,
            local_consistency: 0.5,
        }
    }
}
