//! Typed configuration and the stage sequence of a reconstruction. Every stage is also callable
//! on its own (see the module of each stage).
#![forbid(unsafe_code)]

use crate::burst::{reconstruct_burst, BurstConfig, BurstReconstruction};
use crate::capture::Capture;
use crate::denoise::chroma::{
    denoise_linear_with_progress, DenoiseConfig, DenoiseInput, DenoiseMethod, DenoiseReport,
    MergeNoise,
};
use crate::error::{Error, Result};
use crate::naive::{reconstruct_naive, NaiveConfig};
use crate::progress::Progress;
use crate::timing::StageTiming;
use ndarray::Array3;
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// Reconstruction method.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Method {
    /// Align, jointly demosaic and merge, combine RGBW (paper §4).
    Burst,
    /// Sum a window of frames without motion compensation (paper Table 2 baseline).
    Naive,
}

impl std::str::FromStr for Method {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "burst" => Ok(Method::Burst),
            "naive" => Ok(Method::Naive),
            other => Err(Error::invalid(format!(
                "unknown method '{other}' (available: burst, naive)"
            ))),
        }
    }
}

impl std::fmt::Display for Method {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Method::Burst => "burst",
            Method::Naive => "naive",
        })
    }
}

/// A named set of settings (`reconstruct --profile`): `default`, or `fast` for those who need
/// speed more than the last 0.1–0.2 dB (this project's: longer sub-blocks, one refinement
/// pass, BM3D's fast profile; the settings are
/// `profiles/fast.toml` of this crate, measured in docs/speed.md).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Profile {
    #[default]
    Default,
    Fast,
}

impl std::str::FromStr for Profile {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "default" => Ok(Profile::Default),
            "fast" => Ok(Profile::Fast),
            other => Err(Error::invalid(format!(
                "unknown profile '{other}' (available: default, fast)"
            ))),
        }
    }
}

impl std::fmt::Display for Profile {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Profile::Default => "default",
            Profile::Fast => "fast",
        })
    }
}

impl Profile {
    /// The profile's settings: a partial config in TOML (empty for the default).
    pub fn toml(self) -> &'static str {
        match self {
            Profile::Default => "",
            Profile::Fast => include_str!("../profiles/fast.toml"),
        }
    }

    /// The reconstruction config of this profile.
    pub fn config(self) -> Result<ReconstructConfig> {
        crate::config_toml::parse(self.toml())
    }

    /// The partial config in TOML `text` laid over this profile's settings.
    pub fn config_with(self, text: &str) -> Result<ReconstructConfig> {
        crate::config_toml::parse_over(self.toml(), text)
    }
}

/// Configuration of a whole reconstruction.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct ReconstructConfig {
    pub method: Method,
    /// Reference frame (default: the capture's).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reference_frame: Option<usize>,
    pub naive: NaiveConfig,
    pub burst: BurstConfig,
    pub denoise: DenoiseConfig,
}

impl Default for ReconstructConfig {
    fn default() -> Self {
        ReconstructConfig {
            method: Method::Burst,
            reference_frame: None,
            naive: NaiveConfig::default(),
            burst: BurstConfig::default(),
            denoise: DenoiseConfig::default(),
        }
    }
}

/// A finished reconstruction.
#[derive(Debug, Clone)]
pub struct Reconstruction {
    /// Linear RGB (H, W, 3) in detections per frame of an R, G or B pixel, dark counts removed,
    /// registered to the scene at the reference frame; never negative.
    pub linear: Array3<f32>,
    /// The merged image before denoising (`None` when denoising is off).
    pub merged_linear: Option<Array3<f32>>,
    /// What the denoising stage did (`None` when it is off).
    pub denoise: Option<DenoiseReport>,
    pub reference_frame: usize,
    /// Frames that contributed.
    pub frames_used: usize,
    pub timings: Vec<StageTiming>,
    /// Intermediate stages of the burst method (for `--dump-stages`).
    pub burst: Option<BurstReconstruction>,
}

/// The burst configuration actually run: the merge's colour-kernel spacing exponent is
/// replaced by the denoiser's `merge_spacing_exponent` when denoising is on.
pub fn burst_config_for(config: &ReconstructConfig) -> BurstConfig {
    let mut burst = config.burst.clone();
    if config.denoise.method != DenoiseMethod::None {
        if let Some(e) = config.denoise.merge_spacing_exponent {
            burst.merge.accumulate.spacing_exponent = e;
        }
        if let Some(k) = config.denoise.merge_k_denoise {
            burst.merge.kernels.k_denoise = k;
        }
    }
    burst
}

/// The denoiser's inputs for a reconstruction of `capture`: the merge's noise model (binomial,
/// or Gaussian–Poisson for multi-bit frames) when there is a burst merge, else the number of
/// frames summed.
pub fn denoise_input<'a>(
    capture: &Capture,
    burst: Option<&'a BurstReconstruction>,
    frames_used: usize,
) -> DenoiseInput<'a> {
    DenoiseInput {
        noise: burst.map(|b| MergeNoise {
            flux: b.merged.planes.flux.view(),
            effective_frames: b.merged.planes.effective_frames.view(),
        }),
        frames: frames_used as f64,
        model: capture.meta.pixel_model(),
        w_weights: capture.meta.w_weights,
    }
}

/// Runs the configured reconstruction on `capture`.
pub fn reconstruct(
    capture: &Capture,
    config: &ReconstructConfig,
    progress: &dyn Progress,
) -> Result<Reconstruction> {
    crate::cpu::on_pool(|| reconstruct_on_pool(capture, config, progress))
}

fn reconstruct_on_pool(
    capture: &Capture,
    config: &ReconstructConfig,
    progress: &dyn Progress,
) -> Result<Reconstruction> {
    let reference_frame = config
        .reference_frame
        .unwrap_or_else(|| capture.reference_frame());
    let t = capture.frames.frame_count();
    if reference_frame >= t {
        return Err(Error::invalid(format!(
            "reference frame {reference_frame} is outside the capture's {t} frames"
        )));
    }
    let start = Instant::now();
    let (linear, frames_used, burst, timings) = match config.method {
        Method::Naive => {
            progress.start("naive merge", 1);
            let naive = reconstruct_naive(capture, reference_frame, &config.naive)?;
            progress.advance(1);
            progress.finish();
            let timing = StageTiming::since("naive", start);
            (naive.linear, naive.frames.len(), None, vec![timing])
        }
        Method::Burst => {
            let burst_config = burst_config_for(config);
            let burst = reconstruct_burst(capture, reference_frame, &burst_config, progress)?;
            let timings = burst.timings.clone();
            (burst.merged.linear.clone(), t, Some(burst), timings)
        }
    };

    let merged = Merged {
        linear,
        frames_used,
        burst,
        timings,
    };
    denoise_and_finish(capture, config, reference_frame, merged, progress)
}

/// A merged image before denoising: the merge's `linear` RGB from `frames_used` frames, the
/// burst reconstruction it came from (burst method) and the stage timings so far.
pub(crate) struct Merged {
    pub(crate) linear: Array3<f32>,
    pub(crate) frames_used: usize,
    pub(crate) burst: Option<BurstReconstruction>,
    pub(crate) timings: Vec<StageTiming>,
}

/// The last stage of a reconstruction, chrominance-focused denoising (paper §4.3), of the
/// merged `linear` image, and the finished [`Reconstruction`] (shared by [`reconstruct`] and
/// [`crate::video`]).
pub(crate) fn denoise_and_finish(
    capture: &Capture,
    config: &ReconstructConfig,
    reference_frame: usize,
    merged: Merged,
    progress: &dyn Progress,
) -> Result<Reconstruction> {
    let Merged {
        linear,
        frames_used,
        burst,
        mut timings,
    } = merged;
    let start = Instant::now();
    let input = denoise_input(capture, burst.as_ref(), frames_used);
    let (mut denoised, denoise) =
        denoise_linear_with_progress(linear.view(), &input, &config.denoise, progress)?;
    // A flux is never negative. Inside the merge a channel that saw nothing keeps its unbiased
    // MLE −d (paper Eq. 6, unclamped, so that averages stay unbiased); the output does not.
    denoised.mapv_inplace(|v| v.max(0.0));
    let merged_linear = denoise.as_ref().map(|_| linear);
    if denoise.is_some() {
        timings.push(StageTiming::since("denoise", start));
    }
    Ok(Reconstruction {
        linear: denoised,
        merged_linear,
        denoise,
        reference_frame,
        frames_used,
        timings,
        burst,
    })
}

/// Options that override parts of a [`ReconstructConfig`]: the flags of `quantacolor
/// reconstruct` and the keywords of the Python `reconstruct()`, validated in one place. `None`
/// leaves the config's value.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ReconstructOverrides {
    pub method: Option<Method>,
    pub reference_frame: Option<usize>,
    /// Naive method: frames centred on the reference frame.
    pub window: Option<usize>,
    /// Burst method: frames per temporal block for alignment.
    pub block_size: Option<usize>,
    /// Burst method: output grid scale, 1..=4.
    pub scale: Option<usize>,
    pub denoise: Option<DenoiseMethod>,
    pub sigma_y: Option<f32>,
    pub sigma_c: Option<f32>,
    /// Burst method: largest camera motion inside one sub-block, px.
    pub max_sub_block_motion: Option<f64>,
}

impl ReconstructOverrides {
    /// Applies the overrides to `config`. Errors name the option through `name`, which maps a
    /// field name (`"scale"`) to the caller's spelling (`--scale` on the command line).
    pub fn apply(
        &self,
        config: &mut ReconstructConfig,
        name: &dyn Fn(&str) -> String,
    ) -> Result<()> {
        if let Some(m) = self.method {
            config.method = m;
            // The naive baseline is the plain sum (paper Table 2), not denoised unless asked.
            if m == Method::Naive && self.denoise.is_none() {
                config.denoise.method = DenoiseMethod::None;
            }
        }
        if self.reference_frame.is_some() {
            config.reference_frame = self.reference_frame;
        }
        if self.window.is_some() {
            config.naive.window = self.window;
        }
        if self.block_size.is_some() {
            config.burst.align.blocks.block_size = self.block_size;
        }
        if let Some(scale) = self.scale {
            if !(1..=4).contains(&scale) {
                return Err(Error::invalid(format!(
                    "{} must be 1, 2, 3 or 4, got {scale}",
                    name("scale")
                )));
            }
            config.burst.merge.accumulate.scale = scale;
        }
        if let Some(d) = self.denoise {
            config.denoise.method = d;
        }
        for (key, sigma) in [("sigma_y", self.sigma_y), ("sigma_c", self.sigma_c)] {
            if let Some(s) = sigma {
                if !(s.is_finite() && s >= 0.0) {
                    return Err(Error::invalid(format!(
                        "{} must be a non-negative number, got {s}",
                        name(key)
                    )));
                }
            }
        }
        if self.sigma_y.is_some() {
            config.denoise.sigma_y = self.sigma_y;
        }
        if self.sigma_c.is_some() {
            config.denoise.sigma_c = self.sigma_c;
        }
        if let Some(m) = self.max_sub_block_motion {
            if !(m.is_finite() && m > 0.0) {
                return Err(Error::invalid(format!(
                    "{} must be a positive number of pixels, got {m}",
                    name("max_sub_block_motion")
                )));
            }
            config.burst.refine.max_sub_block_motion_px = m;
        }
        Ok(())
    }
}
