//! The settings of the photon-trajectory fit (`[burst.trajectory]`) and their checks.
//! Tuning measurements of these keys: docs/tuning.md.

#![forbid(unsafe_code)]

use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};

/// Settings of [`super::fit_photon_trajectory`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct TrajectoryConfig {
    /// Fit the trajectory to the photons after fast-motion tracking.
    pub enabled: bool, // true
    /// Frames between knots of the piecewise-linear trajectory.
    pub knot_frames: usize, // 4 frames
    /// Template blur of each coarse-to-fine level (px): the capture range of the fit.
    pub sigmas_px: Vec<f32>,
    /// Fisher-scoring iterations per level (the template is rebuilt before each).
    pub iterations: usize, // 2
    /// Prior standard deviation of the camera's acceleration (px per frame², at the image
    /// corners for the linear part): hand shake is smooth, photon noise is not.
    pub acceleration_px: f64, // 0.05 px/frame²
    /// Scene margin around the sensor kept in the template (px): content that leaves the
    /// sensor while the camera moves still aligns.
    pub margin_px: usize, // 48 px
    /// Every iteration but the last uses the grey sites of every n-th sensor row only (the
    /// last uses all). 1 uses every row throughout; 2 is a speed setting (0.68 of the stage's
    /// time, within ±0.16 dB, but lost up to 0.15 dB on sheared HDR captures; docs/tuning.md).
    pub early_row_step: usize, // 1
    /// The score reads only the sites that land in the template's most informative 8 × 8 px
    /// blocks, those holding this share of its Fisher information about position (flat
    /// regions add little); 1 reads every site. Below 1 it is a speed setting: 0.9 takes about
    /// half the stage's time but lost 0.11 dB (0.20 dB after chroma-BM3D) on `bench
    /// quality`'s kodim15 fast capture, so it is not the default (docs/tuning.md).
    pub informative_fraction: f64, // 1
}

impl Default for TrajectoryConfig {
    fn default() -> Self {
        TrajectoryConfig {
            enabled: true,
            knot_frames: 4,
            sigmas_px: vec![1.5, 0.6],
            iterations: 2,
            acceleration_px: 0.05,
            margin_px: 48,
            early_row_step: 1,
            informative_fraction: 1.0,
        }
    }
}

impl TrajectoryConfig {
    /// Checks that the settings hold usable values (the error names the key).
    pub fn validate(&self) -> Result<()> {
        let bad = |key: &str, what: &str, value: String| {
            Err(Error::invalid(format!(
                "photon trajectory: [burst.trajectory] {key} must be {what}, got {value}"
            )))
        };
        for (key, value) in [
            ("knot_frames", self.knot_frames),
            ("iterations", self.iterations),
            ("early_row_step", self.early_row_step),
        ] {
            if value == 0 {
                return bad(key, "at least 1", value.to_string());
            }
        }
        if self.sigmas_px.is_empty() || self.sigmas_px.iter().any(|&s| !(s > 0.0 && s.is_finite()))
        {
            return bad(
                "sigmas_px",
                "a non-empty list of positive pixel sizes",
                format!("{:?}", self.sigmas_px),
            );
        }
        if !(self.acceleration_px > 0.0 && self.acceleration_px.is_finite()) {
            return bad(
                "acceleration_px",
                "a positive number",
                self.acceleration_px.to_string(),
            );
        }
        if !(self.informative_fraction > 0.0 && self.informative_fraction <= 1.0) {
            return bad(
                "informative_fraction",
                "a fraction in (0, 1]",
                self.informative_fraction.to_string(),
            );
        }
        Ok(())
    }
}
