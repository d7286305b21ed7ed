//! Chrominance-focused colour denoising (paper §4.3, Fig. 6; supplement §1.5, Eq. 7–8).
//!
//! With an RGBW array the luminance of the merged image comes from the dense W pixels and the
//! chrominance from the sparse R, G, B pixels, so chrominance is far noisier. The image is
//! variance-stabilised per channel ([`Stabiliser`]: the binomial Anscombe transform, or for
//! multi-bit frames the generalized Anscombe transform of the Gaussian–Poisson model), converted to a YCbCr whose luma
//! weights (kR, kG, kB) are the normalised W weights (supplement Eq. 7–8), so that Y carries
//! exactly the W information, and denoised with BM3D grouping on Y only, filtering Y with a
//! small σ and Cb, Cr with a larger one. The σs come from the noise model of the merge
//! (each channel's flux and effective number of frames under the pixel model, carried through Eq. 8, the
//! transform and the colour matrix by the delta method) unless the user gives them.
//!
//! [`DenoiseMethod::Bm3d`] is the plain colour BM3D it is compared against (CBM3D, Dabov et al.
//! ICIP 2007): the orthonormal opponent colour space, grouping on its luminance, one σ for all
//! three channels (the RMS noise of the stabilised R, G, B).

#![forbid(unsafe_code)]

use super::anscombe::Stabiliser;
use super::bm3d::{bm3d_planes, Bm3dBuffers, Bm3dConfig, FirstChannel};
use crate::cpu::Isa;
use crate::error::{Error, Result};
use crate::filters::{bilinear, box_downsample};
use crate::model::PixelModel;
use crate::progress::{Progress, Silent};
use crate::rgbw::combine_rgbw_jacobian;
use ndarray::{Array2, Array3, ArrayView3, Axis, Zip};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Denoising method of `reconstruct --denoise`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum DenoiseMethod {
    None,
    /// Plain colour BM3D: opponent colour space, equal σ in all channels.
    Bm3d,
    /// Chrominance-focused colour BM3D in the W-weighted YCbCr (paper Fig. 6).
    ChromaBm3d,
}

impl std::str::FromStr for DenoiseMethod {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "none" => Ok(DenoiseMethod::None),
            "bm3d" => Ok(DenoiseMethod::Bm3d),
            "chroma-bm3d" => Ok(DenoiseMethod::ChromaBm3d),
            other => Err(Error::invalid(format!(
                "unknown denoising method '{other}' (available: none, bm3d, chroma-bm3d)"
            ))),
        }
    }
}

impl std::fmt::Display for DenoiseMethod {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            DenoiseMethod::None => "none",
            DenoiseMethod::Bm3d => "bm3d",
            DenoiseMethod::ChromaBm3d => "chroma-bm3d",
        })
    }
}

/// Configuration of the denoising stage.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct DenoiseConfig {
    /// The denoiser: none, plain colour BM3D, or chroma-BM3D (the paper's, the default).
    pub method: DenoiseMethod,
    /// σ of Y (of all channels for plain BM3D) in the stabilised domain, where one binomial
    /// count of the Anscombe trial number has unit σ. Default: from the noise model.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sigma_y: Option<f32>,
    /// σ of Cb and Cr in the stabilised domain. Default: from the noise model.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sigma_c: Option<f32>,
    /// Multiplies the modelled per-pixel σ of Y (of every channel for plain BM3D): 1, as
    /// `noise_correlation_px` models the merge's correlated noise (tuning: docs/tuning.md).
    pub luma_gain: f32,
    /// Multiplies the modelled per-pixel σ of Cb and Cr: the chroma kernels span several sparse
    /// colour sites, so BM3D must remove more than the per-pixel σ says (docs/tuning.md).
    pub chroma_gain: f32,
    /// Spacing exponent of the merge's colour kernels (`merge::AccumulateConfig::
    /// spacing_exponent`) when this denoiser runs: narrower kernels leave the smoothing to
    /// BM3D, which keeps edges (this project's tuning). `None` keeps the merge's own value.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub merge_spacing_exponent: Option<f32>,
    /// Flat-area kernel std (`merge::KernelConfig::k_denoise`, px) of the merge when this
    /// denoiser runs: BM3D removes that noise without wide kernels' blur (this project's
    /// tuning). `None` keeps the merge's own value.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub merge_k_denoise: Option<f32>,
    /// Coarse scales at which chroma is denoised again (0: off; 1: 1/2; 2: 1/2 and 1/4): the
    /// merge's chroma noise is coarse-grained, more than 8×8 blocks see. See
    /// [`bm3d_multiscale`] (this project's heuristic).
    pub chroma_scales: usize,
    /// σ at a coarser scale as a multiple of the σ one scale finer: 0.5 for white noise (a 2×2
    /// mean), up to 1 for noise correlated over more than 2 px.
    pub coarse_sigma_factor: f32,
    /// Filter each BM3D group with the σ of its own pixels from the merge's noise model
    /// ([`model_variance_map`]; the effective frames vary over the image) instead of one σ per
    /// channel. Ignored without a merge noise model.
    pub sigma_map: bool,
    /// Correlation length (px) of the merge's noise for luma and for chroma, which sets
    /// [`Bm3dConfig::noise_correlation_px`]: the merge's kernels correlate its noise, and a
    /// white-noise BM3D over-thresholds detail and leaves blotches (tuning: docs/tuning.md).
    pub noise_correlation_px: [f32; 2],
    /// BM3D's own parameters (its `noise_correlation_px` is set from the field above).
    pub bm3d: Bm3dConfig,
}

impl DenoiseConfig {
    /// Checks the gains (positive) and the given σs (non-negative); the error names the field.
    pub fn validate_sigmas(&self) -> Result<()> {
        for (name, gain) in [
            ("luma_gain", self.luma_gain),
            ("chroma_gain", self.chroma_gain),
        ] {
            if !(gain.is_finite() && gain > 0.0) {
                return Err(Error::invalid(format!(
                    "{name} must be positive, got {gain}"
                )));
            }
        }
        for (name, s) in [("sigma_y", self.sigma_y), ("sigma_c", self.sigma_c)] {
            if let Some(s) = s {
                if !(s.is_finite() && s >= 0.0) {
                    return Err(Error::invalid(format!(
                        "{name} must be a non-negative number, got {s}"
                    )));
                }
            }
        }
        Ok(())
    }

    /// The σ of each stabilised channel BM3D filters with, and where it came from: the
    /// `modelled` σs times the luma and chroma gains (plain BM3D: one σ, the RMS over the
    /// channels of the orthonormal transform, times the luma gain), or `sigma_y` / `sigma_c`
    /// where given.
    fn channel_sigmas(&self, modelled: [f32; 3], source: SigmaSource) -> ([f32; 3], SigmaSource) {
        let mut sigmas = match self.method {
            DenoiseMethod::Bm3d => {
                let rms = (modelled.iter().map(|s| s * s).sum::<f32>() / 3.0).sqrt();
                [rms * self.luma_gain; 3]
            }
            _ => [
                modelled[0] * self.luma_gain,
                modelled[1] * self.chroma_gain,
                modelled[2] * self.chroma_gain,
            ],
        };
        let mut source = source;
        if let Some(sy) = self.sigma_y {
            sigmas[0] = sy;
            if self.method == DenoiseMethod::Bm3d {
                sigmas = [sy; 3];
            }
            source = SigmaSource::Given;
        }
        if let Some(sc) = self.sigma_c {
            if self.method == DenoiseMethod::ChromaBm3d {
                sigmas[1] = sc;
                sigmas[2] = sc;
                source = SigmaSource::Given;
            }
        }
        (sigmas, source)
    }

    /// The BM3D settings the denoiser runs with: `bm3d` with `noise_correlation_px`.
    pub fn bm3d_config(&self) -> Bm3dConfig {
        Bm3dConfig {
            noise_correlation_px: self.noise_correlation_px,
            ..self.bm3d.clone()
        }
    }
}

impl Default for DenoiseConfig {
    fn default() -> Self {
        DenoiseConfig {
            method: DenoiseMethod::ChromaBm3d,
            sigma_y: None,
            sigma_c: None,
            luma_gain: 1.0,
            chroma_gain: 2.0,
            merge_spacing_exponent: Some(0.5),
            merge_k_denoise: Some(0.7),
            chroma_scales: 1,
            coarse_sigma_factor: 0.7,
            sigma_map: true,
            noise_correlation_px: [0.8, 0.4],
            bm3d: Bm3dConfig::default(),
        }
    }
}

/// A 3×3 luma–chroma transform of linear-stabilised R, G, B.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ColorTransform {
    /// Rows map (R, G, B) to the three output channels; channel 0 is the luma used for grouping.
    pub forward: [[f64; 3]; 3],
    pub inverse: [[f64; 3]; 3],
}

impl ColorTransform {
    /// YCbCr with luma weights k = w / Σw from the W weights (supplement Eq. 7–8):
    /// Y = kR·R + kG·G + kB·B, Cb = (B − Y)/(2(1 − kB)), Cr = (R − Y)/(2(1 − kR)).
    pub fn w_weighted_ycbcr(w_weights: [f64; 3]) -> Result<Self> {
        let sum: f64 = w_weights.iter().sum();
        if !w_weights.iter().all(|w| w.is_finite() && *w > 0.0) || sum <= 0.0 {
            return Err(Error::invalid(format!(
                "W weights must be positive and finite, got {w_weights:?}"
            )));
        }
        let [kr, kg, kb] = w_weights.map(|w| w / sum);
        let forward = [
            [kr, kg, kb],
            [-kr / (2.0 * (1.0 - kb)), -kg / (2.0 * (1.0 - kb)), 0.5],
            [0.5, -kg / (2.0 * (1.0 - kr)), -kb / (2.0 * (1.0 - kr))],
        ];
        // R = Y + 2(1 − kR)·Cr, B = Y + 2(1 − kB)·Cb, G = (Y − kR·R − kB·B)/kG.
        let (cr_r, cb_b) = (2.0 * (1.0 - kr), 2.0 * (1.0 - kb));
        let inverse = [
            [1.0, 0.0, cr_r],
            [1.0, -kb * cb_b / kg, -kr * cr_r / kg],
            [1.0, cb_b, 0.0],
        ];
        Ok(ColorTransform { forward, inverse })
    }

    /// The orthonormal opponent colour transform of CBM3D: (R+G+B)/√3, (R−B)/√2, (R−2G+B)/√6.
    pub fn opponent() -> Self {
        let (a, b, c) = (1.0 / 3f64.sqrt(), 1.0 / 2f64.sqrt(), 1.0 / 6f64.sqrt());
        let forward = [[a, a, a], [b, 0.0, -b], [c, -2.0 * c, c]];
        // Orthonormal: the inverse is the transpose.
        let mut inverse = [[0.0; 3]; 3];
        for (i, row) in forward.iter().enumerate() {
            for (j, &v) in row.iter().enumerate() {
                inverse[j][i] = v;
            }
        }
        ColorTransform { forward, inverse }
    }

    fn apply(m: &[[f64; 3]; 3], v: [f64; 3]) -> [f64; 3] {
        m.map(|row| row[0] * v[0] + row[1] * v[1] + row[2] * v[2])
    }
}

/// The merge's noise model (see `merge::MergedPlanes`, with the pixel model of
/// [`DenoiseInput::model`]): per-channel flux and effective number of frames, (4, H, W) in code order R, G, B, W, on the grid of the linear image.
#[derive(Debug, Clone, Copy)]
pub struct MergeNoise<'a> {
    pub flux: ArrayView3<'a, f32>,
    pub effective_frames: ArrayView3<'a, f32>,
}

/// Where the σs came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SigmaSource {
    /// The binomial noise model of the merge.
    BinomialModel,
    /// The Gaussian–Poisson noise model of the merge (multi-bit frames).
    GaussianPoissonModel,
    /// Median absolute deviation of the finest diagonal Haar coefficients (Donoho 1995), used
    /// when no merge noise model exists (e.g. the naive method).
    Estimated,
    /// Given by the user.
    Given,
}

/// What the denoiser did.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DenoiseReport {
    pub method: DenoiseMethod,
    /// Frames n of the Anscombe transform (binomial, or generalized for multi-bit frames).
    pub anscombe_trials: f64,
    /// σ of the three channels of the colour transform, stabilised domain.
    pub sigmas: [f32; 3],
    pub sigma_source: SigmaSource,
}

/// Inputs of [`denoise_linear`] besides the image.
#[derive(Debug, Clone, Copy)]
pub struct DenoiseInput<'a> {
    /// The merge's noise model; `None` estimates σ from the image.
    pub noise: Option<MergeNoise<'a>>,
    /// Frames behind each pixel when `noise` is `None` (sets the Anscombe trials).
    pub frames: f64,
    /// The capture's pixel model (binary with its dark counts, or Gaussian–Poisson).
    pub model: PixelModel,
    pub w_weights: [f64; 3],
}

/// Denoises a linear RGB image (H, W, 3) in detections per frame (paper §4.3): Anscombe
/// transform per channel ([`Stabiliser`]), colour transform, BM3D with grouping on the luma, inverse colour
/// transform, exact unbiased inverse Anscombe, back to flux.
pub fn denoise_linear(
    linear: ArrayView3<f32>,
    input: &DenoiseInput,
    config: &DenoiseConfig,
) -> Result<(Array3<f32>, Option<DenoiseReport>)> {
    denoise_linear_with_progress(linear, input, config, &Silent)
}

/// [`denoise_linear`], reporting to `progress` as the stage "denoise" in pixels of BM3D work
/// (each scale's planes, finest first).
pub fn denoise_linear_with_progress(
    linear: ArrayView3<f32>,
    input: &DenoiseInput,
    config: &DenoiseConfig,
    progress: &dyn Progress,
) -> Result<(Array3<f32>, Option<DenoiseReport>)> {
    let isa = Isa::current();
    crate::cpu::on_pool(|| denoise_on_pool(linear, input, config, isa, progress))
}

fn denoise_on_pool(
    linear: ArrayView3<f32>,
    input: &DenoiseInput,
    config: &DenoiseConfig,
    isa: Isa,
    progress: &dyn Progress,
) -> Result<(Array3<f32>, Option<DenoiseReport>)> {
    let (h, w, c) = linear.dim();
    if c != 3 {
        return Err(Error::invalid(format!(
            "denoising expects an (H, W, 3) image, got {c} channels"
        )));
    }
    let transform = match config.method {
        DenoiseMethod::None => return Ok((linear.to_owned(), None)),
        DenoiseMethod::Bm3d => ColorTransform::opponent(),
        DenoiseMethod::ChromaBm3d => ColorTransform::w_weighted_ycbcr(input.w_weights)?,
    };
    config.validate_sigmas()?;
    let Stabilised {
        stabiliser,
        mut planes,
        sigmas: modelled,
        source,
        relative_variance,
        ..
    } = stabilise(linear, input, transform)?;
    let relative_variance = relative_variance.filter(|_| config.sigma_map);
    let (sigmas, source) = config.channel_sigmas(modelled, source);
    // BM3D's published thresholds are for images on a 0–255 scale: map the luma range there.
    let scale = scale_to_255(planes.index_axis(Axis(0), 0));
    planes.par_mapv_inplace(|v| v * scale);
    let chroma_scales = match config.method {
        DenoiseMethod::ChromaBm3d => config.chroma_scales,
        _ => 0,
    };
    let bm3d = config.bm3d_config();
    progress.start(
        "denoise",
        scale_pixels(h, w, chroma_scales, 4 * bm3d.block_size),
    );
    let mut denoised = multiscale(
        Scale {
            planes: planes.view(),
            sigmas: sigmas.map(|s| s * scale),
            relative_variance: relative_variance.as_ref().map(|v| v.view()),
            scales: chroma_scales,
            first_channel: FirstChannel::Filtered,
        },
        &Multiscale {
            coarse_sigma_factor: config.coarse_sigma_factor,
            config: &bm3d,
            isa,
            progress,
        },
        &mut Bm3dBuffers::default(),
    )?;
    progress.finish();
    denoised.par_mapv_inplace(|v| v / scale);
    Ok((
        unstabilise(denoised.view(), &transform, &stabiliser, (h, w)),
        Some(DenoiseReport {
            method: config.method,
            anscombe_trials: stabiliser.trials(),
            sigmas,
            sigma_source: source,
        }),
    ))
}

/// The factor that maps the range of `plane` onto 0–255 (1 for a constant plane).
fn scale_to_255(plane: ndarray::ArrayView2<f32>) -> f32 {
    let (lo, hi) = plane
        .as_slice()
        .expect("planes in standard layout")
        .par_iter()
        .fold(
            || (f32::INFINITY, f32::NEG_INFINITY),
            |(lo, hi), &v| (lo.min(v), hi.max(v)),
        )
        .reduce(
            || (f32::INFINITY, f32::NEG_INFINITY),
            |(lo, hi), (l, h)| (lo.min(l), hi.max(h)),
        );
    if hi > lo {
        255.0 / (hi - lo)
    } else {
        1.0
    }
}

/// Back from the denoised planes `(3, H, W)` to a linear image `(H, W, 3)`: the inverse colour
/// transform, then the stabiliser's unbiased inverse to flux.
fn unstabilise(
    denoised: ArrayView3<f32>,
    transform: &ColorTransform,
    stabiliser: &Stabiliser,
    (h, w): (usize, usize),
) -> Array3<f32> {
    let mut out = Array3::<f32>::zeros((h, w, 3));
    out.axis_iter_mut(Axis(0))
        .into_par_iter()
        .enumerate()
        .for_each(|(y, mut row)| {
            for x in 0..w {
                let t = [0, 1, 2].map(|ch| denoised[[ch, y, x]] as f64);
                let a = ColorTransform::apply(&transform.inverse, t);
                for ch in 0..3 {
                    row[[x, ch]] = stabiliser.inverse(a[ch]) as f32;
                }
            }
        });
    out
}

/// BM3D of (Y, Cb, Cr) planes with grouping on Y, and the low frequencies of Cb and Cr taken
/// from BM3D at `scales` coarser scales (this project's heuristic, after the multiscale
/// scheme of Lebrun, Colom & Morel, "Multiscale image blind denoising", IEEE TIP 2015): the
/// merge's colour kernels span several of the sparse colour sites, so chroma noise is
/// correlated over more pixels than BM3D's 8×8 blocks see. At each scale the planes are
/// averaged over 2×2 cells, denoised with σ × `coarse_sigma_factor` (recursively), and
/// fine = fine + up(coarse_denoised − down(fine)) for the chroma planes, with `down` the 2×2
/// mean and `up` bilinear interpolation between cell centres. Y keeps its full-scale result.
pub fn bm3d_multiscale(
    planes: ArrayView3<f32>,
    sigmas: [f32; 3],
    relative_variance: Option<ArrayView3<f32>>,
    scales: usize,
    coarse_sigma_factor: f32,
    config: &Bm3dConfig,
) -> Result<Array3<f32>> {
    multiscale(
        Scale {
            planes,
            sigmas,
            relative_variance,
            scales,
            first_channel: FirstChannel::Filtered,
        },
        &Multiscale {
            coarse_sigma_factor,
            config,
            isa: Isa::current(),
            progress: &Silent,
        },
        &mut Bm3dBuffers::default(),
    )
}

/// One scale of [`multiscale`]: its planes, σs and relative variance, the coarser scales
/// still below it, and what it needs of channel 0.
struct Scale<'p, 'v> {
    planes: ArrayView3<'p, f32>,
    sigmas: [f32; 3],
    relative_variance: Option<ArrayView3<'v, f32>>,
    scales: usize,
    first_channel: FirstChannel,
}

/// What every scale of [`multiscale`] shares.
struct Multiscale<'a> {
    coarse_sigma_factor: f32,
    config: &'a Bm3dConfig,
    /// The instruction set, taken once at the entry.
    isa: Isa,
    /// Advanced by each scale's pixels when its BM3D is done.
    progress: &'a dyn Progress,
}

/// Pixels of every scale [`multiscale`] denoises: the full `h` x `w`, then its 2x2 means while
/// `scales` remain and both sides stay at least `min_side` (the units of its progress).
fn scale_pixels(h: usize, w: usize, scales: usize, min_side: usize) -> u64 {
    let (mut h, mut w, mut total) = (h, w, (h * w) as u64);
    for _ in 0..scales {
        if h / 2 < min_side || w / 2 < min_side {
            break;
        }
        (h, w) = (h / 2, w / 2);
        total += (h * w) as u64;
    }
    total
}

/// [`bm3d_multiscale`]; the coarse scales use only their chroma, so their Y is only the
/// grouping guide ([`FirstChannel::GuideOnly`]: the same chroma, less work). Every scale's BM3D
/// works in `buffers`, allocated at the finest.
fn multiscale(scale: Scale, shared: &Multiscale, buffers: &mut Bm3dBuffers) -> Result<Array3<f32>> {
    let Scale {
        planes,
        sigmas,
        relative_variance,
        scales,
        first_channel,
    } = scale;
    let Multiscale {
        coarse_sigma_factor,
        config,
        isa,
        progress,
    } = *shared;
    let mut fine = bm3d_planes(
        planes,
        &sigmas,
        relative_variance,
        config,
        first_channel,
        buffers,
        isa,
    )?;
    let (_, h, w) = planes.dim();
    progress.advance((h * w) as u64);
    let min_side = 4 * config.block_size;
    if scales == 0 || h / 2 < min_side || w / 2 < min_side {
        return Ok(fine);
    }
    if !(coarse_sigma_factor.is_finite() && coarse_sigma_factor > 0.0) {
        return Err(Error::invalid(format!(
            "coarse_sigma_factor must be positive, got {coarse_sigma_factor}"
        )));
    }
    let down = |p: ndarray::ArrayView2<f32>| box_downsample(&p.to_owned(), 2);
    let down3 = |a: ArrayView3<f32>| {
        let coarse: Vec<Array2<f32>> = a.outer_iter().map(down).collect();
        let views: Vec<_> = coarse.iter().map(|p| p.view()).collect();
        ndarray::stack(Axis(0), &views).expect("planes of one shape")
    };
    let coarse = down3(planes);
    let coarse_variance = relative_variance.map(down3);
    let coarse_denoised = multiscale(
        Scale {
            planes: coarse.view(),
            sigmas: sigmas.map(|s| s * coarse_sigma_factor),
            relative_variance: coarse_variance.as_ref().map(|v| v.view()),
            scales: scales - 1,
            first_channel: FirstChannel::GuideOnly,
        },
        shared,
        buffers,
    )?;
    for ch in 1..3 {
        let correction =
            coarse_denoised.index_axis(Axis(0), ch).to_owned() - down(fine.index_axis(Axis(0), ch));
        let mut plane = fine.index_axis_mut(Axis(0), ch);
        plane
            .axis_iter_mut(Axis(0))
            .into_par_iter()
            .enumerate()
            .for_each(|(y, mut row)| {
                // Fine pixel centres in coarse cell coordinates.
                let cy = (y as f32 + 0.5) / 2.0 - 0.5;
                for (x, v) in row.iter_mut().enumerate() {
                    let cx = (x as f32 + 0.5) / 2.0 - 0.5;
                    *v += bilinear(correction.view(), cy, cx);
                }
            });
    }
    Ok(fine)
}

/// A linear image in the stabilised, colour-transformed domain, with its noise σs.
#[derive(Debug, Clone)]
pub struct Stabilised {
    pub stabiliser: Stabiliser,
    pub transform: ColorTransform,
    /// (3, H, W): the transform's channels of A(n·p) per colour channel.
    pub planes: Array3<f32>,
    /// Noise σ of each plane (binomial model, or estimated from the planes without one).
    pub sigmas: [f32; 3],
    pub source: SigmaSource,
    /// (3, H, W) per-pixel noise variance of the binomial model relative to `sigmas`² (clamped
    /// to [1/16, 25]; 1 where the model is undefined); `None` without a model.
    pub relative_variance: Option<Array3<f32>>,
}

/// Stabilises a linear image (H, W, 3): each colour channel's flux by the [`Stabiliser`] of the
/// pixel model (binary: bit rate p = 1 − exp(−(λ + d)), then the binomial Anscombe transform
/// A(n·p); multi-bit: the generalized Anscombe transform) with n from the merge's effective
/// frames, then `transform`. The σs come from the merge's noise model when
/// `input.noise` is given, otherwise from the planes ([`mad_sigma`]).
pub fn stabilise(
    linear: ArrayView3<f32>,
    input: &DenoiseInput,
    transform: ColorTransform,
) -> Result<Stabilised> {
    let (h, w, c) = linear.dim();
    if c != 3 {
        return Err(Error::invalid(format!(
            "denoising expects an (H, W, 3) image, got {c} channels"
        )));
    }
    let trials = match input.noise {
        Some(noise) => {
            check_noise_shape(&noise, h, w)?;
            anscombe_trials(&noise)
        }
        None => input.frames,
    };
    let stabiliser = Stabiliser::new(input.model, trials.max(1.0))?;
    let mut planes = Array3::<f32>::zeros((3, h, w));
    // With a noise model, the stabiliser's derivative at every pixel as well (the delta method
    // of `variance_map`), from the same bit rate as the stabilised value.
    let with_derivative = input.noise.is_some();
    // In parallel by rows of the planes (`rows[y]` holds row y of all three, and of the
    // derivatives).
    let rows: Vec<Vec<([f32; 3], [f64; 3])>> = (0..h)
        .into_par_iter()
        .map(|y| {
            (0..w)
                .map(|x| {
                    let mut da = [0.0; 3];
                    let a = [0, 1, 2].map(|ch| {
                        let v = linear[[y, x, ch]];
                        if !v.is_finite() {
                            // The noise model takes the value as it is (`model_variance_map`).
                            if with_derivative {
                                da[ch] = stabiliser.derivative(v as f64);
                            }
                            return stabiliser.forward(0.0);
                        }
                        if !with_derivative {
                            return stabiliser.forward(v as f64);
                        }
                        let (a, d) = stabiliser.forward_and_derivative(v as f64);
                        da[ch] = d;
                        a
                    });
                    let t = ColorTransform::apply(&transform.forward, a).map(|t| t as f32);
                    (t, da)
                })
                .collect()
        })
        .collect();
    scatter_rows(&mut planes, &rows, |(t, _)| *t);
    let (sigmas, source, relative_variance) = match input.noise {
        Some(noise) => {
            let variance = variance_map(
                &noise,
                stabiliser.model(),
                &transform,
                input.w_weights,
                |y, x| rows[y][x].1,
            );
            let sigmas = median_sigmas(&variance);
            let relative = relative_variance(variance, sigmas);
            let source = if input.model.is_binary() {
                SigmaSource::BinomialModel
            } else {
                SigmaSource::GaussianPoissonModel
            };
            (sigmas, source, Some(relative))
        }
        None => {
            let est = [0, 1, 2].map(|ch| mad_sigma(planes.index_axis(Axis(0), ch)));
            (est, SigmaSource::Estimated, None)
        }
    };
    Ok(Stabilised {
        stabiliser,
        transform,
        planes,
        sigmas,
        source,
        relative_variance,
    })
}

fn check_noise_shape(noise: &MergeNoise, h: usize, w: usize) -> Result<()> {
    for (name, a) in [
        ("flux", noise.flux),
        ("effective_frames", noise.effective_frames),
    ] {
        if a.dim() != (4, h, w) {
            return Err(Error::invalid(format!(
                "noise model {name} has shape {:?}, expected (4, {h}, {w})",
                a.dim()
            )));
        }
    }
    Ok(())
}

/// Trials of the Anscombe transform: the median effective frame count of W (of G without W),
/// so one stabilised unit is the binomial σ of a typical merged luminance sample.
fn anscombe_trials(noise: &MergeNoise) -> f64 {
    let of_channel = |ch: usize| {
        let mut v: Vec<f32> = noise
            .effective_frames
            .index_axis(Axis(0), ch)
            .iter()
            .copied()
            .filter(|n| n.is_finite() && *n > 0.0)
            .collect();
        if v.is_empty() {
            return None;
        }
        Some(upper_median(&mut v, f32::total_cmp) as f64)
    };
    of_channel(3).or_else(|| of_channel(1)).unwrap_or(1.0)
}

/// σ of the three transformed channels: the square root of the median over pixels of a
/// variance map ([`model_variance_map`]).
fn median_sigmas(variances: &Array3<f32>) -> [f32; 3] {
    let sigmas: Vec<f32> = variances
        .outer_iter()
        .into_par_iter()
        .map(|plane| {
            let mut v: Vec<f32> = plane.iter().copied().filter(|v| v.is_finite()).collect();
            if v.is_empty() {
                return 0.0;
            }
            upper_median(&mut v, f32::total_cmp).sqrt()
        })
        .collect();
    [sigmas[0], sigmas[1], sigmas[2]]
}

/// `variance / sigma²` per channel, clamped to [1/16, 25] (σ within a factor 4 below and 5
/// above the channel's σ), 1 where undefined.
fn relative_variance(mut variance: Array3<f32>, sigmas: [f32; 3]) -> Array3<f32> {
    for (ch, mut plane) in variance.outer_iter_mut().enumerate() {
        let s2 = sigmas[ch] * sigmas[ch];
        plane.par_mapv_inplace(|v| {
            if v.is_finite() && s2 > 0.0 {
                (v / s2).clamp(1.0 / 16.0, 25.0)
            } else {
                1.0
            }
        });
    }
    variance
}

/// Per-pixel noise variance (3, H, W) of the three transformed channels from the merge's noise
/// model, by the delta method (Var λ_c of the pixel model, [`PixelModel::flux_variance`]:
/// p_c / ((1 − p_c)·N_c) for the binary MLE of Eq. 6, (λ_c + d + σ_r² + gain²/12)/N_c for
/// Gaussian–Poisson; through Eq. 8, the Anscombe transform and the colour matrix); NaN where the
/// model is undefined.
pub fn model_variance_map(
    linear: &ArrayView3<f32>,
    noise: &MergeNoise,
    stabiliser: &Stabiliser,
    transform: &ColorTransform,
    w_weights: [f64; 3],
) -> Array3<f32> {
    variance_map(noise, stabiliser.model(), transform, w_weights, |y, x| {
        [0, 1, 2].map(|c| stabiliser.derivative(linear[[y, x, c]] as f64))
    })
}

/// [`model_variance_map`] with the stabiliser's derivative ∂a_c/∂λ_c at pixel (y, x) given by
/// `derivative(y, x)` ([`stabilise`] has them from the stabilisation itself).
fn variance_map(
    noise: &MergeNoise,
    model: &PixelModel,
    transform: &ColorTransform,
    w_weights: [f64; 3],
    derivative: impl Fn(usize, usize) -> [f64; 3] + Sync,
) -> Array3<f32> {
    let (_, h, w) = noise.flux.dim();
    let has_w = noise
        .flux
        .index_axis(Axis(0), 3)
        .iter()
        .any(|v| v.is_finite());
    let mut out = Array3::<f32>::from_elem((3, h, w), f32::NAN);
    let delta = DeltaMethod {
        noise,
        model,
        transform,
        w_weights,
        has_w,
    };
    let rows: Vec<Vec<[f32; 3]>> = (0..h)
        .into_par_iter()
        .map(|y| {
            (0..w)
                .map(|x| {
                    pixel_variance(&delta, y, x, || derivative(y, x))
                        .map_or([f32::NAN; 3], |v| v.map(|v| v as f32))
                })
                .collect()
        })
        .collect();
    scatter_rows(&mut out, &rows, |v| *v);
    out
}

/// Writes `rows[y][x]`'s three values (`triple` of it) into `planes[.., y, x]`, (3, H, W), in
/// parallel by rows.
fn scatter_rows<T: Sync>(
    planes: &mut Array3<f32>,
    rows: &[Vec<T>],
    triple: impl Fn(&T) -> [f32; 3] + Sync,
) {
    planes
        .axis_iter_mut(Axis(1))
        .into_par_iter()
        .zip(rows.par_iter())
        .for_each(|(mut plane_row, row)| {
            for (x, value) in row.iter().enumerate() {
                let t = triple(value);
                for ch in 0..3 {
                    plane_row[[ch, x]] = t[ch];
                }
            }
        });
}

/// What [`pixel_variance`] carries through the delta method: the merge's noise model, the
/// pixel model, the colour transform, the W weights of Eq. 8 and whether the image has W.
struct DeltaMethod<'a, 'n> {
    noise: &'a MergeNoise<'n>,
    model: &'a PixelModel,
    transform: &'a ColorTransform,
    w_weights: [f64; 3],
    has_w: bool,
}

/// The variances of [`model_variance_map`] at pixel (y, x); `derivative` gives ∂a_c/∂λ_c there
/// (asked only where the model is defined).
fn pixel_variance(
    delta: &DeltaMethod,
    y: usize,
    x: usize,
    derivative: impl FnOnce() -> [f64; 3],
) -> Option<[f64; 3]> {
    let DeltaMethod {
        noise,
        model,
        transform,
        w_weights,
        has_w,
    } = *delta;
    let lam = [0, 1, 2, 3].map(|c| noise.flux[[c, y, x]] as f64);
    let n = [0, 1, 2, 3].map(|c| noise.effective_frames[[c, y, x]] as f64);
    let channels = if has_w { 4 } else { 3 };
    if (0..channels).any(|c| !lam[c].is_finite() || n[c].is_nan() || n[c] <= 0.0) {
        return None;
    }
    let var_lam = [0, 1, 2, 3].map(|c| {
        if c >= channels {
            return 0.0;
        }
        model.flux_variance(lam[c], n[c])
    });
    // ∂out_c/∂λ_k of Eq. 8.
    let jac = combine_rgbw_jacobian(lam, w_weights, has_w);
    // ∂a_c/∂out_c of the stabilisation a = A(n·p(out)).
    let da = derivative();
    // Rows of the full Jacobian from (λ_R, λ_G, λ_B, λ_W) to the transformed channels.
    let mut var = [0.0; 3];
    for (i, row) in transform.forward.iter().enumerate() {
        for k in 0..4 {
            let d: f64 = (0..3).map(|c| row[c] * da[c] * jac[c][k]).sum();
            var[i] += d * d * var_lam[k];
        }
    }
    Some(var)
}

/// Noise σ of a plane from the median absolute finest diagonal Haar coefficient / 0.6745
/// (Donoho & Johnstone 1994).
pub fn mad_sigma(plane: ndarray::ArrayView2<f32>) -> f32 {
    let (h, w) = plane.dim();
    let mut coeffs = Vec::with_capacity((h / 2) * (w / 2));
    for y in (0..h.saturating_sub(1)).step_by(2) {
        for x in (0..w.saturating_sub(1)).step_by(2) {
            let d = (plane[[y, x]] - plane[[y, x + 1]] - plane[[y + 1, x]] + plane[[y + 1, x + 1]])
                / 2.0;
            if d.is_finite() {
                coeffs.push(d.abs());
            }
        }
    }
    if coeffs.is_empty() {
        return 0.0;
    }
    upper_median(&mut coeffs, f32::total_cmp) / 0.6745
}

/// The element of rank len/2 of a non-empty slice (reorders it).
fn upper_median<T: Copy>(values: &mut [T], cmp: fn(&T, &T) -> std::cmp::Ordering) -> T {
    let mid = values.len() / 2;
    *values.select_nth_unstable_by(mid, cmp).1
}

/// Applies the forward transform to an (H, W, 3) image, giving (3, H, W) planes (for tests and
/// inspection).
pub fn to_planes(image: ArrayView3<f32>, transform: &ColorTransform) -> Array3<f32> {
    let (h, w, _) = image.dim();
    let mut planes = Array3::<f32>::zeros((3, h, w));
    Zip::indexed(image.lanes(Axis(2))).for_each(|(y, x), px| {
        let t = ColorTransform::apply(
            &transform.forward,
            [px[0] as f64, px[1] as f64, px[2] as f64],
        );
        for ch in 0..3 {
            planes[[ch, y, x]] = t[ch] as f32;
        }
    });
    planes
}

#[cfg(test)]
mod tests;
