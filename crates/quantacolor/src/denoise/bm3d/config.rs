//! The parameters of both BM3D steps (Dabov et al., TIP 2007, Table I), their checks, and the
//! high-noise regime that switches some of them when σ > 40 (on the paper's 0..255 scale).

#![forbid(unsafe_code)]

use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};

/// Parameters of both BM3D steps. Defaults are the "normal profile" of TIP 2007 Table I
/// (σ ≤ 40), with its σ > 40 values of `τ^ht_match`, `λ_3D` and `τ^wie_match` switched on
/// automatically (but λ_2D = 0, see the module doc).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct Bm3dConfig {
    /// Block side `N1` in pixels (both steps).
    pub block_size: usize,
    /// Stride `Nstep` of the reference-block grid in pixels (both steps); the last row and
    /// column of block positions are always included. TIP 2007 Table I: 3 (normal profile),
    /// 5–6 (fast). Default 5, this project's tuning (docs/tuning.md).
    pub step: usize,
    /// Side `NS` of the search window centred on the reference block, in pixels (both steps).
    /// 39 (TIP 2007 Table I, normal profile); smaller windows measured worse (docs/tuning.md).
    pub search_window: usize,
    /// Maximum group size `N2^ht` of Step 1 (a power of two).
    pub max_group_ht: usize,
    /// Maximum group size `N2^wie` of Step 2 (a power of two).
    pub max_group_wiener: usize,
    /// Step 1 matching threshold `τ^ht_match`: mean squared difference per pixel, 0..255 scale.
    pub tau_match_ht: f32,
    /// Step 1 matching threshold used when σ > `high_noise_sigma` (paper: 5000).
    pub tau_match_ht_high_noise: f32,
    /// Step 2 matching threshold `τ^wie_match`, per pixel, 0..255 scale.
    pub tau_match_wiener: f32,
    /// Step 2 matching threshold used when σ > `high_noise_sigma` (paper: 3500).
    pub tau_match_wiener_high_noise: f32,
    /// Hard threshold of the 3D spectrum, `λ_3D` (multiplies σ).
    pub lambda_3d: f32,
    /// `λ_3D` used when σ > `high_noise_sigma` (paper: 2.8).
    pub lambda_3d_high_noise: f32,
    /// Hard threshold `λ_2D` (multiplies σ) of the 2D coefficients used for Step 1 matching when
    /// σ > `high_noise_sigma` (paper: 2.0; default 0 = no thresholding, measured better here).
    pub lambda_2d: f32,
    /// σ on the 0..255 scale above which the `*_high_noise` values and `λ_2D` apply (paper: 40).
    pub high_noise_sigma: f32,
    /// β of the 2D Kaiser window applied to every block estimate in aggregation.
    pub kaiser_beta: f32,
    /// Intensity that corresponds to 255 in the paper's thresholds (the caller's white level).
    pub data_range: f32,
    /// Run Step 2 (Wiener filtering); `false` returns the basic estimate of Step 1.
    pub wiener: bool,
    /// Correlation length (px) of the noise, channel 0 then the others: each 2D DCT coefficient
    /// gets the σ of white noise smoothed by a Gaussian of this std (after Mäkinen et al., TIP
    /// 2020; this project's model). 0 = white (TIP 2007); chroma-BM3D sets it.
    // Chroma-BM3D reports it as `DenoiseConfig::noise_correlation_px`, so here only when not white.
    #[serde(skip_serializing_if = "is_white")]
    pub noise_correlation_px: [f32; 2],
}

fn is_white(correlation_px: &[f32; 2]) -> bool {
    correlation_px.iter().all(|&s| s == 0.0)
}

impl Default for Bm3dConfig {
    fn default() -> Self {
        Bm3dConfig {
            block_size: 8,
            step: 5,
            search_window: 39,
            max_group_ht: 16,
            max_group_wiener: 32,
            tau_match_ht: 3000.0,
            tau_match_ht_high_noise: 5000.0,
            tau_match_wiener: 400.0,
            tau_match_wiener_high_noise: 3500.0,
            lambda_3d: 2.7,
            lambda_3d_high_noise: 2.8,
            lambda_2d: 0.0,
            high_noise_sigma: 40.0,
            kaiser_beta: 2.0,
            data_range: 255.0,
            wiener: true,
            noise_correlation_px: [0.0, 0.0],
        }
    }
}

impl Bm3dConfig {
    /// Checks every parameter (the error names the bad one); BM3D runs it too.
    pub fn validate(&self) -> Result<()> {
        let bad = |what: &str| Err(Error::invalid(format!("BM3D config: {what}")));
        if !(1..=32).contains(&self.block_size) {
            return bad(&format!("block_size {} not in 1..=32", self.block_size));
        }
        if self.step == 0 {
            return bad("step must be at least 1");
        }
        if self.search_window == 0 {
            return bad("search_window must be at least 1");
        }
        if self.max_group_ht == 0 || self.max_group_wiener == 0 {
            return bad("group sizes must be at least 1");
        }
        let non_neg = [
            ("tau_match_ht", self.tau_match_ht),
            ("tau_match_ht_high_noise", self.tau_match_ht_high_noise),
            ("tau_match_wiener", self.tau_match_wiener),
            (
                "tau_match_wiener_high_noise",
                self.tau_match_wiener_high_noise,
            ),
            ("lambda_3d_high_noise", self.lambda_3d_high_noise),
            ("lambda_3d", self.lambda_3d),
            ("lambda_2d", self.lambda_2d),
            ("high_noise_sigma", self.high_noise_sigma),
            ("kaiser_beta", self.kaiser_beta),
            ("noise_correlation_px[0]", self.noise_correlation_px[0]),
            ("noise_correlation_px[1]", self.noise_correlation_px[1]),
        ];
        for (name, v) in non_neg {
            if !v.is_finite() || v < 0.0 {
                return bad(&format!("{name} = {v} must be finite and non-negative"));
            }
        }
        if !self.data_range.is_finite() || self.data_range <= 0.0 {
            return bad(&format!(
                "data_range = {} must be finite and positive",
                self.data_range
            ));
        }
        Ok(())
    }
}

/// The parameters TIP 2007 (Table I) switches when channel 0's σ exceeds `high_noise_sigma`.
pub(super) struct NoiseRegime {
    pub(super) high_noise: bool,
    /// `data_range / 255`: the factor from the paper's 0–255 thresholds to image units.
    scale: f32,
}

impl NoiseRegime {
    pub(super) fn of(sigma0: f32, config: &Bm3dConfig) -> Self {
        let scale = config.data_range / 255.0;
        NoiseRegime {
            high_noise: sigma0 / scale > config.high_noise_sigma,
            scale,
        }
    }

    /// A per-pixel matching threshold as the summed squared distance over an N1×N1 block.
    pub(super) fn tau_sum(&self, tau: f32, tau_high_noise: f32, n: usize) -> f32 {
        let tau = if self.high_noise { tau_high_noise } else { tau };
        tau * self.scale * self.scale * (n * n) as f32
    }
}
