//! BM3D: block matching and 3D collaborative filtering (Dabov, Foi, Katkovnik, Egiazarian,
//! "Image denoising by sparse 3D transform-domain collaborative filtering", IEEE TIP 16(8), 2007),
//! and its colour variant CBM3D (Dabov et al., "Color image denoising via sparse 3D collaborative
//! filtering with grouping constraint in luminance-chrominance space", ICIP 2007). It is the
//! denoiser of "Seeing Photons in Color" §4.3 / Fig. 6 and supplement §1.5, applied after a
//! variance-stabilising transform.
//!
//! Written from the papers. Both steps of TIP 2007 §III:
//! 1. **Basic estimate** (§III-A, Step 1): for every reference block on a grid of stride
//!    `Nstep`, group the up to `N2^ht` most similar blocks of the noisy image within an
//!    `NS × NS` window (distance ≤ `τ^ht_match`), transform the 3D group, hard-threshold it at
//!    `λ_3D·σ`, invert, and aggregate the block estimates with weight `1/(σ²·N_har)` (`N_har`
//!    = retained coefficients) times a Kaiser window.
//! 2. **Final estimate** (§III-B, Step 2): group again, now matching on the basic estimate
//!    (`N2^wie`, `τ^wie_match`), and shrink the noisy group's 3D spectrum by the empirical
//!    Wiener coefficients `W = |B|² / (|B|² + σ²)` of the basic estimate's group `B`; aggregate
//!    with weight `1/(σ²·‖W‖²)` times the Kaiser window.
//!
//! Choices made here (documented deviations from TIP 2007 Table I):
//! - The 2D block transform is the orthonormal 2D DCT-II in **both** steps (the paper uses a
//!   bior1.5 wavelet in Step 1); the 1D transform along the group is the orthonormal Haar
//!   transform, as in the paper. The group size is the largest power of two not above the
//!   number of matches (capped at `N2`); the reference block is always the group's first member.
//! - Matching distance: squared L2 distance of the 2D-DCT coefficients divided by `N1²`
//!   (paper Eq. 3 / Eq. 6); with `λ_2D = 0` this equals the pixel-domain distance (Parseval).
//!   When σ (on a 0..255 scale) exceeds `high_noise_sigma` (40), the paper's σ > 40 values of
//!   `τ^ht_match` (5000), `λ_3D` (2.8) and `τ^wie_match` (3500) are used, and Step 1 matching
//!   may hard-threshold the coefficients at `λ_2D·σ` first. The paper's λ_2D = 2 is **off** by
//!   default (`lambda_2d = 0`): with the DCT it cost 0.8 dB at σ = 50 against the reference
//!   package (measured, tools/bm3d_crosscheck), while λ_2D = 0 matched or beat it. The block
//!   size stays `N1` (the paper's σ > 40 profile also enlarges blocks; not done here).
//! - Thresholds `τ_match` are per-pixel squared differences on a 0..255 intensity scale, as in
//!   the paper; [`Bm3dConfig::data_range`] says what 255 corresponds to in the caller's units.
//! - The search window is the `NS × NS` window centred on the reference, truncated at borders.
//!
//! Memory: the 2D DCT of every block position of the matching channel (channel 0: noisy in
//! Step 1, basic estimate in Step 2) is computed once per step and stored,
//! `(H−N1+1)·(W−N1+1)·N1²` f32 (about 65 MB for 512×512 and 250 MB for 1000×1000), so
//! matching is a cheap distance on stored coefficients. The other blocks (every channel's but
//! the matching one's, and in Step 2 noisy channel 0's as well, so that one coefficient buffer
//! serves both steps) are transformed when a group takes them ([`BlockSource`]): each
//! position is a group member only about once or twice per step, so that is cheaper than
//! storing every position (the same bits either way).
//! For 8×8 blocks the matching channel's first two coefficient rows are also stored as planes
//! over the positions (a quarter more), so that the first check of a candidate runs on eight
//! positions at once; matching stops summing a candidate once it cannot enter the group
//! ([`find_group`]). Both only skip work: the groups are those of the plain full search.
//!
//! Parallelism and determinism: reference-block rows are processed in parallel with rayon; each
//! row aggregates into its own strip buffer (the rows its search window reaches), and strips are
//! summed into the image in row order afterwards (batches of 16 rows bound the memory), so the result is bit-identical for any thread count.

use crate::cpu;
use crate::error::{Error, Result};
use ndarray::{Array2, Array3, ArrayView2, ArrayView3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::f32::consts::FRAC_1_SQRT_2;

/// Parameters of both BM3D steps. Defaults are the "normal profile" of TIP 2007 Table I
/// (σ ≤ 40), with its σ > 40 values of `τ^ht_match`, `λ_3D` and `τ^wie_match` switched on
/// automatically (but λ_2D = 0, see the module doc).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct Bm3dConfig {
    /// Block side `N1` in pixels (both steps).
    pub block_size: usize,
    /// Stride `Nstep` of the reference-block grid in pixels (both steps); the last row and
    /// column of block positions are always included. TIP 2007 Table I uses 3 (normal profile)
    /// and 5–6 (fast profile). Default 5: chosen with `bench denoise` (step 3 / 4 / 5 / 6 with
    /// the chroma-BM3D defaults) on the tuning set, 29.67 dB / 0.8739 SSIM / 29.67 / 0.8737 /
    /// 29.66 / 0.8733 / 29.62 / 0.8722, confirmed on the validation set (31.61 / 0.8551 at 3,
    /// 31.61 / 0.8549 at 4, 31.60 / 0.8544 at 5), with 0.36 times the reference blocks (and work) of step 3.
    pub step: usize,
    /// Side `NS` of the search window centred on the reference block, in pixels (both steps).
    /// 39 (TIP 2007 Table I, normal profile). Smaller windows were measured with `bench
    /// denoise` (chroma-BM3D defaults, mean PSNR tuning / validation set): 39 gives 29.65 /
    /// 31.62 dB, 33 29.64 / –, 31 29.64 / 31.61, 25 (the fast profile) 29.61 / 31.60 (kodim07
    /// static −0.11 dB, kodim12 object −0.08), and 25 with `max_group_wiener` 16 29.57 / –. On the
    /// 10,000-frame chart of `bench speed` the denoising stage took 0.40 s at 39, 0.38 at 31,
    /// 0.33 at 25 and 0.27 at 25 with groups of 16 (25 in Step 1 alone 0.36–0.38 s, in Step 2
    /// alone 0.35–0.36 s). Kept at 39: the time saved (at most 5 % of the whole pipeline) is
    /// not worth a consistent loss.
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
    /// Correlation length (px) of the noise: the noise is modelled as white noise smoothed by a
    /// Gaussian of this std, so each 2D DCT coefficient gets its own σ (σ_k ∝ |K̂(ω_k)|, with
    /// the mean of σ_k² equal to σ², the per-pixel variance). The first value is for channel 0
    /// (luma, or the grey image), the second for the other channels; 0 = white noise (TIP
    /// 2007). After Mäkinen, Azzari & Foi (TIP 2020, correlated-noise BM3D), with this
    /// project's one-parameter Gaussian model of the merge's kernels instead of a measured PSD.
    /// Chroma-BM3D sets it from `DenoiseConfig::noise_correlation_px` (so a report lists it
    /// there, and here only when not white).
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

/// Greyscale BM3D, both steps (TIP 2007 §III). `sigma` is the noise std in the units of `noisy`;
/// `sigma == 0` returns the input unchanged.
///
/// Errors: negative or non-finite `sigma`, non-finite pixels, an image smaller than a block, or
/// an invalid config.
pub fn bm3d_grey(noisy: ArrayView2<f32>, sigma: f32, config: &Bm3dConfig) -> Result<Array2<f32>> {
    let (h, w) = noisy.dim();
    let planes = noisy
        .to_shape((1, h, w))
        .map_err(|e| Error::invalid(format!("BM3D: cannot view the image as one plane: {e}")))?;
    let out = bm3d_multichannel(planes.view(), &[sigma], config)?;
    Ok(out
        .into_shape_with_order((h, w))
        .expect("one plane of h x w"))
}

/// Multichannel BM3D over planes `(C, H, W)`: block matching on channel 0 only (Step 1 on the
/// noisy channel 0, Step 2 on the basic estimate's channel 0), the same groups used for every
/// channel, each channel filtered with its own σ (hard threshold `λ_3D·σ_c`, Wiener with `σ_c`,
/// aggregation weights with `σ_c`). This is CBM3D's grouping constraint (ICIP 2007 §3) when
/// channel 0 is a luminance. A channel with `σ_c == 0` is returned unchanged.
///
/// Errors: `sigmas.len() != C`, a negative or non-finite σ, non-finite pixels, planes smaller
/// than a block, no channels, or an invalid config.
pub fn bm3d_multichannel(
    noisy: ArrayView3<f32>,
    sigmas: &[f32],
    config: &Bm3dConfig,
) -> Result<Array3<f32>> {
    bm3d_multichannel_varying(noisy, sigmas, None, config)
}

/// [`bm3d_multichannel`] for noise whose variance varies over the image:
/// `relative_variance` (C, H, W) multiplies σ² per pixel (1 = `sigmas`). Each group is filtered
/// with σ_c·√v̄, v̄ the mean relative variance over the group's pixels (threshold of Step 1,
/// Wiener coefficients of Step 2, aggregation weights); matching is unchanged. An extension of
/// TIP 2007 for signal-dependent noise after a variance-stabilising transform whose trials vary
/// per pixel (this project's; cf. the noise-map BM3D variants in the literature).
///
/// Errors: as [`bm3d_multichannel`], and a map of the wrong shape or with a non-finite or
/// non-positive value.
pub fn bm3d_multichannel_varying(
    noisy: ArrayView3<f32>,
    sigmas: &[f32],
    relative_variance: Option<ArrayView3<f32>>,
    config: &Bm3dConfig,
) -> Result<Array3<f32>> {
    bm3d_planes(
        noisy,
        sigmas,
        relative_variance,
        config,
        FirstChannel::Filtered,
        &mut Bm3dBuffers::default(),
    )
}

/// What a caller needs of channel 0, the channel that groups are matched on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum FirstChannel {
    /// Denoised by both steps, as every other channel.
    Filtered,
    /// Only a guide for the other channels' grouping: Step 1 still estimates it (Step 2
    /// matches on that basic estimate), Step 2 does not filter it, and the returned channel 0
    /// is the basic estimate. The other channels are the same as with `Filtered`.
    GuideOnly,
}

/// The large work buffers of [`bm3d_planes`] (the matching channel's block coefficients of both
/// steps, their [`LowPlanes`], the aggregation sums and strips of [`run_step`]), kept between
/// its two steps and between calls (a multiscale run calls it once per scale, finest first), so
/// that each is allocated, and its pages faulted in, once: fresh, they cost thousands of page
/// faults per step (measured with perf). Their contents never carry over: every use
/// overwrites or clears what it reads.
#[derive(Default)]
pub(crate) struct Bm3dBuffers {
    /// The matching channel's coefficients (noisy in Step 1, basic estimate in Step 2).
    coeffs: Vec<f32>,
    low: Vec<f32>,
    num: Vec<f32>,
    den: Vec<f32>,
    strips: Vec<(Vec<f32>, Vec<f32>)>,
}

/// `buffer`'s allocation as a vector of `len` values, zeros where `zeroed` (otherwise only the
/// values beyond its old length are zeros); a fresh allocation when it is too small. The zeros
/// are written by all threads ([`cpu::fill_par`], [`cpu::resize_par`]): these buffers hold up
/// to tens of megabytes, and one thread's fill (a `calloc` of memory the allocator had used
/// before clears it on one thread too) left a core idle for milliseconds at the start of
/// every denoising.
fn recycled(mut buffer: Vec<f32>, len: usize, zeroed: bool) -> Vec<f32> {
    if buffer.capacity() < len {
        buffer = Vec::with_capacity(len);
    }
    buffer.truncate(len);
    if zeroed {
        cpu::fill_par(&mut buffer, 0.0);
    }
    cpu::resize_par(&mut buffer, len, 0.0);
    buffer
}

/// [`bm3d_multichannel_varying`], with channel 0 filtered or only used as the guide, in
/// `buffers`.
pub(crate) fn bm3d_planes(
    noisy: ArrayView3<f32>,
    sigmas: &[f32],
    relative_variance: Option<ArrayView3<f32>>,
    config: &Bm3dConfig,
    first_channel: FirstChannel,
    buffers: &mut Bm3dBuffers,
) -> Result<Array3<f32>> {
    check_inputs(noisy, sigmas, config)?;
    if sigmas.iter().all(|&s| s == 0.0) {
        return Ok(noisy.to_owned());
    }
    let (c, h, w) = noisy.dim();
    let n = config.block_size;
    let tr = Transforms::new(n, config.kaiser_beta);
    let geo = Geometry::new(h, w, n, config);
    let block_variance = block_variances(relative_variance, c, &geo)?;
    let profiles: Vec<Vec<f32>> = (0..c)
        .map(|ch| coefficient_profile(n, config.noise_correlation_px[(ch > 0) as usize]))
        .collect();
    let planes: Vec<Vec<f32>> = noisy
        .outer_iter()
        .map(|p| p.iter().copied().collect())
        .collect();
    let regime = NoiseRegime::of(sigmas[0], config);
    let shared = SharedParams {
        planes: &planes,
        block_variance: block_variance.as_deref(),
        profiles: &profiles,
        geo: &geo,
        tr: &tr,
    };

    let basic = hard_threshold_step(&shared, &regime, sigmas, config, buffers);
    let out = if config.wiener {
        // σ = 0 leaves a channel out of Step 2's filtering (its plane is copied from `basic`).
        let mut step2_sigmas = sigmas.to_vec();
        if first_channel == FirstChannel::GuideOnly {
            step2_sigmas[0] = 0.0;
        }
        wiener_step(&shared, &regime, &step2_sigmas, config, &basic, buffers)
    } else {
        basic
    };
    Ok(to_array(out, h, w))
}

/// The argument checks of [`bm3d_multichannel_varying`] that do not need the geometry.
fn check_inputs(noisy: ArrayView3<f32>, sigmas: &[f32], config: &Bm3dConfig) -> Result<()> {
    config.validate()?;
    let (c, h, w) = noisy.dim();
    if c == 0 {
        return Err(Error::invalid("BM3D: image has no channels"));
    }
    if sigmas.len() != c {
        return Err(Error::invalid(format!(
            "BM3D: {} sigmas given for {c} channels",
            sigmas.len()
        )));
    }
    for (i, &s) in sigmas.iter().enumerate() {
        if !s.is_finite() || s < 0.0 {
            return Err(Error::invalid(format!(
                "BM3D: sigma of channel {i} is {s}; it must be finite and non-negative"
            )));
        }
    }
    let n = config.block_size;
    if h < n || w < n {
        return Err(Error::invalid(format!(
            "BM3D: image {h}x{w} is smaller than the {n}x{n} block"
        )));
    }
    if let Some(v) = noisy.iter().find(|v| !v.is_finite()) {
        return Err(Error::invalid(format!(
            "BM3D: image contains a non-finite pixel ({v})"
        )));
    }
    Ok(())
}

/// Per channel, the mean relative noise variance of every block position (`None` without a
/// map); errors on a map of the wrong shape or with a non-positive or non-finite value.
fn block_variances(
    relative_variance: Option<ArrayView3<f32>>,
    channels: usize,
    geo: &Geometry,
) -> Result<Option<Vec<Vec<f32>>>> {
    let Some(map) = relative_variance else {
        return Ok(None);
    };
    let expected = (channels, geo.h, geo.w);
    if map.dim() != expected {
        return Err(Error::invalid(format!(
            "BM3D: relative variance map has shape {:?}, expected {expected:?}",
            map.dim()
        )));
    }
    if let Some(v) = map.iter().find(|v| !(v.is_finite() && **v > 0.0)) {
        return Err(Error::invalid(format!(
            "BM3D: relative variance map holds {v}; it must be positive and finite"
        )));
    }
    Ok(Some(
        map.outer_iter()
            .into_par_iter()
            .map(|plane| block_means(plane, geo))
            .collect(),
    ))
}

/// The parameters TIP 2007 (Table I) switches when channel 0's σ exceeds `high_noise_sigma`.
struct NoiseRegime {
    high_noise: bool,
    /// `data_range / 255`: the factor from the paper's 0–255 thresholds to image units.
    scale: f32,
}

impl NoiseRegime {
    fn of(sigma0: f32, config: &Bm3dConfig) -> Self {
        let scale = config.data_range / 255.0;
        NoiseRegime {
            high_noise: sigma0 / scale > config.high_noise_sigma,
            scale,
        }
    }

    /// A per-pixel matching threshold as the summed squared distance over an N1×N1 block.
    fn tau_sum(&self, tau: f32, tau_high_noise: f32, n: usize) -> f32 {
        let tau = if self.high_noise { tau_high_noise } else { tau };
        tau * self.scale * self.scale * (n * n) as f32
    }
}

/// What both steps read: the noisy coefficients, noise model and geometry.
struct SharedParams<'a> {
    /// The noisy planes, one per channel.
    planes: &'a [Vec<f32>],
    block_variance: Option<&'a [Vec<f32>]>,
    profiles: &'a [Vec<f32>],
    geo: &'a Geometry,
    tr: &'a Transforms,
}

/// Step 1 (TIP 2007 §III-A): matching on noisy channel 0 (hard-thresholded in 2D when the
/// noise is high), hard thresholding of every group's 3D spectrum; the basic estimate.
fn hard_threshold_step(
    shared: &SharedParams,
    regime: &NoiseRegime,
    sigmas: &[f32],
    config: &Bm3dConfig,
    buffers: &mut Bm3dBuffers,
) -> Vec<Vec<f32>> {
    let noisy_coeffs = BlockCoeffs::compute_in(
        std::mem::take(&mut buffers.coeffs),
        &shared.planes[0],
        shared.geo,
        shared.tr,
    );
    let noisy = block_sources(&noisy_coeffs, shared.planes);
    let thresholded;
    let matching = if regime.high_noise && config.lambda_2d > 0.0 {
        thresholded = noisy_coeffs.hard_thresholded(config.lambda_2d * sigmas[0]);
        &thresholded
    } else {
        &noisy_coeffs
    };
    let low = low_planes_in(std::mem::take(&mut buffers.low), matching, shared.geo);
    let step = StepParams {
        matching,
        low: low.as_ref(),
        tau_sum: regime.tau_sum(
            config.tau_match_ht,
            config.tau_match_ht_high_noise,
            config.block_size,
        ),
        max_group: config.max_group_ht,
        noisy: &noisy,
        basic: None,
        sigmas,
        block_variance: shared.block_variance,
        lambda_3d: if regime.high_noise {
            config.lambda_3d_high_noise
        } else {
            config.lambda_3d
        },
        profiles: shared.profiles,
    };
    let out = run_step(&step, shared.geo, shared.tr, shared.planes, buffers);
    if let Some(low) = low {
        buffers.low = low.planes;
    }
    buffers.coeffs = noisy_coeffs.data;
    out
}

/// Step 2 (TIP 2007 §III-B): matching on the basic estimate's channel 0, empirical Wiener
/// shrinkage of the noisy groups with the basic estimate as the oracle; the final estimate.
/// The basic estimate's coefficients take the buffer of Step 1's noisy ones, so the noisy
/// blocks of every channel are transformed from the planes (the same bits).
fn wiener_step(
    shared: &SharedParams,
    regime: &NoiseRegime,
    sigmas: &[f32],
    config: &Bm3dConfig,
    basic: &[Vec<f32>],
    buffers: &mut Bm3dBuffers,
) -> Vec<Vec<f32>> {
    let basic_coeffs = BlockCoeffs::compute_in(
        std::mem::take(&mut buffers.coeffs),
        &basic[0],
        shared.geo,
        shared.tr,
    );
    let basic_sources = block_sources(&basic_coeffs, basic);
    let noisy: Vec<BlockSource> = shared
        .planes
        .iter()
        .map(|p| BlockSource::Plane(p))
        .collect();
    let low = low_planes_in(std::mem::take(&mut buffers.low), &basic_coeffs, shared.geo);
    let step = StepParams {
        matching: &basic_coeffs,
        low: low.as_ref(),
        tau_sum: regime.tau_sum(
            config.tau_match_wiener,
            config.tau_match_wiener_high_noise,
            config.block_size,
        ),
        max_group: config.max_group_wiener,
        noisy: &noisy,
        basic: Some(&basic_sources),
        sigmas,
        block_variance: shared.block_variance,
        lambda_3d: config.lambda_3d,
        profiles: shared.profiles,
    };
    let out = run_step(&step, shared.geo, shared.tr, basic, buffers);
    if let Some(low) = low {
        buffers.low = low.planes;
    }
    buffers.coeffs = basic_coeffs.data;
    out
}

/// Relative σ of every 2D DCT coefficient (row-major `n × n`) of white noise smoothed by a
/// Gaussian of std `correlation_px`: |K̂(ω_u, ω_v)| = exp(−(ω_u² + ω_v²)·s²/2) at the basis
/// frequencies ω_k = πk/n, scaled so that the mean square is 1 (Parseval: the per-pixel
/// variance is unchanged). All ones for white noise.
fn coefficient_profile(n: usize, correlation_px: f32) -> Vec<f32> {
    let s2 = (correlation_px as f64).powi(2);
    let omega2 = |k: usize| (std::f64::consts::PI * k as f64 / n as f64).powi(2);
    let power: Vec<f64> = (0..n * n)
        .map(|k| (-(omega2(k / n) + omega2(k % n)) * s2).exp())
        .collect();
    let mean = power.iter().sum::<f64>() / power.len() as f64;
    power.iter().map(|p| (p / mean).sqrt() as f32).collect()
}

/// Mean of `plane` over the N1×N1 block at every block position (row-major, `ph·pw`), from a
/// summed-area table.
fn block_means(plane: ArrayView2<f32>, geo: &Geometry) -> Vec<f32> {
    let (h, w, n) = (geo.h, geo.w, geo.n);
    let mut sat = vec![0.0f64; (h + 1) * (w + 1)];
    for y in 0..h {
        let mut row = 0.0f64;
        for x in 0..w {
            row += plane[[y, x]] as f64;
            sat[(y + 1) * (w + 1) + x + 1] = sat[y * (w + 1) + x + 1] + row;
        }
    }
    let area = (n * n) as f64;
    let mut out = Vec::with_capacity(geo.ph * geo.pw);
    for y in 0..geo.ph {
        for x in 0..geo.pw {
            let at = |yy: usize, xx: usize| sat[yy * (w + 1) + xx];
            let sum = at(y + n, x + n) - at(y, x + n) - at(y + n, x) + at(y, x);
            out.push((sum / area) as f32);
        }
    }
    out
}

fn to_array(planes: Vec<Vec<f32>>, h: usize, w: usize) -> Array3<f32> {
    let c = planes.len();
    let flat: Vec<f32> = planes.into_iter().flatten().collect();
    Array3::from_shape_vec((c, h, w), flat).expect("planes of h x w")
}

/// Image and block-grid sizes.
struct Geometry {
    h: usize,
    w: usize,
    n: usize,
    /// Block positions per column / row: `h − n + 1`, `w − n + 1`.
    ph: usize,
    pw: usize,
    /// Reference-block coordinates (stride `Nstep`, last position always included).
    ref_ys: Vec<usize>,
    ref_xs: Vec<usize>,
    half_window: usize,
}

impl Geometry {
    fn new(h: usize, w: usize, n: usize, config: &Bm3dConfig) -> Self {
        let (ph, pw) = (h - n + 1, w - n + 1);
        Geometry {
            h,
            w,
            n,
            ph,
            pw,
            ref_ys: reference_grid(ph, config.step),
            ref_xs: reference_grid(pw, config.step),
            half_window: config.search_window / 2,
        }
    }
}

/// `0, step, 2·step, …` below `positions`, plus the last position `positions − 1`.
fn reference_grid(positions: usize, step: usize) -> Vec<usize> {
    let mut grid: Vec<usize> = (0..positions).step_by(step).collect();
    if *grid.last().expect("at least one position") != positions - 1 {
        grid.push(positions - 1);
    }
    grid
}

/// The 2D DCT-II matrix and the Kaiser aggregation window for `N1 × N1` blocks.
pub(crate) struct Transforms {
    n: usize,
    /// `dct[k·n + i]`: orthonormal DCT-II basis `k` at sample `i`.
    dct: Vec<f32>,
    /// Transpose of `dct`.
    dct_t: Vec<f32>,
    /// Separable 2D Kaiser window, row-major `n × n`.
    kaiser: Vec<f32>,
}

impl Transforms {
    pub(crate) fn new(n: usize, beta: f32) -> Self {
        let mut dct = vec![0.0f32; n * n];
        for k in 0..n {
            let ck = if k == 0 {
                (1.0 / n as f64).sqrt()
            } else {
                (2.0 / n as f64).sqrt()
            };
            for i in 0..n {
                let arg = std::f64::consts::PI * (2 * i + 1) as f64 * k as f64 / (2 * n) as f64;
                dct[k * n + i] = (ck * arg.cos()) as f32;
            }
        }
        let mut dct_t = vec![0.0f32; n * n];
        for k in 0..n {
            for i in 0..n {
                dct_t[i * n + k] = dct[k * n + i];
            }
        }
        let k1 = kaiser_1d(n, beta as f64);
        let kaiser = (0..n * n).map(|i| k1[i / n] * k1[i % n]).collect();
        Transforms {
            n,
            dct,
            dct_t,
            kaiser,
        }
    }

    /// `out = D · block · Dᵀ` (row-major `n × n`); `tmp` is scratch of `n²`.
    #[inline(always)]
    pub(crate) fn forward(&self, block: &[f32], tmp: &mut [f32], out: &mut [f32]) {
        self.sandwich(&self.dct, block, &self.dct_t, tmp, out);
    }

    /// `out = Dᵀ · coeffs · D`, the inverse of [`Transforms::forward`].
    #[inline(always)]
    pub(crate) fn inverse(&self, coeffs: &[f32], tmp: &mut [f32], out: &mut [f32]) {
        self.sandwich(&self.dct_t, coeffs, &self.dct, tmp, out);
    }

    /// `out = left · x · right` for row-major `n × n` matrices: `tmp[r][·] = Σ_i left[r][i] ·
    /// x[i][·]`, then `out[r][·] = Σ_j tmp[r][j] · right[j][·]`, each row accumulated from zero
    /// in index order ([`axpy`]); `tmp` is scratch of `n²`.
    #[inline(always)]
    fn sandwich(&self, left: &[f32], x: &[f32], right: &[f32], tmp: &mut [f32], out: &mut [f32]) {
        let n = self.n;
        if n == 8 {
            // The default block size, with sizes known to the compiler (unrolled and
            // vectorised): the same products summed in the same order.
            let left: &[f32; 64] = left[..64].try_into().expect("8 x 8");
            let right: &[f32; 64] = right[..64].try_into().expect("8 x 8");
            let x: &[f32; 64] = x[..64].try_into().expect("8 x 8 block");
            let out: &mut [f32; 64] = (&mut out[..64]).try_into().expect("8 x 8 block");
            let mut t = [0.0f32; 64];
            matmul8(left, x, &mut t);
            // The second product reads `t` back from memory (see [`matmul8_avx2`]).
            std::hint::black_box(&mut t);
            matmul8(&t, right, out);
            return;
        }
        tmp[..n * n].fill(0.0);
        for r in 0..n {
            let row = &mut tmp[r * n..(r + 1) * n];
            for i in 0..n {
                axpy(row, left[r * n + i], &x[i * n..(i + 1) * n]);
            }
        }
        out[..n * n].fill(0.0);
        for r in 0..n {
            let dst = &mut out[r * n..(r + 1) * n];
            for j in 0..n {
                axpy(dst, tmp[r * n + j], &right[j * n..(j + 1) * n]);
            }
        }
    }
}

/// `out = a · b` for row-major 8 x 8 matrices, each row of `out` accumulated as
/// `0 + a[r][0]·b[0][·] + a[r][1]·b[1][·] + …` (the order of [`axpy`] in the general path),
/// through [`matmul8_avx2`] where the CPU has AVX2 (the same bits).
#[inline(always)]
fn matmul8(a: &[f32; 64], b: &[f32; 64], out: &mut [f32; 64]) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: AVX2 checked just above.
            unsafe { matmul8_avx2(a, b, out) };
            return;
        }
    }
    matmul8_portable(a, b, out)
}

/// [`matmul8`] with every row of `out` one register: `a[r][i]` broadcast from memory times row
/// `i` of `b`, added in order of `i` to a sum that starts at +0 (a multiply, then an add, never
/// fused), which is what each lane of the portable loop does. Written out because the compiler
/// vectorised the portable loop's second product of a 2D transform (`a` the first product's
/// result) across rows, with a transpose's worth of shuffles per product; the transforms
/// also pass the first product through `black_box`, so that its elements are broadcast from
/// memory rather than shuffled out of registers.
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn matmul8_avx2(a: &[f32; 64], b: &[f32; 64], out: &mut [f32; 64]) {
    use std::arch::x86_64::*;
    let rows: [__m256; 8] = std::array::from_fn(|i| _mm256_loadu_ps(b.as_ptr().add(8 * i)));
    for r in 0..8 {
        let mut sum = _mm256_setzero_ps();
        for (i, row) in rows.iter().enumerate() {
            let s = _mm256_broadcast_ss(&a[8 * r + i]);
            sum = _mm256_add_ps(sum, _mm256_mul_ps(s, *row));
        }
        _mm256_storeu_ps(out.as_mut_ptr().add(8 * r), sum);
    }
}

/// [`matmul8`] without SIMD intrinsics.
#[inline(always)]
fn matmul8_portable(a: &[f32; 64], b: &[f32; 64], out: &mut [f32; 64]) {
    for r in 0..8 {
        let mut row = [0.0f32; 8];
        for i in 0..8 {
            let s = a[r * 8 + i];
            for j in 0..8 {
                row[j] += s * b[i * 8 + j];
            }
        }
        out[r * 8..r * 8 + 8].copy_from_slice(&row);
    }
}

#[inline]
fn axpy(dst: &mut [f32], a: f32, x: &[f32]) {
    for (d, &v) in dst.iter_mut().zip(x) {
        *d += a * v;
    }
}

/// Symmetric Kaiser window of length `n`: `I0(β·sqrt(1 − (2i/(n−1) − 1)²)) / I0(β)`.
fn kaiser_1d(n: usize, beta: f64) -> Vec<f32> {
    if n == 1 {
        return vec![1.0];
    }
    let denom = bessel_i0(beta);
    (0..n)
        .map(|i| {
            let r = 2.0 * i as f64 / (n - 1) as f64 - 1.0;
            (bessel_i0(beta * (1.0 - r * r).max(0.0).sqrt()) / denom) as f32
        })
        .collect()
}

/// Modified Bessel function of the first kind, order 0, by its power series.
fn bessel_i0(x: f64) -> f64 {
    let q = x * x / 4.0;
    let (mut term, mut sum) = (1.0f64, 1.0f64);
    for k in 1..200 {
        term *= q / (k * k) as f64;
        sum += term;
        if term < sum * 1e-17 {
            break;
        }
    }
    sum
}

/// 2D DCT coefficients of every `n × n` block position of one plane, row-major over positions.
struct BlockCoeffs {
    n2: usize,
    pw: usize,
    /// Where the coefficients start in `data`: its first 64-byte boundary ([`line_start`]), so
    /// that an 8 × 8 block's 256 bytes are four whole cache lines. From the allocation's own
    /// 16-byte alignment every block spanned five, and matching, which loads a block for every
    /// candidate that passes its first check, waited for a fifth of the lines more (the
    /// prefetch of a block's four lines left its last one out).
    start: usize,
    /// `start` + the coefficients + [`LINE_FLOATS`] of room.
    data: Vec<f32>,
}

/// f32 values per 64-byte cache line.
const LINE_FLOATS: usize = 16;

/// The index of the first 64-byte boundary in `data` (f32 allocations are 4-byte aligned, so it
/// is below [`LINE_FLOATS`]).
fn line_start(data: &[f32]) -> usize {
    let misalignment = data.as_ptr() as usize % 64;
    (64 - misalignment) % 64 / std::mem::size_of::<f32>()
}

impl BlockCoeffs {
    #[cfg(test)]
    fn compute(plane: &[f32], geo: &Geometry, tr: &Transforms) -> Self {
        Self::compute_in(Vec::new(), plane, geo, tr)
    }

    /// [`BlockCoeffs::compute`] in `buffer`'s allocation ([`Bm3dBuffers`]; every value is
    /// overwritten).
    fn compute_in(buffer: Vec<f32>, plane: &[f32], geo: &Geometry, tr: &Transforms) -> Self {
        let (n, n2, pw, w) = (geo.n, geo.n * geo.n, geo.pw, geo.w);
        let len = geo.ph * pw * n2;
        let mut data = recycled(buffer, len + LINE_FLOATS, false);
        let start = line_start(&data);
        data[start..start + len]
            .par_chunks_mut(pw * n2)
            .enumerate()
            .for_each(|(y, row)| {
                #[cfg(target_arch = "x86_64")]
                {
                    if std::arch::is_x86_feature_detected!("avx2") {
                        // SAFETY: the CPU supports AVX2 (checked just above).
                        return unsafe { Self::row_avx2(plane, y, n, w, tr, row) };
                    }
                }
                Self::row(plane, y, n, w, tr, row)
            });
        BlockCoeffs {
            n2,
            pw,
            start,
            data,
        }
    }

    /// The coefficients of the blocks of position row `y` into `row`.
    #[inline(always)]
    fn row(plane: &[f32], y: usize, n: usize, w: usize, tr: &Transforms, row: &mut [f32]) {
        let n2 = n * n;
        if n == 8 {
            // Separably: the column transform D·(rows y..y+8) once for every column, shared by
            // the eight blocks that contain the column, then each block's ·Dᵀ. Every
            // coefficient is the same products summed in the same order as `forward`'s.
            let d: &[f32; 64] = tr.dct[..64].try_into().expect("8 x 8");
            let dt: &[f32; 64] = tr.dct_t[..64].try_into().expect("8 x 8");
            let mut columns = vec![0.0f32; 8 * w];
            for (k, out) in columns.chunks_exact_mut(w).enumerate() {
                for i in 0..8 {
                    let src = &plane[(y + i) * w..(y + i + 1) * w];
                    axpy(out, d[k * 8 + i], src);
                }
            }
            let mut t = [0.0f32; 64];
            for (x, dst) in row.chunks_exact_mut(n2).enumerate() {
                for k in 0..8 {
                    t[k * 8..k * 8 + 8].copy_from_slice(&columns[k * w + x..k * w + x + 8]);
                }
                let dst: &mut [f32; 64] = dst.try_into().expect("8 x 8 block");
                matmul8(&t, dt, dst);
            }
            return;
        }
        let mut block = vec![0.0f32; n2];
        let mut tmp = vec![0.0f32; n2];
        for (x, dst) in row.chunks_exact_mut(n2).enumerate() {
            for i in 0..n {
                let src = &plane[(y + i) * w + x..(y + i) * w + x + n];
                block[i * n..(i + 1) * n].copy_from_slice(src);
            }
            tr.forward(&block, &mut tmp, dst);
        }
    }

    /// [`BlockCoeffs::row`] compiled for AVX2 (no fused multiply-add: the same bits).
    ///
    /// # Safety
    /// The CPU must support AVX2.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn row_avx2(
        plane: &[f32],
        y: usize,
        n: usize,
        w: usize,
        tr: &Transforms,
        row: &mut [f32],
    ) {
        Self::row(plane, y, n, w, tr, row)
    }

    /// A copy with every coefficient of magnitude ≤ `t` set to zero (Step 1 matching, σ > 40).
    fn hard_thresholded(&self, t: f32) -> Self {
        let mut data = vec![0.0f32; self.data.len()];
        let start = line_start(&data);
        let coefficients = self.coefficients();
        data[start..start + coefficients.len()]
            .par_iter_mut()
            .zip(coefficients.par_iter())
            .for_each(|(dst, &v)| *dst = if v.abs() > t { v } else { 0.0 });
        BlockCoeffs {
            n2: self.n2,
            pw: self.pw,
            start,
            data,
        }
    }

    /// Every position's coefficients.
    fn coefficients(&self) -> &[f32] {
        &self.data[self.start..self.start + self.data.len() - LINE_FLOATS]
    }

    #[inline]
    fn block(&self, pos: usize) -> &[f32] {
        let at = self.start + pos * self.n2;
        &self.data[at..at + self.n2]
    }
}

/// Where a step reads the 2D DCT coefficients of a channel's blocks: stored for every
/// position (the step's matching channel, which is read at every position of every search
/// window), or computed from the plane for each group member (the other channels, and noisy
/// channel 0 in Step 2: with the reference grid's stride of 5 and groups of up to 16 / 32, a
/// position is a group member about once or twice per step on average, so storing every
/// position's coefficients, tens of MB per channel, cost more in page faults and cache misses
/// than transforming the members; measured with perf: keeping Step 1's noisy channel 0 for
/// Step 2 cost 14k page faults per call on a 496 × 254 image). Both give the same bits
/// ([`Transforms::forward`] is [`BlockCoeffs`]' transform, test
/// `block_coefficients_are_each_blocks_own_transform_bit_for_bit`).
enum BlockSource<'a> {
    Stored(&'a BlockCoeffs),
    Plane(&'a [f32]),
}

impl BlockSource<'_> {
    /// The coefficients of the block at position `pos` into `out` (`n²`); `pixels` and `tmp`
    /// are scratch of `n²`.
    #[inline(always)]
    fn block_into(
        &self,
        pos: usize,
        geo: &Geometry,
        tr: &Transforms,
        (pixels, tmp): (&mut [f32], &mut [f32]),
        out: &mut [f32],
    ) {
        match self {
            BlockSource::Stored(coeffs) => copy_coefficients(out, coeffs.block(pos)),
            BlockSource::Plane(plane) => {
                let (n, w) = (geo.n, geo.w);
                let (y, x) = (pos / geo.pw, pos % geo.pw);
                if n == 8 {
                    let mut block = [0.0f32; 64];
                    for (i, row) in block.chunks_exact_mut(8).enumerate() {
                        let at = (y + i) * w + x;
                        row.copy_from_slice(&plane[at..at + 8]);
                    }
                    tr.forward(&block, tmp, out);
                    return;
                }
                for i in 0..n {
                    let at = (y + i) * w + x;
                    pixels[i * n..(i + 1) * n].copy_from_slice(&plane[at..at + n]);
                }
                tr.forward(pixels, tmp, out);
            }
        }
    }
}

/// Channel 0 from its stored coefficients, the others from their planes.
fn block_sources<'a>(channel0: &'a BlockCoeffs, planes: &'a [Vec<f32>]) -> Vec<BlockSource<'a>> {
    std::iter::once(BlockSource::Stored(channel0))
        .chain(planes[1..].iter().map(|p| BlockSource::Plane(p)))
        .collect()
}

/// Squared L2 distance with eight partial sums (vectorises; fixed order, so deterministic).
#[cfg(test)]
fn squared_distance(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0.0f32; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for j in 0..8 {
            let d = x[j] - y[j];
            acc[j] += d * d;
        }
    }
    let mut tail = 0.0f32;
    for (x, y) in ra.iter().zip(rb) {
        tail += (x - y) * (x - y);
    }
    acc.iter().sum::<f32>() + tail
}

/// [`squared_distance`] when it is at most `limit`, else `None`, possibly without summing
/// every coefficient: the eight partial sums only grow (non-negative terms, and rounding is
/// monotone), so once their total over the first half of the chunks exceeds `limit`, so does
/// the full distance. Distances at or below `limit` are the same bits as [`squared_distance`].
#[inline(always)]
fn squared_distance_at_most(a: &[f32], b: &[f32], limit: f32) -> Option<f32> {
    let mut acc = [0.0f32; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    let check_after = a.len() / 16;
    for (chunk, (x, y)) in ca.zip(cb).enumerate() {
        if chunk == check_after && check_after > 0 && acc.iter().sum::<f32>() > limit {
            return None;
        }
        for j in 0..8 {
            let d = x[j] - y[j];
            acc[j] += d * d;
        }
    }
    let mut tail = 0.0f32;
    for (x, y) in ra.iter().zip(rb) {
        tail += (x - y) * (x - y);
    }
    let d = acc.iter().sum::<f32>() + tail;
    (d <= limit).then_some(d)
}

/// [`squared_distance_at_most`], with 8 × 8 blocks (64 coefficients, the default) unrolled
/// and checked against `limit` after the first two rows of coefficients as well (the low
/// vertical frequencies, where most of a mismatch shows): the same bits, or `None` under the
/// same condition (a partial sum of non-negative terms, summed over the lanes in the same
/// order as the full one, only grows).
///
/// `two_rows`: the sum after the first two rows when the caller has it already (the
/// [`low_partial_distances`] lane of this candidate: the same bits), so that the check
/// after two rows compares it instead of totalling the lanes again.
#[inline(always)]
fn distance_at_most(a: &[f32], b: &[f32], limit: f32, two_rows: Option<f32>) -> Option<f32> {
    if let (Ok(a), Ok(b)) = (<&[f32; 64]>::try_from(a), <&[f32; 64]>::try_from(b)) {
        let mut acc = [0.0f32; 8];
        for chunk in 0..8 {
            let early = match chunk {
                2 => Some(two_rows.unwrap_or_else(|| acc.iter().sum::<f32>())),
                4 => Some(acc.iter().sum::<f32>()),
                _ => None,
            };
            if early.is_some_and(|e| e > limit) {
                return None;
            }
            for j in 0..8 {
                let d = a[chunk * 8 + j] - b[chunk * 8 + j];
                acc[j] += d * d;
            }
        }
        // `+ 0.0`: the empty tail of the general path.
        let d = acc.iter().sum::<f32>() + 0.0;
        return (d <= limit).then_some(d);
    }
    squared_distance_at_most(a, b, limit)
}

/// Coefficients per block in [`LowPlanes`]: the first two rows of an 8 × 8 block's DCT.
const LOW_COEFFS: usize = 16;

/// `planes[(y·LOW_COEFFS + k)·stride + x]`: coefficient k < [`LOW_COEFFS`] of the block at
/// position (y, x) (`stride` = positions per row + 8, the padding zero), so that eight
/// consecutive positions of a row are read as lanes.
struct LowPlanes {
    planes: Vec<f32>,
    stride: usize,
}

/// The [`LowPlanes`] of `coeffs` for 8 × 8 blocks, `None` for other sizes.
#[cfg(test)]
fn low_planes(coeffs: &BlockCoeffs, geo: &Geometry) -> Option<LowPlanes> {
    low_planes_in(Vec::new(), coeffs, geo)
}

/// [`low_planes`] in `buffer`'s allocation ([`Bm3dBuffers`]).
fn low_planes_in(buffer: Vec<f32>, coeffs: &BlockCoeffs, geo: &Geometry) -> Option<LowPlanes> {
    if coeffs.n2 != 64 {
        return None;
    }
    let pw = geo.pw;
    let stride = pw + LANES8;
    let mut planes = recycled(buffer, geo.ph * LOW_COEFFS * stride, false);
    planes
        .par_chunks_mut(LOW_COEFFS * stride)
        .zip(coeffs.coefficients().par_chunks(pw * 64))
        .for_each(|(rows, blocks)| {
            for (x, block) in blocks.chunks_exact(64).enumerate() {
                for (k, &v) in block[..LOW_COEFFS].iter().enumerate() {
                    rows[k * stride + x] = v;
                }
            }
            // The padding (a recycled buffer holds old values there).
            for row in rows.chunks_exact_mut(stride) {
                row[pw..].fill(0.0);
            }
        });
    Some(LowPlanes { planes, stride })
}

/// Lanes of the first matching check (eight f32: one AVX2 register).
const LANES8: usize = 8;

/// For the eight block positions (y, x..x + 8), the partial distance to `reference` that
/// [`distance_at_most`] compares with its limit after two rows of coefficients: per lane,
/// `acc[j] = (r[j] − c[j])² + (r[j+8] − c[j+8])²`, summed over j in order. The same operations
/// on the same values, so the same bits, with the positions as vector lanes.
#[inline(always)]
fn low_partial_distances(low: &LowPlanes, reference: &[f32], y: usize, x: usize) -> [f32; LANES8] {
    let mut sum = [0.0f32; LANES8];
    let row = y * LOW_COEFFS * low.stride + x;
    for j in 0..8 {
        let at = row + j * low.stride;
        let c0: &[f32; LANES8] = low.planes[at..at + LANES8].try_into().expect("lanes");
        let at = row + (j + 8) * low.stride;
        let c1: &[f32; LANES8] = low.planes[at..at + LANES8].try_into().expect("lanes");
        let (r0, r1) = (reference[j], reference[j + 8]);
        for l in 0..LANES8 {
            let d0 = r0 - c0[l];
            let d1 = r1 - c1[l];
            let acc = d0 * d0 + d1 * d1;
            sum[l] = if j == 0 { acc } else { sum[l] + acc };
        }
    }
    sum
}

/// The first check of [`find_group`] for the eight block positions (y, x..x + 8): a mask of
/// the lanes whose [`low_partial_distances`] are at most `bound` (bit l for position x + l),
/// and those partials; through [`low_check_avx2`] when `AVX2`.
///
/// The first row of coefficients is checked before the second: per lane, Σ_j (r[j] − c[j])²
/// summed over j in order is the same sum with smaller terms (each lane's two-row term is the
/// one-row square plus a non-negative one, and rounding is monotone), so it is at most the
/// two-row partial, which is at most the full distance. When no lane passes it, the chunk is
/// done after eight coefficients instead of sixteen (mask 0; the partials are then unused
/// zeros). The mask is the same either way.
#[inline(always)]
fn low_check<const AVX2: bool>(
    low: &LowPlanes,
    reference: &[f32],
    y: usize,
    x: usize,
    bound: f32,
) -> (u32, [f32; LANES8]) {
    #[cfg(target_arch = "x86_64")]
    {
        if AVX2 {
            // SAFETY: `AVX2` is only true under `process_row_avx2`, whose caller checked the CPU.
            return unsafe { low_check_avx2(low, reference, y, x, bound) };
        }
    }
    let row = y * LOW_COEFFS * low.stride + x;
    let mut first = [0.0f32; LANES8];
    for (j, &r) in reference[..8].iter().enumerate() {
        let at = row + j * low.stride;
        let c0: &[f32; LANES8] = low.planes[at..at + LANES8].try_into().expect("lanes");
        for l in 0..LANES8 {
            let d0 = r - c0[l];
            first[l] = if j == 0 { d0 * d0 } else { first[l] + d0 * d0 };
        }
    }
    if !first.iter().any(|&f| f <= bound) {
        return (0, [0.0; LANES8]);
    }
    let partial = low_partial_distances(low, reference, y, x);
    let mut mask = 0u32;
    for (l, &part) in partial.iter().enumerate() {
        mask |= ((part <= bound) as u32) << l;
    }
    (mask, partial)
}

/// [`low_check`] in AVX2 registers: the eight positions are the eight lanes of one register,
/// and every lane does the subtractions, products and sums of [`low_partial_distances`] in the
/// same order (no fused multiply-add), so the same bits; the first row's squares are kept for
/// the second row's sums, and each mask is one vector comparison (`≤`, false for NaN as the
/// portable `<=`). (The compiler did not vectorise the portable version well: it split the
/// lanes into 4 + 1 + 1 + 2.)
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn low_check_avx2(
    low: &LowPlanes,
    reference: &[f32],
    y: usize,
    x: usize,
    bound: f32,
) -> (u32, [f32; LANES8]) {
    use std::arch::x86_64::*;
    let stride = low.stride;
    let row = y * LOW_COEFFS * stride + x;
    // Every load below stays inside (`low.planes` is padded by eight lanes per row).
    assert!(
        reference.len() >= LOW_COEFFS
            && row + (LOW_COEFFS - 1) * stride + LANES8 <= low.planes.len()
    );
    let base = low.planes.as_ptr().add(row);
    let limit = _mm256_set1_ps(bound);
    let mut squares = [_mm256_setzero_ps(); 8];
    let mut first = _mm256_setzero_ps();
    for (j, square) in squares.iter_mut().enumerate() {
        let d0 = _mm256_sub_ps(
            _mm256_set1_ps(reference[j]),
            _mm256_loadu_ps(base.add(j * stride)),
        );
        *square = _mm256_mul_ps(d0, d0);
        first = if j == 0 {
            *square
        } else {
            _mm256_add_ps(first, *square)
        };
    }
    if _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_LE_OQ>(first, limit)) == 0 {
        return (0, [0.0; LANES8]);
    }
    let mut sum = _mm256_setzero_ps();
    for (j, &square) in squares.iter().enumerate() {
        let d1 = _mm256_sub_ps(
            _mm256_set1_ps(reference[j + 8]),
            _mm256_loadu_ps(base.add((j + 8) * stride)),
        );
        let acc = _mm256_add_ps(square, _mm256_mul_ps(d1, d1));
        sum = if j == 0 { acc } else { _mm256_add_ps(sum, acc) };
    }
    let mask = _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_LE_OQ>(sum, limit)) as u32;
    let mut out = [0.0f32; LANES8];
    _mm256_storeu_ps(out.as_mut_ptr(), sum);
    (mask, out)
}

/// What differs between the two steps.
struct StepParams<'a> {
    /// Coefficients that matching compares (channel 0 of noisy or basic estimate).
    matching: &'a BlockCoeffs,
    /// The first [`LOW_COEFFS`] of `matching`'s coefficients as planes over the block
    /// positions ([`low_planes`]; 8 × 8 blocks only): the first check of [`find_group`].
    low: Option<&'a LowPlanes>,
    /// Matching threshold on the summed squared coefficient distance (τ·N1², image units).
    tau_sum: f32,
    max_group: usize,
    /// Noisy coefficients per channel.
    noisy: &'a [BlockSource<'a>],
    /// Basic-estimate coefficients per channel: `Some` selects Step 2 (Wiener).
    basic: Option<&'a [BlockSource<'a>]>,
    sigmas: &'a [f32],
    /// Per channel, the mean relative noise variance of every block position (`None`: 1).
    block_variance: Option<&'a [Vec<f32>]>,
    lambda_3d: f32,
    /// Per channel, the relative σ of every 2D coefficient ([`coefficient_profile`]).
    profiles: &'a [Vec<f32>],
}

/// Per-worker buffers, allocated once per rayon job split, reused for every group.
struct Scratch {
    candidates: Vec<(f32, u32)>,
    group: Vec<usize>,
    /// The group of the last reference block this worker grouped (a search bound for the
    /// next, see [`find_group`]; never changes a result).
    previous_group: Vec<usize>,
    /// Distances of `previous_group`'s members to the current reference.
    warm: Vec<f32>,
    /// The positions (and two-row partial distances) that passed [`find_group`]'s first check
    /// in the window row checked last, whose blocks are being prefetched, and in the row
    /// being checked now.
    pending: Vec<(u32, f32)>,
    checked: Vec<(u32, f32)>,
    noisy_group: Vec<f32>,
    basic_group: Vec<f32>,
    haar_tmp: Vec<f32>,
    tmp: Vec<f32>,
    pixels: Vec<f32>,
}

impl Scratch {
    fn new(n2: usize, max_group: usize) -> Self {
        Scratch {
            candidates: Vec::new(),
            group: Vec::with_capacity(max_group),
            previous_group: Vec::with_capacity(max_group),
            warm: Vec::with_capacity(max_group),
            pending: Vec::new(),
            checked: Vec::new(),
            noisy_group: vec![0.0; max_group * n2],
            basic_group: vec![0.0; max_group * n2],
            haar_tmp: vec![0.0; max_group * n2],
            tmp: vec![0.0; n2],
            pixels: vec![0.0; n2],
        }
    }
}

/// Numerator and denominator of the aggregation for image rows `y0..y0+rows`, every channel.
struct Strip<'b> {
    y0: usize,
    rows: usize,
    num: &'b mut [f32],
    den: &'b mut [f32],
}

/// One BM3D step over the whole image; returns one plane per channel. Channels with σ = 0 are
/// copied from `planes`.
fn run_step(
    p: &StepParams,
    geo: &Geometry,
    tr: &Transforms,
    planes: &[Vec<f32>],
    work: &mut Bm3dBuffers,
) -> Vec<Vec<f32>> {
    let (h, w, n) = (geo.h, geo.w, geo.n);
    let n2 = n * n;
    let channels = planes.len();
    let mut num = recycled(std::mem::take(&mut work.num), channels * h * w, true);
    let mut den = recycled(std::mem::take(&mut work.den), channels * h * w, true);
    // Reference rows in batches of equal size, so that at most `MAX_ROWS_PER_BATCH` strips live
    // at once; their buffers are made once (or kept from the last step, `work`) and cleared for
    // every batch (fresh ones cost page faults). Each batch ends when its slowest row does, so
    // batches are few and alike (one short last batch left a thread idle).
    const MAX_ROWS_PER_BATCH: usize = 32;
    let rows_per_batch = cpu::balanced_chunk_len(geo.ref_ys.len(), MAX_ROWS_PER_BATCH);
    let strip_rows = (2 * geo.half_window + n).min(h);
    let mut buffers = std::mem::take(&mut work.strips);
    buffers.resize_with(rows_per_batch, Default::default);
    for (num, den) in &mut buffers {
        let len = channels * strip_rows * w;
        *num = recycled(std::mem::take(num), len, false);
        *den = recycled(std::mem::take(den), len, false);
    }
    // Group members lie within the search window's rows.
    let strip_of = |yr: usize| {
        let y0 = yr.saturating_sub(geo.half_window);
        (y0, (yr + geo.half_window + n).min(h) - y0)
    };
    for batch in geo.ref_ys.chunks(rows_per_batch) {
        batch.par_iter().zip(buffers.par_iter_mut()).for_each_init(
            || Scratch::new(n2, p.max_group),
            |scratch, (&yr, (num, den))| {
                let (y0, rows) = strip_of(yr);
                let len = channels * rows * w;
                num[..len].fill(0.0);
                den[..len].fill(0.0);
                let mut strip = Strip {
                    y0,
                    rows,
                    num: &mut num[..len],
                    den: &mut den[..len],
                };
                process_row(p, geo, tr, yr, scratch, &mut strip);
            },
        );
        // Sum the strips in reference-row order: the same float additions for any thread count.
        // Image rows are independent, so they are split among the threads; each row still adds
        // the strips that cover it in reference-row order.
        let strips: Vec<(usize, usize)> = batch.iter().map(|&yr| strip_of(yr)).collect();
        let add_rows = |acc: &mut [f32], first: usize, numerator: bool| {
            for (k, dst) in acc.chunks_exact_mut(w).enumerate() {
                let (c, y) = ((first + k) / h, (first + k) % h);
                for (&(y0, rows), buffer) in strips.iter().zip(&buffers) {
                    if (y0..y0 + rows).contains(&y) {
                        let strip = if numerator { &buffer.0 } else { &buffer.1 };
                        let src = &strip[(c * rows + y - y0) * w..][..w];
                        for (d, s) in dst.iter_mut().zip(src) {
                            *d += s;
                        }
                    }
                }
            }
        };
        const SUM_ROWS: usize = 16;
        num.par_chunks_mut(SUM_ROWS * w)
            .zip(den.par_chunks_mut(SUM_ROWS * w))
            .enumerate()
            .for_each(|(i, (num, den))| {
                add_rows(num, i * SUM_ROWS, true);
                add_rows(den, i * SUM_ROWS, false);
            });
    }
    let out = (0..channels)
        .map(|c| {
            if p.sigmas[c] == 0.0 {
                return planes[c].clone();
            }
            let plane = c * h * w..(c + 1) * h * w;
            num[plane.clone()]
                .iter()
                .zip(&den[plane])
                .map(|(&a, &b)| a / b)
                .collect()
        })
        .collect();
    (work.num, work.den, work.strips) = (num, den, buffers);
    out
}

/// Every reference block of row `yr` ([`process_reference`]), with AVX2 where the CPU has it.
///
/// The AVX2 build of the same code is bit-identical: the kernels' sums are laid out lane by lane
/// in a fixed order (eight partial sums, rows of eight), wider registers only hold more lanes,
/// and no multiply-add is fused.
fn process_row(
    p: &StepParams,
    geo: &Geometry,
    tr: &Transforms,
    yr: usize,
    s: &mut Scratch,
    strip: &mut Strip<'_>,
) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2 (checked just above).
            unsafe { process_row_avx2(p, geo, tr, yr, s, strip) };
            return;
        }
    }
    process_row_generic::<false>(p, geo, tr, yr, s, strip);
}

/// The reference blocks of row `yr`; `AVX2` selects the explicit AVX2 kernels
/// ([`low_check_avx2`], [`hard_threshold_avx2`], [`wiener_shrink_avx2`]), which
/// give the same bits as the portable ones.
#[inline(always)]
fn process_row_generic<const AVX2: bool>(
    p: &StepParams,
    geo: &Geometry,
    tr: &Transforms,
    yr: usize,
    s: &mut Scratch,
    strip: &mut Strip<'_>,
) {
    for &xr in &geo.ref_xs {
        process_reference::<AVX2>(p, geo, tr, yr, xr, s, strip);
    }
}

/// [`process_row_generic`] compiled for AVX2.
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn process_row_avx2(
    p: &StepParams,
    geo: &Geometry,
    tr: &Transforms,
    yr: usize,
    s: &mut Scratch,
    strip: &mut Strip<'_>,
) {
    // `true`: this function is the AVX2 build, and its callers checked the CPU.
    process_row_generic::<true>(p, geo, tr, yr, s, strip);
}

/// Groups the blocks similar to reference `(yr, xr)`, filters the group in every channel with
/// σ > 0, and aggregates the block estimates into `strip`.
#[inline(always)]
fn process_reference<const AVX2: bool>(
    p: &StepParams,
    geo: &Geometry,
    tr: &Transforms,
    yr: usize,
    xr: usize,
    s: &mut Scratch,
    strip: &mut Strip<'_>,
) {
    let n = geo.n;
    let n2 = n * n;
    find_group::<AVX2>(p, geo, yr, xr, s);
    let m = s.group.len();
    let w = geo.w;
    let channels = p.noisy.len();

    for c in 0..channels {
        let mut sigma = p.sigmas[c];
        if sigma == 0.0 {
            continue;
        }
        if let Some(variance) = p.block_variance {
            let mean: f32 = s.group.iter().map(|&pos| variance[c][pos]).sum::<f32>() / m as f32;
            sigma *= mean.sqrt();
        }
        for (g, &pos) in s.group.iter().enumerate() {
            p.noisy[c].block_into(
                pos,
                geo,
                tr,
                (&mut s.pixels, &mut s.tmp),
                &mut s.noisy_group[g * n2..(g + 1) * n2],
            );
        }
        let group = &mut s.noisy_group[..m * n2];
        let profile = &p.profiles[c];
        let weight = match p.basic {
            None => {
                // Step 1: hard thresholding of the 3D spectrum (TIP 2007 §III-A, Eq. 5) and
                // weight 1/(σ²·N_har) (Eq. 10).
                // With correlated noise each 2D coefficient k has its own σ·profile[k], and
                // N_har becomes the retained coefficients' summed relative variance.
                let threshold = p.lambda_3d * sigma;
                let retained = filter_group::<AVX2, false>(
                    group,
                    &mut [],
                    m,
                    profile,
                    threshold,
                    &mut s.haar_tmp,
                );
                if retained > 0.0 {
                    1.0 / (sigma * sigma * retained)
                } else {
                    1.0
                }
            }
            Some(basic) => {
                // Step 2: empirical Wiener shrinkage W = |B|²/(|B|² + σ²) (§III-B, Eq. 7–8) and
                // weight 1/(σ²·‖W‖²) (Eq. 12).
                for (g, &pos) in s.group.iter().enumerate() {
                    basic[c].block_into(
                        pos,
                        geo,
                        tr,
                        (&mut s.pixels, &mut s.tmp),
                        &mut s.basic_group[g * n2..(g + 1) * n2],
                    );
                }
                let bgroup = &mut s.basic_group[..m * n2];
                let s2 = sigma * sigma;
                let w_norm =
                    filter_group::<AVX2, true>(group, bgroup, m, profile, s2, &mut s.haar_tmp);
                if w_norm > 0.0 {
                    1.0 / (s2 * w_norm)
                } else {
                    1.0 / s2
                }
            }
        };

        // Aggregation with the Kaiser window (§III-A.3 / §III-B.3; Table I, β = 2).
        let len = strip.rows * w;
        let num = &mut strip.num[c * len..(c + 1) * len];
        let den = &mut strip.den[c * len..(c + 1) * len];
        for (g, &pos) in s.group.iter().enumerate() {
            let (by, bx) = (pos / geo.pw, pos % geo.pw);
            tr.inverse(&group[g * n2..(g + 1) * n2], &mut s.tmp, &mut s.pixels);
            for i in 0..n {
                let row = (by + i - strip.y0) * w + bx;
                let kai = &tr.kaiser[i * n..(i + 1) * n];
                let px = &s.pixels[i * n..(i + 1) * n];
                let (num, den) = (&mut num[row..row + n], &mut den[row..row + n]);
                if n == 8 {
                    // Fixed length: unrolled and vectorised.
                    let num: &mut [f32; 8] = num.try_into().expect("8 wide");
                    let den: &mut [f32; 8] = den.try_into().expect("8 wide");
                    let kai: &[f32; 8] = kai.try_into().expect("8 wide");
                    let px: &[f32; 8] = px.try_into().expect("8 wide");
                    aggregate_row8(num, den, kai, px, weight);
                } else {
                    aggregate_row(num, den, kai, px, weight);
                }
            }
        }
    }
}

/// The collaborative filtering of a group in its blocks' 2D spectra (`m` stacked blocks of
/// `profile.len()` coefficients): the 1D Haar transform along the group, the shrinkage of the
/// 3D spectrum, hard thresholding at `param`·q ([`hard_threshold`]) or, when `WIENER`, the
/// empirical Wiener shrinkage with noise variance `param` and the basic estimate's group
/// `basic` in the same 2D spectra ([`wiener_shrink`]; `basic` is overwritten), and the inverse
/// Haar transform. Returns the shrinkage's sum (N_har or ‖W‖²). `tmp`: scratch of the group's
/// size.
///
/// For 8 × 8 blocks in groups of up to [`MAX_LANE_GROUP`] (the defaults) all three run on
/// eight coefficients of every member at a time ([`filter_group_lanes`]) instead of three
/// passes over the group: the same operations on the same values, and the shrinkage's terms
/// summed in the same order, so the same bits.
#[inline(always)]
fn filter_group<const AVX2: bool, const WIENER: bool>(
    group: &mut [f32],
    basic: &mut [f32],
    m: usize,
    profile: &[f32],
    param: f32,
    tmp: &mut [f32],
) -> f32 {
    if let Ok(profile) = <&[f32; 64]>::try_from(profile) {
        // Sizes known to the compiler, as in `haar_lanes` (called directly: a closure here was
        // compiled on its own, without AVX2 and out of line).
        let (g, b, q, t) = (&mut *group, &*basic, profile, &mut *tmp);
        match m {
            1 => return filter_group_sized::<WIENER, 1>(g, b, q, param, t),
            2 => return filter_group_sized::<WIENER, 2>(g, b, q, param, t),
            4 => return filter_group_sized::<WIENER, 4>(g, b, q, param, t),
            8 => return filter_group_sized::<WIENER, 8>(g, b, q, param, t),
            16 => return filter_group_sized::<WIENER, 16>(g, b, q, param, t),
            32 => return filter_group_sized::<WIENER, 32>(g, b, q, param, t),
            _ => {}
        }
    }
    let n2 = profile.len();
    haar_forward(group, m, n2, tmp);
    let total = if WIENER {
        haar_forward(basic, m, n2, tmp);
        wiener_shrink_dispatch::<AVX2>(group, basic, profile, param)
    } else {
        hard_threshold_dispatch::<AVX2>(group, profile, param)
    };
    haar_inverse(group, m, n2, tmp);
    total
}

/// [`filter_group_lanes`] of `M` blocks.
#[inline(always)]
fn filter_group_sized<const WIENER: bool, const M: usize>(
    group: &mut [f32],
    basic: &[f32],
    profile: &[f32; 64],
    param: f32,
    terms: &mut [f32],
) -> f32 {
    let basic_rows = if WIENER { M * 64 } else { 0 };
    filter_group_lanes::<WIENER>(
        &mut group[..M * 64],
        &basic[..basic_rows],
        M,
        profile,
        param,
        &mut terms[..M * 64],
    )
}

/// [`filter_group`] of `m` ≤ [`MAX_LANE_GROUP`] blocks of 64 coefficients, eight
/// coefficients of every member at a time (as [`haar_lanes`]): their Haar transform, their
/// shrinkage (the formulas of [`hard_threshold`] / [`wiener_shrink`], lane by lane), and the
/// inverse transform, held in stack arrays between the three. Each coefficient's term of the
/// shrinkage's sum goes to `terms` (`m·64`, the group's layout), which is summed afterwards
/// in the order of the separate pass (member by member, lane `l` taking coefficients `l`
/// mod 8), so the sum has the same bits too.
#[inline(always)]
fn filter_group_lanes<const WIENER: bool>(
    group: &mut [f32],
    basic: &[f32],
    m: usize,
    profile: &[f32; 64],
    param: f32,
    terms: &mut [f32],
) -> f32 {
    let (mut x, mut y) = ([[0.0f32; 8]; MAX_LANE_GROUP], [[0.0f32; 8]; MAX_LANE_GROUP]);
    let (mut bx, mut by) = ([[0.0f32; 8]; MAX_LANE_GROUP], [[0.0f32; 8]; MAX_LANE_GROUP]);
    let mut work = [[[0.0f32; 8]; MAX_LANE_GROUP]; 2];
    for chunk in 0..8 {
        let lanes = chunk * 8..chunk * 8 + 8;
        for (x, row) in x[..m].iter_mut().zip(group.chunks_exact(64)) {
            *x = row[lanes.clone()].try_into().expect("eight lanes");
        }
        haar_forward_lanes(&mut x, &mut y, &mut work[0], m);
        if WIENER {
            for (x, row) in bx[..m].iter_mut().zip(basic.chunks_exact(64)) {
                *x = row[lanes.clone()].try_into().expect("eight lanes");
            }
            haar_forward_lanes(&mut bx, &mut by, &mut work[0], m);
        }
        let q: &[f32; 8] = profile[lanes.clone()].try_into().expect("eight lanes");
        for ((v, b), row) in y[..m].iter_mut().zip(&by).zip(terms.chunks_exact_mut(64)) {
            let term: &mut [f32; 8] = (&mut row[lanes.clone()]).try_into().expect("eight lanes");
            for l in 0..8 {
                if WIENER {
                    let (b2, q2) = (b[l] * b[l], q[l] * q[l]);
                    let wc = b2 / (b2 + param * q2);
                    v[l] *= wc;
                    term[l] = wc * wc * q2;
                } else {
                    let keep = v[l].abs() > param * q[l];
                    v[l] = if keep { v[l] } else { 0.0 };
                    term[l] = if keep { q[l] * q[l] } else { 0.0 };
                }
            }
        }
        haar_inverse_lanes(&mut y, &mut x, &mut work, m);
        for (x, row) in x[..m].iter().zip(group.chunks_exact_mut(64)) {
            row[lanes.clone()].copy_from_slice(x);
        }
    }
    let mut sum = [0.0f32; SHRINK_LANES];
    for term in terms.chunks_exact(SHRINK_LANES) {
        for l in 0..SHRINK_LANES {
            sum[l] += term[l];
        }
    }
    lane_total(sum)
}

/// Lanes of the sums in [`hard_threshold`] and [`wiener_shrink`]: coefficient i of a group row
/// adds into lane i mod 8, and the lanes are added in order at the end (independent sums that
/// vectorise; the same result on every CPU).
const SHRINK_LANES: usize = 8;

/// Sum of the lanes of a [`SHRINK_LANES`] accumulator, in lane order.
#[inline(always)]
fn lane_total(lanes: [f32; SHRINK_LANES]) -> f32 {
    lanes.iter().sum()
}

/// Zeroes the coefficients of `group` (rows of `profile.len()`) with |v| ≤ `threshold`·q (q the
/// coefficient's relative σ in `profile`) and returns the retained coefficients' Σ q² (N_har,
/// TIP 2007 Eq. 10, with correlated noise).
#[inline(always)]
fn hard_threshold(group: &mut [f32], profile: &[f32], threshold: f32) -> f32 {
    let mut lanes = [0.0f32; SHRINK_LANES];
    let shrink = |v: &mut f32, q: f32, lane: &mut f32| {
        if v.abs() > threshold * q {
            *lane += q * q;
        } else {
            *v = 0.0;
        }
    };
    for row in group.chunks_exact_mut(profile.len()) {
        let whole = row.len() - row.len() % SHRINK_LANES;
        let (row_head, row_tail) = row.split_at_mut(whole);
        let (q_head, q_tail) = profile.split_at(whole);
        for (v, q) in row_head
            .chunks_exact_mut(SHRINK_LANES)
            .zip(q_head.chunks_exact(SHRINK_LANES))
        {
            let v: &mut [f32; SHRINK_LANES] = v.try_into().expect("lane chunk");
            let q: &[f32; SHRINK_LANES] = q.try_into().expect("lane chunk");
            for l in 0..SHRINK_LANES {
                let keep = v[l].abs() > threshold * q[l];
                v[l] = if keep { v[l] } else { 0.0 };
                lanes[l] += if keep { q[l] * q[l] } else { 0.0 };
            }
        }
        for (l, (v, &q)) in row_tail.iter_mut().zip(q_tail).enumerate() {
            shrink(v, q, &mut lanes[l]);
        }
    }
    lane_total(lanes)
}

/// [`hard_threshold`], through [`hard_threshold_avx2`] when `AVX2` and the rows are whole
/// lane chunks.
#[inline(always)]
fn hard_threshold_dispatch<const AVX2: bool>(
    group: &mut [f32],
    profile: &[f32],
    threshold: f32,
) -> f32 {
    #[cfg(target_arch = "x86_64")]
    {
        let rem = profile.len() % SHRINK_LANES; // not is_multiple_of: rust-version is 1.80
        if AVX2 && rem == 0 {
            // SAFETY: `AVX2` is only true under `process_row_avx2`, whose caller checked the CPU.
            return unsafe { hard_threshold_avx2(group, profile, threshold) };
        }
    }
    hard_threshold(group, profile, threshold)
}

/// [`hard_threshold`] for rows of whole lane chunks, lane `l` of [`SHRINK_LANES`] in lane `l`
/// of an AVX2 register: the same comparison, the same products added in the same order (a
/// zeroed coefficient adds `+0.0`, as in the portable version), so the same bits.
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn hard_threshold_avx2(group: &mut [f32], profile: &[f32], threshold: f32) -> f32 {
    use std::arch::x86_64::*;
    let n2 = profile.len();
    let (rem, rows_rem) = (n2 % SHRINK_LANES, group.len() % n2.max(1)); // rust-version 1.80
    assert!(rem == 0 && rows_rem == 0);
    let t = _mm256_set1_ps(threshold);
    let abs_mask = _mm256_castsi256_ps(_mm256_set1_epi32(0x7fff_ffff));
    let mut lanes = _mm256_setzero_ps();
    for row in group.chunks_exact_mut(n2) {
        for k in (0..n2).step_by(SHRINK_LANES) {
            let v = _mm256_loadu_ps(row.as_ptr().add(k));
            let q = _mm256_loadu_ps(profile.as_ptr().add(k));
            let keep = _mm256_cmp_ps::<_CMP_GT_OQ>(_mm256_and_ps(v, abs_mask), _mm256_mul_ps(t, q));
            _mm256_storeu_ps(row.as_mut_ptr().add(k), _mm256_and_ps(v, keep));
            lanes = _mm256_add_ps(lanes, _mm256_and_ps(_mm256_mul_ps(q, q), keep));
        }
    }
    let mut out = [0.0f32; SHRINK_LANES];
    _mm256_storeu_ps(out.as_mut_ptr(), lanes);
    lane_total(out)
}

/// [`wiener_shrink`], through [`wiener_shrink_avx2`] when `AVX2` and the rows are whole lane
/// chunks.
#[inline(always)]
fn wiener_shrink_dispatch<const AVX2: bool>(
    group: &mut [f32],
    basic: &[f32],
    profile: &[f32],
    s2: f32,
) -> f32 {
    #[cfg(target_arch = "x86_64")]
    {
        let rem = profile.len() % SHRINK_LANES; // not is_multiple_of: rust-version is 1.80
        if AVX2 && rem == 0 {
            // SAFETY: `AVX2` is only true under `process_row_avx2`, whose caller checked the CPU.
            return unsafe { wiener_shrink_avx2(group, basic, profile, s2) };
        }
    }
    wiener_shrink(group, basic, profile, s2)
}

/// [`wiener_shrink`] for rows of whole lane chunks in AVX2 registers: the same operations in
/// the same order per lane (IEEE division, no fused multiply-add), so the same bits.
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn wiener_shrink_avx2(group: &mut [f32], basic: &[f32], profile: &[f32], s2: f32) -> f32 {
    use std::arch::x86_64::*;
    let n2 = profile.len();
    let (rem, rows_rem) = (n2 % SHRINK_LANES, group.len() % n2.max(1)); // rust-version 1.80
    assert!(rem == 0 && rows_rem == 0 && basic.len() >= group.len());
    let s2v = _mm256_set1_ps(s2);
    let mut lanes = _mm256_setzero_ps();
    for (r, row) in group.chunks_exact_mut(n2).enumerate() {
        let brow = basic.as_ptr().add(r * n2);
        for k in (0..n2).step_by(SHRINK_LANES) {
            let v = _mm256_loadu_ps(row.as_ptr().add(k));
            let b = _mm256_loadu_ps(brow.add(k));
            let q = _mm256_loadu_ps(profile.as_ptr().add(k));
            let b2 = _mm256_mul_ps(b, b);
            let q2 = _mm256_mul_ps(q, q);
            let wc = _mm256_div_ps(b2, _mm256_add_ps(b2, _mm256_mul_ps(s2v, q2)));
            _mm256_storeu_ps(row.as_mut_ptr().add(k), _mm256_mul_ps(v, wc));
            lanes = _mm256_add_ps(lanes, _mm256_mul_ps(_mm256_mul_ps(wc, wc), q2));
        }
    }
    let mut out = [0.0f32; SHRINK_LANES];
    _mm256_storeu_ps(out.as_mut_ptr(), lanes);
    lane_total(out)
}

/// Empirical Wiener shrinkage of `group` (rows of `profile.len()`) with the basic estimate's
/// spectrum `basic`: v ·= W, W = B²/(B² + σ²q²) (TIP 2007 Eq. 7–8, each coefficient's own
/// σ·q); returns Σ W²q² (‖W‖² of Eq. 12, with correlated noise).
#[inline(always)]
fn wiener_shrink(group: &mut [f32], basic: &[f32], profile: &[f32], s2: f32) -> f32 {
    let mut lanes = [0.0f32; SHRINK_LANES];
    let shrink = |v: &mut f32, b: f32, q: f32, lane: &mut f32| {
        let (b2, q2) = (b * b, q * q);
        let wc = b2 / (b2 + s2 * q2);
        *v *= wc;
        *lane += wc * wc * q2;
    };
    let n2 = profile.len();
    for (row, brow) in group.chunks_exact_mut(n2).zip(basic.chunks_exact(n2)) {
        let whole = n2 - n2 % SHRINK_LANES;
        let (row_head, row_tail) = row.split_at_mut(whole);
        let (b_head, b_tail) = brow.split_at(whole);
        let (q_head, q_tail) = profile.split_at(whole);
        for ((v, b), q) in row_head
            .chunks_exact_mut(SHRINK_LANES)
            .zip(b_head.chunks_exact(SHRINK_LANES))
            .zip(q_head.chunks_exact(SHRINK_LANES))
        {
            let v: &mut [f32; SHRINK_LANES] = v.try_into().expect("lane chunk");
            let b: &[f32; SHRINK_LANES] = b.try_into().expect("lane chunk");
            let q: &[f32; SHRINK_LANES] = q.try_into().expect("lane chunk");
            let b2: [f32; SHRINK_LANES] = std::array::from_fn(|l| b[l] * b[l]);
            let q2: [f32; SHRINK_LANES] = std::array::from_fn(|l| q[l] * q[l]);
            let wc: [f32; SHRINK_LANES] = std::array::from_fn(|l| b2[l] / (b2[l] + s2 * q2[l]));
            for l in 0..SHRINK_LANES {
                v[l] *= wc[l];
                lanes[l] += wc[l] * wc[l] * q2[l];
            }
        }
        for (l, ((v, &b), &q)) in row_tail.iter_mut().zip(b_tail).zip(q_tail).enumerate() {
            shrink(v, b, q, &mut lanes[l]);
        }
    }
    lane_total(lanes)
}

/// `num += weight·kai·px`, `den += weight·kai` along one block row (aggregation, TIP 2007
/// Eq. 10 / Eq. 12).
#[inline(always)]
fn aggregate_row(num: &mut [f32], den: &mut [f32], kai: &[f32], px: &[f32], weight: f32) {
    for (((num, den), &k), &v) in num.iter_mut().zip(den.iter_mut()).zip(kai).zip(px) {
        let wk = weight * k;
        *num += wk * v;
        *den += wk;
    }
}

/// [`aggregate_row`] of an 8-pixel row, through local copies so that it compiles to a few
/// vector instructions: the same operations, so the same bits.
#[inline(always)]
fn aggregate_row8(
    num: &mut [f32; 8],
    den: &mut [f32; 8],
    kai: &[f32; 8],
    px: &[f32; 8],
    weight: f32,
) {
    let (mut n8, mut d8) = (*num, *den);
    for j in 0..8 {
        let wk = weight * kai[j];
        n8[j] += wk * px[j];
        d8[j] += wk;
    }
    *num = n8;
    *den = d8;
}

/// `dst.copy_from_slice(src)`, as a fixed-size copy for 8 × 8 blocks (no call to `memcpy`).
#[inline(always)]
fn copy_coefficients(dst: &mut [f32], src: &[f32]) {
    match (
        <&mut [f32; 64]>::try_from(&mut *dst),
        <&[f32; 64]>::try_from(src),
    ) {
        (Ok(d), Ok(s)) => *d = *s,
        _ => dst.copy_from_slice(src),
    }
}

/// Fills `s.group` with the reference position followed by its best matches (distance ≤ τ,
/// ascending distance, ties by position), truncated to a power of two ≤ `max_group`.
///
/// Only the best `max_group − 1` matches can enter the group, so a candidate farther than the
/// `(max_group − 1)`-th best distance known so far need not be summed to the end: the scan
/// keeps that bound (from the previous reference's group members, which mostly lie in this
/// window too, and then from the matches found), and [`distance_at_most`] stops once a
/// partial sum exceeds it. The bound is always the distance of an actual candidate, so every
/// candidate the group can take is still summed in full: the group is the one of a full scan
/// (the test `bounded_search_finds_the_full_search_group` compares them).
#[inline(always)]
fn find_group<const AVX2: bool>(
    p: &StepParams,
    geo: &Geometry,
    yr: usize,
    xr: usize,
    s: &mut Scratch,
) {
    let hw = geo.half_window;
    let pw = geo.pw;
    let ref_pos = yr * pw + xr;
    let reference = p.matching.block(ref_pos);
    s.candidates.clear();
    let (y0, y1) = (yr.saturating_sub(hw), (yr + hw).min(geo.ph - 1));
    let (x0, x1) = (xr.saturating_sub(hw), (xr + hw).min(pw - 1));
    let order = |a: &(f32, u32), b: &(f32, u32)| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1));
    let keep = p.max_group - 1;
    s.group.clear();
    s.group.push(ref_pos);
    if keep == 0 {
        return;
    }
    // Bound from the previous reference's group: the keep-th smallest of its members'
    // distances to this reference, when enough of them lie in this window.
    let mut bound = p.tau_sum;
    let in_window = |pos: usize| {
        let (y, x) = (pos / pw, pos % pw);
        pos != ref_pos && (y0..=y1).contains(&y) && (x0..=x1).contains(&x)
    };
    s.warm.clear();
    for &pos in &s.previous_group {
        if in_window(pos) {
            if let Some(d) =
                distance_at_most_dispatch::<AVX2>(reference, p.matching.block(pos), bound, None)
            {
                s.warm.push(d);
            }
        }
    }
    if s.warm.len() >= keep {
        s.warm.select_nth_unstable_by(keep - 1, f32::total_cmp);
        bound = bound.min(s.warm[keep - 1]);
    }
    // Every position of the window; the list is cut back to the best `keep` (and the bound
    // lowered to the last of them) whenever it reaches `cap`.
    let cap = 2 * keep.max(8);
    let consider =
        |pos: usize, two_rows: Option<f32>, bound: &mut f32, candidates: &mut Vec<(f32, u32)>| {
            consider_candidate::<AVX2>(
                reference, p.matching, pos, two_rows, bound, candidates, keep, cap,
            );
        };
    // Rows from the reference's out: its best matches usually lie near it, so the bound falls
    // early and fewer candidates are summed in full (any order gives the same group).
    match p.low {
        Some(low) => {
            // Each row's first check runs before the candidates of the row checked before it
            // are summed, so that their blocks' prefetches have a row's work to arrive (summed
            // right after their own row's check, the first load of each stalled: about 10 % of
            // the step's time, perf). The check then uses an older bound, which lets more
            // lanes pass, but `consider` compares every one's two-row partial with the
            // current bound first: the same candidates join in the same order.
            s.pending.clear();
            for y in centre_out(yr, y0, y1) {
                s.checked.clear();
                // Eight positions at a time through the first check (the tail's extra lanes
                // read the next positions or the padding and are not used).
                let mut x = x0;
                while x <= x1 {
                    // Lanes that pass the check, as bits.
                    let (mut pass, partial) = low_check::<AVX2>(low, reference, y, x, bound);
                    pass &= (1u32 << (x1 + 1 - x).min(LANES8)) - 1;
                    if AVX2 {
                        prefetch_blocks(p.matching, y * pw + x, pass);
                    }
                    while pass != 0 {
                        let lane = pass.trailing_zeros() as usize;
                        let pos = y * pw + x + lane;
                        pass &= pass - 1;
                        if pos != ref_pos {
                            // The lane's partial is the candidate's sum after two rows.
                            s.checked.push((pos as u32, partial[lane]));
                        }
                    }
                    x += LANES8;
                }
                for &(pos, two_rows) in &s.pending {
                    consider(pos as usize, Some(two_rows), &mut bound, &mut s.candidates);
                }
                std::mem::swap(&mut s.pending, &mut s.checked);
            }
            for &(pos, two_rows) in &s.pending {
                consider(pos as usize, Some(two_rows), &mut bound, &mut s.candidates);
            }
        }
        None => {
            for y in centre_out(yr, y0, y1) {
                for x in x0..=x1 {
                    let pos = y * pw + x;
                    if pos != ref_pos {
                        consider(pos, None, &mut bound, &mut s.candidates);
                    }
                }
            }
        }
    }
    if s.candidates.len() > keep {
        s.candidates.select_nth_unstable_by(keep - 1, order);
        s.candidates.truncate(keep);
    }
    s.candidates.sort_unstable_by(order);
    let size = prev_power_of_two(1 + s.candidates.len()).min(prev_power_of_two(p.max_group));
    s.group.extend(
        s.candidates[..size - 1]
            .iter()
            .map(|&(_, pos)| pos as usize),
    );
    s.previous_group.clear();
    s.previous_group.extend_from_slice(&s.group);
}

/// `y0..=y1` (which holds `centre`) in the order `centre, centre + 1, centre − 1, centre + 2,
/// …`, then the rest of the longer side.
fn centre_out(centre: usize, y0: usize, y1: usize) -> impl Iterator<Item = usize> {
    let below = (centre + 1..=y1).map(Some).chain(std::iter::repeat(None));
    let above = (y0..centre).rev().map(Some).chain(std::iter::repeat(None));
    std::iter::once(centre).chain(
        below
            .zip(above)
            .take_while(|(b, a)| b.is_some() || a.is_some())
            .flat_map(|(b, a)| b.into_iter().chain(a)),
    )
}

/// Asks the CPU to start loading the coefficients of the positions `first + l` for every bit
/// `l` of `lanes` (all of them before any is summed, so that their cache misses overlap). A
/// hint only: no result depends on it.
#[inline(always)]
fn prefetch_blocks(coeffs: &BlockCoeffs, first: usize, lanes: u32) {
    let mut bits = lanes;
    while bits != 0 {
        let pos = first + bits.trailing_zeros() as usize;
        bits &= bits - 1;
        crate::cpu::prefetch(coeffs.block(pos));
    }
}

/// One candidate of [`find_group`]'s scan: its distance to `reference` when at most `bound`
/// joins `candidates`, which are cut back to the best `keep` (and `bound` lowered to the last
/// of them) whenever they reach `cap`. A function rather than a closure, so that it is inlined
/// into the AVX2 build (the closure was compiled on its own, without AVX2). `two_rows`: the
/// candidate's distance after two rows when known ([`distance_at_most`]).
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn consider_candidate<const AVX2: bool>(
    reference: &[f32],
    matching: &BlockCoeffs,
    pos: usize,
    two_rows: Option<f32>,
    bound: &mut f32,
    candidates: &mut Vec<(f32, u32)>,
    keep: usize,
    cap: usize,
) {
    let block = matching.block(pos);
    if let Some(d) = distance_at_most_dispatch::<AVX2>(reference, block, *bound, two_rows) {
        candidates.push((d, pos as u32));
        if candidates.len() == cap {
            *bound = cut_candidates(candidates, keep);
        }
    }
}

/// Keeps the best `keep` of `candidates` (ascending distance, ties by position: the order of
/// [`find_group`]) and returns the last one's distance.
#[inline(never)]
fn cut_candidates(candidates: &mut Vec<(f32, u32)>, keep: usize) -> f32 {
    let order = |a: &(f32, u32), b: &(f32, u32)| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1));
    candidates.select_nth_unstable_by(keep - 1, order);
    candidates.truncate(keep);
    candidates[keep - 1].0
}

/// [`distance_at_most`], through [`distance_at_most_avx2`] when `AVX2` and the blocks are
/// 8 × 8.
#[inline(always)]
fn distance_at_most_dispatch<const AVX2: bool>(
    a: &[f32],
    b: &[f32],
    limit: f32,
    two_rows: Option<f32>,
) -> Option<f32> {
    #[cfg(target_arch = "x86_64")]
    {
        if AVX2 {
            if let (Ok(a), Ok(b)) = (<&[f32; 64]>::try_from(a), <&[f32; 64]>::try_from(b)) {
                // SAFETY: `AVX2` is only true under `process_row_avx2`, whose caller checked
                // the CPU.
                return unsafe { distance_at_most_avx2(a, b, limit, two_rows) };
            }
        }
    }
    distance_at_most(a, b, limit, two_rows)
}

/// [`distance_at_most`] of 8 × 8 blocks with its eight partial sums as the lanes of one AVX2
/// register: the same differences, squares and sums in the same order, and the lanes totalled
/// by the same in-order sum, so the same bits and the same early exits.
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn distance_at_most_avx2(
    a: &[f32; 64],
    b: &[f32; 64],
    limit: f32,
    two_rows: Option<f32>,
) -> Option<f32> {
    use std::arch::x86_64::*;
    let total = |acc: __m256| {
        let mut lanes = [0.0f32; 8];
        _mm256_storeu_ps(lanes.as_mut_ptr(), acc);
        lanes.iter().sum::<f32>()
    };
    let mut acc = _mm256_setzero_ps();
    for chunk in 0..8 {
        let early = match chunk {
            2 => Some(two_rows.unwrap_or_else(|| total(acc))),
            4 => Some(total(acc)),
            _ => None,
        };
        if early.is_some_and(|e| e > limit) {
            return None;
        }
        let d = _mm256_sub_ps(
            _mm256_loadu_ps(a.as_ptr().add(chunk * 8)),
            _mm256_loadu_ps(b.as_ptr().add(chunk * 8)),
        );
        acc = _mm256_add_ps(acc, _mm256_mul_ps(d, d));
    }
    // `+ 0.0`: as in `distance_at_most`.
    let d = total(acc) + 0.0;
    (d <= limit).then_some(d)
}

/// Largest power of two ≤ `k` (`k ≥ 1`).
fn prev_power_of_two(k: usize) -> usize {
    1 << (usize::BITS - 1 - k.leading_zeros())
}

/// Orthonormal 1D Haar transform along the group (full decomposition) of `m` (a power of two)
/// stacked `n2`-coefficient blocks: `g[b·n2 + k]`. Output order: approximation, then details
/// from coarse to fine.
#[inline(always)]
pub(crate) fn haar_forward(g: &mut [f32], m: usize, n2: usize, tmp: &mut [f32]) {
    let rem = n2 % 8; // not is_multiple_of: rust-version is 1.80
    if rem == 0 && m <= MAX_LANE_GROUP {
        haar_lanes::<true>(g, m, n2);
    } else {
        haar_forward_general(g, m, n2, tmp);
    }
}

/// [`haar_forward`] level by level over whole blocks (any `n2` and `m`).
#[inline(always)]
fn haar_forward_general(g: &mut [f32], m: usize, n2: usize, tmp: &mut [f32]) {
    let mut len = m;
    while len > 1 {
        let half = len / 2;
        for i in 0..half {
            for k in 0..n2 {
                let a = g[2 * i * n2 + k];
                let b = g[(2 * i + 1) * n2 + k];
                tmp[i * n2 + k] = (a + b) * FRAC_1_SQRT_2;
                tmp[(half + i) * n2 + k] = (a - b) * FRAC_1_SQRT_2;
            }
        }
        g[..len * n2].copy_from_slice(&tmp[..len * n2]);
        len = half;
    }
}

/// Inverse of [`haar_forward`].
#[inline(always)]
pub(crate) fn haar_inverse(g: &mut [f32], m: usize, n2: usize, tmp: &mut [f32]) {
    let rem = n2 % 8; // not is_multiple_of: rust-version is 1.80
    if rem == 0 && m <= MAX_LANE_GROUP {
        haar_lanes::<false>(g, m, n2);
    } else {
        haar_inverse_general(g, m, n2, tmp);
    }
}

/// [`haar_inverse`] level by level over whole blocks (any `n2` and `m`).
#[inline(always)]
fn haar_inverse_general(g: &mut [f32], m: usize, n2: usize, tmp: &mut [f32]) {
    let mut len = 2;
    while len <= m {
        let half = len / 2;
        for i in 0..half {
            for k in 0..n2 {
                let a = g[i * n2 + k];
                let d = g[(half + i) * n2 + k];
                tmp[2 * i * n2 + k] = (a + d) * FRAC_1_SQRT_2;
                tmp[(2 * i + 1) * n2 + k] = (a - d) * FRAC_1_SQRT_2;
            }
        }
        g[..len * n2].copy_from_slice(&tmp[..len * n2]);
        len *= 2;
    }
}

/// Largest group that [`haar_lanes`] transforms on the stack.
const MAX_LANE_GROUP: usize = 32;

/// Eight lanes of every group member (`[[f32; 8]; MAX_LANE_GROUP]`, first `m` rows used).
type Lanes = [[f32; 8]; MAX_LANE_GROUP];

/// Eight coefficients of every group member at a time, held in stack arrays while the
/// transform ([`haar_forward_lanes`] when `FORWARD`, else [`haar_inverse_lanes`]) runs all
/// levels on them: the same operations on the same values as the general path of
/// [`haar_forward`] / [`haar_inverse`] (so the same bits), without copying the whole group back
/// after every level.
///
/// The transforms are called directly, not passed as functions: passed as a value, the
/// transform was compiled on its own (through `Fn::call`, without AVX2 and out of line) and
/// took 8 % of the denoiser's time (perf); called directly it is inlined into the AVX2 build.
/// The work arrays are made once per call, not once per eight coefficients (every row a
/// transform reads was written by it first, so their contents never matter).
///
/// For 8 × 8 blocks (`n2` = 64) and every group size up to [`MAX_LANE_GROUP`], the sizes are
/// passed as constants to [`haar_lanes_sized`] (inlined), so that the compiler unrolls the
/// levels and drops the bounds checks of the copies in and out (they took about half of the
/// transform's time, perf); the same operations, so the same bits.
#[inline(always)]
fn haar_lanes<const FORWARD: bool>(g: &mut [f32], m: usize, n2: usize) {
    if n2 == 64 {
        match m {
            1 => return haar_lanes_sized::<FORWARD>(&mut g[..64], 1, 64),
            2 => return haar_lanes_sized::<FORWARD>(&mut g[..2 * 64], 2, 64),
            4 => return haar_lanes_sized::<FORWARD>(&mut g[..4 * 64], 4, 64),
            8 => return haar_lanes_sized::<FORWARD>(&mut g[..8 * 64], 8, 64),
            16 => return haar_lanes_sized::<FORWARD>(&mut g[..16 * 64], 16, 64),
            32 => return haar_lanes_sized::<FORWARD>(&mut g[..32 * 64], 32, 64),
            _ => {}
        }
    }
    haar_lanes_sized::<FORWARD>(g, m, n2);
}

/// The body of [`haar_lanes`], for `m` blocks of `n2` coefficients.
#[inline(always)]
fn haar_lanes_sized<const FORWARD: bool>(g: &mut [f32], m: usize, n2: usize) {
    let (mut x, mut y) = ([[0.0f32; 8]; MAX_LANE_GROUP], [[0.0f32; 8]; MAX_LANE_GROUP]);
    let mut work = [[[0.0f32; 8]; MAX_LANE_GROUP]; 2];
    for chunk in 0..n2 / 8 {
        let lanes = chunk * 8..chunk * 8 + 8;
        for (x, row) in x[..m].iter_mut().zip(g.chunks_exact(n2)) {
            *x = row[lanes.clone()].try_into().expect("eight lanes");
        }
        if FORWARD {
            haar_forward_lanes(&mut x, &mut y, &mut work[0], m);
        } else {
            haar_inverse_lanes(&mut x, &mut y, &mut work, m);
        }
        for (y, row) in y[..m].iter().zip(g.chunks_exact_mut(n2)) {
            row[lanes.clone()].copy_from_slice(y);
        }
    }
}

/// [`haar_forward`] of the lanes `x` into `y` (`x` is overwritten): each level's details go
/// straight to their place in `y`, its approximation to the other of `x` and `work`.
#[inline(always)]
fn haar_forward_lanes(x: &mut Lanes, y: &mut Lanes, work: &mut Lanes, m: usize) {
    let (mut src, mut dst) = (x, work);
    let mut len = m;
    while len > 1 {
        let half = len / 2;
        for i in 0..half {
            // Whole rows into locals first: no store can alias a load, so it vectorises.
            let (a, b) = (src[2 * i], src[2 * i + 1]);
            dst[i] = std::array::from_fn(|k| (a[k] + b[k]) * FRAC_1_SQRT_2);
            y[half + i] = std::array::from_fn(|k| (a[k] - b[k]) * FRAC_1_SQRT_2);
        }
        std::mem::swap(&mut src, &mut dst);
        len = half;
    }
    y[0] = src[0];
}

/// [`haar_inverse`] of the lanes `x` into `y`: each level reads the approximation of the
/// level before (at first `x[0]`) and its details in `x`, and writes to the other of the two
/// `work` arrays; the last level writes `y`.
#[inline(always)]
fn haar_inverse_lanes(x: &mut Lanes, y: &mut Lanes, work: &mut [Lanes; 2], m: usize) {
    if m == 1 {
        y[0] = x[0];
        return;
    }
    let [p, q] = work;
    p[0] = x[0];
    let (mut approx, mut next) = (p, q);
    let mut len = 2;
    while len <= m {
        let half = len / 2;
        let out: &mut Lanes = if len == m { &mut *y } else { &mut *next };
        for i in 0..half {
            // As in `haar_forward_lanes` (here `out` is one of two arrays chosen at run time,
            // and the compiler left the element-wise loop scalar).
            let (a, d) = (approx[i], x[half + i]);
            out[2 * i] = std::array::from_fn(|k| (a[k] + d[k]) * FRAC_1_SQRT_2);
            out[2 * i + 1] = std::array::from_fn(|k| (a[k] - d[k]) * FRAC_1_SQRT_2);
        }
        std::mem::swap(&mut approx, &mut next);
        len *= 2;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random(len: usize, seed: u64) -> Vec<f32> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        (0..len).map(|_| rng.gen_range(-1.0..1.0)).collect()
    }

    /// White Gaussian noise of unit variance smoothed by a Gaussian of std `s` px and scaled
    /// back to unit per-pixel variance.
    fn correlated_noise(h: usize, w: usize, s: f32, seed: u64) -> ndarray::Array2<f32> {
        use rand_distr::{Distribution, StandardNormal};
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let white = ndarray::Array2::from_shape_fn((h, w), |_| StandardNormal.sample(&mut rng));
        let smooth = crate::filters::gaussian_blur(&white, s);
        let var = smooth.iter().map(|v| v * v).sum::<f32>() / smooth.len() as f32;
        smooth / var.sqrt()
    }

    #[test]
    fn coefficient_profile_matches_the_dct_spectrum_of_smoothed_noise() {
        assert!(coefficient_profile(8, 0.0).iter().all(|&q| q == 1.0));
        let tr = Transforms::new(8, 2.0);
        for s in [0.5f32, 0.8, 1.2] {
            let noise = correlated_noise(256, 256, s, 11);
            // Variance of every DCT coefficient over the non-overlapping 8x8 blocks.
            let mut power = [0.0f64; 64];
            let (mut tmp, mut out) = (vec![0.0f32; 64], vec![0.0f32; 64]);
            let mut blocks = 0;
            for by in (0..256).step_by(8) {
                for bx in (0..256).step_by(8) {
                    let block: Vec<f32> =
                        (0..64).map(|k| noise[[by + k / 8, bx + k % 8]]).collect();
                    tr.forward(&block, &mut tmp, &mut out);
                    for (p, v) in power.iter_mut().zip(&out) {
                        *p += (*v as f64).powi(2);
                    }
                    blocks += 1;
                }
            }
            let profile = coefficient_profile(8, s);
            let mean_square = profile.iter().map(|q| (q * q) as f64).sum::<f64>() / 64.0;
            assert!((mean_square - 1.0).abs() < 1e-5, "{mean_square}");
            // The model against the measured σ of the coefficients that hold most of the noise
            // (within 25 %), and of the first three frequencies along each axis.
            for k in [0usize, 1, 2, 8, 9, 16, 18] {
                let measured = (power[k] / blocks as f64).sqrt();
                let ratio = profile[k] as f64 / measured;
                assert!(
                    (0.75..1.33).contains(&ratio),
                    "s {s}, coefficient {k}: model {} vs measured {measured}",
                    profile[k]
                );
            }
            // High frequencies hold far less noise than the low ones.
            assert!(profile[63] < 0.2 * profile[0], "{profile:?}");
        }
    }

    #[test]
    fn correlated_noise_is_removed_better_with_its_profile() {
        // A smooth ramp with a step, plus noise correlated over 0.8 px of known per-pixel σ.
        let (h, w, sigma) = (96usize, 96usize, 20.0f32);
        let clean = ndarray::Array2::from_shape_fn((h, w), |(y, x)| {
            100.0 + x as f32 + if y > 48 { 60.0 } else { 0.0 }
        });
        let noisy = &clean + &(correlated_noise(h, w, 0.8, 5) * sigma);
        let mse = |correlation: f32| {
            let config = Bm3dConfig {
                noise_correlation_px: [correlation, correlation],
                ..Bm3dConfig::default()
            };
            let out = bm3d_grey(noisy.view(), sigma, &config).unwrap();
            (&out - &clean).mapv(|v| v * v).mean().unwrap()
        };
        let (white, matched) = (mse(0.0), mse(0.8));
        assert!(
            matched < 0.8 * white,
            "white-noise model {white}, correlated {matched}"
        );
    }

    #[test]
    fn bounded_distance_is_the_full_distance_or_none() {
        for (len, seed) in [(64usize, 1u64), (16, 2), (9, 3), (1, 4)] {
            for k in 0..50u64 {
                let a = random(len, seed * 100 + k);
                let b = random(len, seed * 1000 + k);
                let full = squared_distance(&a, &b);
                for limit in [0.0, full * 0.5, full, full * 1.0001, full * 2.0] {
                    let bounded = squared_distance_at_most(&a, &b, limit);
                    if full <= limit {
                        assert_eq!(bounded.map(f32::to_bits), Some(full.to_bits()));
                    } else {
                        assert_eq!(bounded, None);
                    }
                    // The 8 x 8 kernels: the portable one and the AVX2 one, the same bits and
                    // the same `None`s (also for limits between the early checks' sums).
                    if len == 64 {
                        let (a8, b8): (&[f32; 64], &[f32; 64]) =
                            (a[..].try_into().unwrap(), b[..].try_into().unwrap());
                        let portable = distance_at_most(&a, &b, limit, None);
                        assert_eq!(portable.map(f32::to_bits), bounded.map(f32::to_bits));
                        // Given the sum after two rows (as `low_partial_distances` makes
                        // it), the same answer.
                        let two_rows = (0..8).fold(0.0f32, |sum, j| {
                            let (d0, d1) = (a[j] - b[j], a[j + 8] - b[j + 8]);
                            let acc = d0 * d0 + d1 * d1;
                            if j == 0 {
                                acc
                            } else {
                                sum + acc
                            }
                        });
                        for l in [limit, two_rows, two_rows * 0.999, full * 0.3] {
                            let given = distance_at_most(&a, &b, l, Some(two_rows));
                            let own = distance_at_most(&a, &b, l, None);
                            assert_eq!(given.map(f32::to_bits), own.map(f32::to_bits));
                        }
                        #[cfg(target_arch = "x86_64")]
                        if std::arch::is_x86_feature_detected!("avx2") {
                            for l in [limit, full * 0.1, full * 0.3, full * 0.6] {
                                // SAFETY: AVX2 checked just above.
                                let wide = unsafe { distance_at_most_avx2(a8, b8, l, None) };
                                let portable = distance_at_most(&a, &b, l, None);
                                assert_eq!(wide.map(f32::to_bits), portable.map(f32::to_bits));
                                // SAFETY: AVX2 checked just above.
                                let given =
                                    unsafe { distance_at_most_avx2(a8, b8, l, Some(two_rows)) };
                                assert_eq!(given.map(f32::to_bits), portable.map(f32::to_bits));
                            }
                        }
                        let _ = (a8, b8);
                    }
                }
            }
        }
    }

    #[test]
    fn transforms_of_8x8_blocks_match_the_general_path() {
        // The unrolled 8 x 8 transforms against the general one, bit for bit.
        let tr = Transforms::new(8, 2.0);
        let general = |block: &[f32], inverse: bool| {
            let n = 8;
            let (m1, m2): (&[f32], &[f32]) = if inverse {
                (&tr.dct_t, &tr.dct)
            } else {
                (&tr.dct, &tr.dct_t)
            };
            let mut tmp = vec![0.0f32; 64];
            for k in 0..n {
                for i in 0..n {
                    axpy(
                        &mut tmp[k * n..(k + 1) * n],
                        m1[k * n + i],
                        &block[i * n..(i + 1) * n],
                    );
                }
            }
            let mut out = vec![0.0f32; 64];
            for k in 0..n {
                for j in 0..n {
                    axpy(
                        &mut out[k * n..(k + 1) * n],
                        tmp[k * n + j],
                        &m2[j * n..(j + 1) * n],
                    );
                }
            }
            out
        };
        for seed in 0..20 {
            let block = random(64, 700 + seed);
            // The dispatched product (AVX2 where present) against the portable loop.
            let (a, b): (&[f32; 64], &[f32; 64]) = (
                block[..].try_into().unwrap(),
                tr.dct[..].try_into().unwrap(),
            );
            let (mut fast, mut portable) = ([0.0f32; 64], [0.0f32; 64]);
            matmul8(a, b, &mut fast);
            matmul8_portable(a, b, &mut portable);
            assert_eq!(fast.map(f32::to_bits), portable.map(f32::to_bits));
            matmul8(b, a, &mut fast);
            matmul8_portable(b, a, &mut portable);
            assert_eq!(fast.map(f32::to_bits), portable.map(f32::to_bits));
            let (mut tmp, mut out) = (vec![0.0f32; 64], vec![0.0f32; 64]);
            tr.forward(&block, &mut tmp, &mut out);
            assert_eq!(out, general(&block, false));
            tr.inverse(&block, &mut tmp, &mut out);
            assert_eq!(out, general(&block, true));
        }
    }

    #[test]
    fn dct_is_orthonormal_round_trip_and_parseval() {
        for n in [4usize, 8, 11] {
            let tr = Transforms::new(n, 2.0);
            // D·Dᵀ = I.
            for a in 0..n {
                for b in 0..n {
                    let dot: f32 = (0..n).map(|i| tr.dct[a * n + i] * tr.dct[b * n + i]).sum();
                    let want = if a == b { 1.0 } else { 0.0 };
                    assert!((dot - want).abs() < 1e-5, "n {n} rows {a},{b}: {dot}");
                }
            }
            let block = random(n * n, n as u64);
            let (mut tmp, mut coeffs, mut back) =
                (vec![0.0; n * n], vec![0.0; n * n], vec![0.0; n * n]);
            tr.forward(&block, &mut tmp, &mut coeffs);
            tr.inverse(&coeffs, &mut tmp, &mut back);
            for (a, b) in block.iter().zip(&back) {
                assert!((a - b).abs() < 1e-5);
            }
            let e_pix: f32 = block.iter().map(|v| v * v).sum();
            let e_coef: f32 = coeffs.iter().map(|v| v * v).sum();
            assert!((e_pix - e_coef).abs() < 1e-4 * e_pix);
        }
    }

    #[test]
    fn block_coefficients_are_each_blocks_own_transform_bit_for_bit() {
        // The separable all-positions transform (8 x 8) and the general path (5 x 5) against
        // `forward` of every block cut out of the plane.
        for n in [8usize, 5] {
            let (h, w) = (13, 29);
            let plane = random(h * w, 11 + n as u64);
            let config = Bm3dConfig {
                block_size: n,
                ..Bm3dConfig::default()
            };
            let geo = Geometry::new(h, w, n, &config);
            let tr = Transforms::new(n, 2.0);
            let coeffs = BlockCoeffs::compute(&plane, &geo, &tr);
            // And computed in a given buffer, and hard-thresholded (a copy): other allocations.
            let t = 0.3;
            let recycled = BlockCoeffs::compute_in(vec![1.0; 5], &plane, &geo, &tr);
            let thresholded = coeffs.hard_thresholded(t);
            assert_eq!(coeffs.coefficients().len(), geo.ph * geo.pw * n * n);
            let (mut block, mut tmp, mut expected) =
                (vec![0.0; n * n], vec![0.0; n * n], vec![0.0; n * n]);
            for y in 0..geo.ph {
                for x in 0..geo.pw {
                    let pos = y * geo.pw + x;
                    for stored in [&coeffs, &recycled, &thresholded] {
                        // Whole cache lines from the first block on.
                        assert_eq!(
                            stored.block(pos).as_ptr() as usize % 64,
                            (pos * n * n * 4) % 64
                        );
                    }
                    let kept = coeffs
                        .block(pos)
                        .iter()
                        .map(|&v| if v.abs() > t { v } else { 0.0 });
                    assert!(kept.eq(thresholded.block(pos).iter().copied()));
                    assert_eq!(coeffs.block(pos), recycled.block(pos));
                    for i in 0..n {
                        block[i * n..(i + 1) * n]
                            .copy_from_slice(&plane[(y + i) * w + x..(y + i) * w + x + n]);
                    }
                    tr.forward(&block, &mut tmp, &mut expected);
                    let got = coeffs.block(y * geo.pw + x);
                    let same = got
                        .iter()
                        .zip(&expected)
                        .all(|(a, b)| a.to_bits() == b.to_bits());
                    assert!(same, "n = {n}, block ({y}, {x}): {got:?} != {expected:?}");
                }
            }
        }
    }

    #[test]
    fn dct_of_constant_block_is_dc_only() {
        let tr = Transforms::new(8, 2.0);
        let block = vec![3.0f32; 64];
        let (mut tmp, mut coeffs) = (vec![0.0; 64], vec![0.0; 64]);
        tr.forward(&block, &mut tmp, &mut coeffs);
        assert!(
            (coeffs[0] - 24.0).abs() < 1e-4,
            "DC = 3·8 = 24, got {}",
            coeffs[0]
        );
        assert!(coeffs[1..].iter().all(|v| v.abs() < 1e-4));
    }

    #[test]
    fn haar_is_orthonormal_round_trip_and_parseval() {
        let n2 = 5;
        for m in [1usize, 2, 4, 16, 32] {
            let orig = random(m * n2, m as u64 + 100);
            let mut g = orig.clone();
            let mut tmp = vec![0.0; m * n2];
            haar_forward(&mut g, m, n2, &mut tmp);
            let e0: f32 = orig.iter().map(|v| v * v).sum();
            let e1: f32 = g.iter().map(|v| v * v).sum();
            assert!((e0 - e1).abs() < 1e-4 * e0.max(1.0), "m {m}");
            // The first coefficient of each column is the scaled group mean.
            let mean0: f32 = (0..m).map(|b| orig[b * n2]).sum::<f32>() / m as f32;
            assert!((g[0] - mean0 * (m as f32).sqrt()).abs() < 1e-4);
            haar_inverse(&mut g, m, n2, &mut tmp);
            for (a, b) in orig.iter().zip(&g) {
                assert!((a - b).abs() < 1e-5);
            }
        }
    }

    #[test]
    fn haar_of_eight_lanes_matches_the_general_path() {
        for n2 in [8usize, 64] {
            for m in [1usize, 2, 4, 8, 16, 32] {
                let orig = random(m * n2, (m * n2) as u64 + 7);
                let mut tmp = vec![0.0; m * n2];
                let (mut fast, mut general) = (orig.clone(), orig.clone());
                haar_forward(&mut fast, m, n2, &mut tmp);
                haar_forward_general(&mut general, m, n2, &mut tmp);
                assert_eq!(fast, general, "forward, m {m}, n2 {n2}");
                haar_inverse(&mut fast, m, n2, &mut tmp);
                haar_inverse_general(&mut general, m, n2, &mut tmp);
                assert_eq!(fast, general, "inverse, m {m}, n2 {n2}");
            }
        }
    }

    /// The filtering of 8 × 8 groups in eight-coefficient lanes gives the bits of the three
    /// separate passes (Haar, shrinkage, inverse Haar), group and sum, for every group size,
    /// both shrinkages, white and correlated noise, with and without the AVX2 kernels.
    #[test]
    fn group_filtering_in_lanes_matches_the_separate_passes() {
        let profiles = [vec![1.0f32; 64], coefficient_profile(8, 0.8)];
        for m in [1usize, 2, 4, 8, 16, 32] {
            for (p, profile) in profiles.iter().enumerate() {
                let seed = (m * 10 + p) as u64;
                let group: Vec<f32> = random(m * 64, seed).iter().map(|v| 40.0 * v).collect();
                let basic: Vec<f32> = random(m * 64, seed + 1).iter().map(|v| 40.0 * v).collect();
                for wiener in [false, true] {
                    // Thresholds that keep about half of the coefficients.
                    let param = if wiener { 300.0 } else { 10.0 };
                    let mut tmp = vec![0.0; m * 64];
                    let mut expected = group.clone();
                    let mut b = basic.clone();
                    haar_forward(&mut expected, m, 64, &mut tmp);
                    let total = if wiener {
                        haar_forward(&mut b, m, 64, &mut tmp);
                        wiener_shrink(&mut expected, &b, profile, param)
                    } else {
                        hard_threshold(&mut expected, profile, param)
                    };
                    haar_inverse(&mut expected, m, 64, &mut tmp);
                    let mut runs = vec![false];
                    #[cfg(target_arch = "x86_64")]
                    if std::arch::is_x86_feature_detected!("avx2") {
                        runs.push(true);
                    }
                    for avx2 in runs {
                        let (mut g, mut b) = (group.clone(), basic.clone());
                        let got = match (avx2, wiener) {
                            (false, false) => filter_group::<false, false>(
                                &mut g, &mut b, m, profile, param, &mut tmp,
                            ),
                            (false, true) => filter_group::<false, true>(
                                &mut g, &mut b, m, profile, param, &mut tmp,
                            ),
                            (true, false) => filter_group::<true, false>(
                                &mut g, &mut b, m, profile, param, &mut tmp,
                            ),
                            (true, true) => filter_group::<true, true>(
                                &mut g, &mut b, m, profile, param, &mut tmp,
                            ),
                        };
                        let what = format!("m {m}, profile {p}, wiener {wiener}, avx2 {avx2}");
                        assert_eq!(got.to_bits(), total.to_bits(), "{what}");
                        assert_eq!(g, expected, "{what}");
                        assert!(total > 0.0 && total < (m * 64) as f32, "{what}: {total}");
                    }
                }
            }
        }
    }

    /// The shrinkages keep, zero and scale every coefficient as the formulas say, and their
    /// lane sums equal the plain f64 sums, for 8x8 blocks and a length with a remainder (5x5).
    #[test]
    fn shrinkages_match_their_formulas() {
        for n2 in [64usize, 25] {
            let m = 5;
            let group = random(m * n2, 3);
            let basic = random(m * n2, 4);
            let profile: Vec<f32> = (0..n2).map(|k| 0.5 + (k % 7) as f32 * 0.2).collect();
            let (threshold, s2) = (0.9f32, 0.3f32);

            let mut thresholded = group.clone();
            let retained = hard_threshold(&mut thresholded, &profile, threshold);
            let mut expected = 0.0f64;
            for (i, (&v, &t)) in group.iter().zip(&thresholded).enumerate() {
                let q = profile[i % n2];
                if v.abs() > threshold * q {
                    assert_eq!(t, v);
                    expected += (q * q) as f64;
                } else {
                    assert_eq!(t, 0.0);
                }
            }
            assert!(
                (retained as f64 - expected).abs() < 1e-5 * expected,
                "{retained} {expected}"
            );

            let mut shrunk = group.clone();
            let norm = wiener_shrink(&mut shrunk, &basic, &profile, s2);
            let mut expected = 0.0f64;
            for (i, (&v, &t)) in group.iter().zip(&shrunk).enumerate() {
                let (b2, q2) = (basic[i] * basic[i], profile[i % n2] * profile[i % n2]);
                let wc = b2 / (b2 + s2 * q2);
                assert_eq!(t, v * wc);
                expected += (wc * wc * q2) as f64;
            }
            assert!(
                (norm as f64 - expected).abs() < 1e-5 * expected,
                "{norm} {expected}"
            );
        }
    }

    /// The AVX2 shrinkages give the portable versions' bits: the shrunk coefficients and the
    /// lane sums, for groups of 1 to 32 blocks of 8x8 and of 4x4 coefficients, with
    /// coefficients exactly at the threshold, zeros (a zero basic coefficient with a zero
    /// profile entry makes W = 0/0) and both signs.
    #[test]
    fn avx2_shrinkages_are_bit_identical_to_portable() {
        #[cfg(target_arch = "x86_64")]
        {
            if !std::arch::is_x86_feature_detected!("avx2") {
                return;
            }
            for n2 in [64usize, 16] {
                for m in [1usize, 2, 4, 8, 16, 32] {
                    let mut group = random(m * n2, 10 + m as u64);
                    let mut basic = random(m * n2, 20 + m as u64);
                    let mut profile: Vec<f32> =
                        (0..n2).map(|k| 0.5 + (k % 7) as f32 * 0.2).collect();
                    let threshold = 0.6f32;
                    // On the threshold exactly (kept only if strictly above), zeros, -0.0.
                    group[0] = threshold * profile[0];
                    group[1] = -threshold * profile[1];
                    group[2] = 0.0;
                    group[3] = -0.0;
                    basic[4] = 0.0;
                    profile[4] = 0.0;
                    basic[5] = -0.0;
                    for s2 in [0.3f32, 0.0, 7.5] {
                        let (mut a, mut b) = (group.clone(), group.clone());
                        let ra = hard_threshold(&mut a, &profile, threshold);
                        // SAFETY: AVX2 checked above.
                        let rb = unsafe { hard_threshold_avx2(&mut b, &profile, threshold) };
                        assert_eq!(ra.to_bits(), rb.to_bits(), "n2 {n2} m {m}");
                        assert_eq!(
                            a.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                            b.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
                        );
                        let (mut a, mut b) = (group.clone(), group.clone());
                        let wa = wiener_shrink(&mut a, &basic, &profile, s2);
                        // SAFETY: AVX2 checked above.
                        let wb = unsafe { wiener_shrink_avx2(&mut b, &basic, &profile, s2) };
                        assert_eq!(wa.to_bits(), wb.to_bits(), "n2 {n2} m {m} s2 {s2}");
                        assert_eq!(
                            a.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                            b.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
                        );
                    }
                }
            }
        }
    }

    /// A block's coefficients computed from the plane are the stored ones, bit for bit (8 x 8
    /// and the general path).
    #[test]
    fn block_source_from_the_plane_is_the_stored_coefficients() {
        for n in [8usize, 5] {
            let (h, w) = (23usize, 31usize);
            let image = random(h * w, 40 + n as u64);
            let geo = Geometry::new(h, w, n, &Bm3dConfig::default());
            let tr = Transforms::new(n, 2.0);
            let coeffs = BlockCoeffs::compute(&image, &geo, &tr);
            let (stored, plane) = (BlockSource::Stored(&coeffs), BlockSource::Plane(&image));
            let (mut pixels, mut tmp) = (vec![0.0f32; n * n], vec![0.0f32; n * n]);
            let (mut a, mut b) = (vec![0.0f32; n * n], vec![0.0f32; n * n]);
            for pos in 0..geo.ph * geo.pw {
                stored.block_into(pos, &geo, &tr, (&mut pixels, &mut tmp), &mut a);
                plane.block_into(pos, &geo, &tr, (&mut pixels, &mut tmp), &mut b);
                assert_eq!(
                    a.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                    b.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                    "n {n}, position {pos}"
                );
            }
        }
    }

    #[test]
    fn kaiser_window_matches_closed_form() {
        // I0(0) = 1; I0(2) = 2.2795853023360673.
        assert!((bessel_i0(0.0) - 1.0).abs() < 1e-15);
        assert!((bessel_i0(2.0) - 2.279_585_302_336_067).abs() < 1e-12);
        let k = kaiser_1d(8, 2.0);
        assert!((k[0] - (1.0 / 2.279_585_3) as f32).abs() < 1e-6);
        for i in 0..4 {
            assert!((k[i] - k[7 - i]).abs() < 1e-7, "symmetric");
            assert!(k[i] < k[i + 1] || i == 3, "rising to the centre");
        }
    }

    #[test]
    fn reference_grid_covers_last_position() {
        assert_eq!(reference_grid(10, 3), vec![0, 3, 6, 9]);
        assert_eq!(reference_grid(11, 3), vec![0, 3, 6, 9, 10]);
        assert_eq!(reference_grid(1, 3), vec![0]);
    }

    #[test]
    fn previous_power_of_two() {
        let got: Vec<usize> = (1..=9).map(prev_power_of_two).collect();
        assert_eq!(got, vec![1, 2, 2, 4, 4, 4, 4, 8, 8]);
    }

    /// The group of a plain full search: every window position within τ, sorted by
    /// (distance, position), the best `max_group − 1` kept, cut to a power of two.
    fn full_search_group(p: &StepParams, geo: &Geometry, yr: usize, xr: usize) -> Vec<usize> {
        let hw = geo.half_window;
        let ref_pos = yr * geo.pw + xr;
        let reference = p.matching.block(ref_pos);
        let mut found: Vec<(f32, usize)> = Vec::new();
        for y in yr.saturating_sub(hw)..=(yr + hw).min(geo.ph - 1) {
            for x in xr.saturating_sub(hw)..=(xr + hw).min(geo.pw - 1) {
                let pos = y * geo.pw + x;
                let d = squared_distance(reference, p.matching.block(pos));
                if pos != ref_pos && d <= p.tau_sum {
                    found.push((d, pos));
                }
            }
        }
        found.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        found.truncate(p.max_group - 1);
        let size = prev_power_of_two(1 + found.len()).min(prev_power_of_two(p.max_group));
        std::iter::once(ref_pos)
            .chain(found[..size - 1].iter().map(|&(_, pos)| pos))
            .collect()
    }

    #[test]
    fn bounded_search_finds_the_full_search_group() {
        // A smooth image with repeated texture and noise, so that many blocks are near each
        // other and near the thresholds.
        let (h, w) = (48usize, 56usize);
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let image: Vec<f32> = (0..h * w)
            .map(|i| {
                let (y, x) = ((i / w) as f32, (i % w) as f32);
                100.0 + 40.0 * (x * 0.7).sin() * (y * 0.3).cos() + rng.gen_range(-20.0..20.0)
            })
            .collect();
        let config = Bm3dConfig {
            search_window: 21,
            ..Bm3dConfig::default()
        };
        let geo = Geometry::new(h, w, 8, &config);
        let tr = Transforms::new(8, 2.0);
        let coeffs = [BlockCoeffs::compute(&image, &geo, &tr)];
        let low = low_planes(&coeffs[0], &geo).expect("8 x 8 blocks");
        for (tau_sum, max_group) in [(64.0 * 400.0, 16), (64.0 * 3000.0, 32), (64.0 * 50.0, 8)] {
            for with_low in [true, false] {
                let p = StepParams {
                    matching: &coeffs[0],
                    low: with_low.then_some(&low),
                    tau_sum,
                    max_group,
                    noisy: &[BlockSource::Stored(&coeffs[0])],
                    basic: None,
                    sigmas: &[20.0],
                    block_variance: None,
                    lambda_3d: 2.7,
                    profiles: &[vec![1.0; 64]],
                };
                // One worker's scratch across many references, so that the bound from the
                // previous group is used (and sometimes from another row).
                let mut s = Scratch::new(64, max_group);
                #[cfg(target_arch = "x86_64")]
                let mut s_avx2 = Scratch::new(64, max_group);
                for &yr in &geo.ref_ys {
                    for &xr in &geo.ref_xs {
                        let full = full_search_group(&p, &geo, yr, xr);
                        find_group::<false>(&p, &geo, yr, xr, &mut s);
                        assert_eq!(
                            s.group, full,
                            "tau {tau_sum}, group {max_group}, low {with_low}, ({yr}, {xr})"
                        );
                        #[cfg(target_arch = "x86_64")]
                        if std::arch::is_x86_feature_detected!("avx2") {
                            // The AVX2 kernels, with the worker's own scratch.
                            find_group::<true>(&p, &geo, yr, xr, &mut s_avx2);
                            assert_eq!(s_avx2.group, full, "AVX2 ({yr}, {xr})");
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn low_coefficient_partials_are_the_bounded_distance_checks() {
        // Eight lanes of the first check equal the partial sum that `distance_at_most` compares
        // after two rows of coefficients (bit for bit), and never exceed the full distance.
        let (h, w) = (20usize, 30usize);
        let image = random(h * w, 77);
        let geo = Geometry::new(h, w, 8, &Bm3dConfig::default());
        let tr = Transforms::new(8, 2.0);
        let coeffs = BlockCoeffs::compute(&image, &geo, &tr);
        let low = low_planes(&coeffs, &geo).expect("8 x 8 blocks");
        let reference = coeffs.block(5 * geo.pw + 4);
        for y in 0..geo.ph {
            for x0 in (0..geo.pw).step_by(8) {
                let lanes = low_partial_distances(&low, reference, y, x0);
                // With no bound every lane passes and the check returns the partials.
                let (mask, partial) = low_check::<false>(&low, reference, y, x0, f32::INFINITY);
                assert_eq!(mask, 0xff);
                assert_eq!(partial.map(f32::to_bits), lanes.map(f32::to_bits));
                #[cfg(target_arch = "x86_64")]
                if std::arch::is_x86_feature_detected!("avx2") {
                    // SAFETY: AVX2 checked just above.
                    let (mask, wide) =
                        unsafe { low_check_avx2(&low, reference, y, x0, f32::INFINITY) };
                    assert_eq!(mask, 0xff);
                    assert_eq!(
                        wide.map(f32::to_bits),
                        lanes.map(f32::to_bits),
                        "({y}, {x0})"
                    );
                }
                // With bounds around the lanes' partials (and below all of them, where the
                // first row alone rejects the chunk), the mask is the lanes at most the bound.
                let mut bounds: Vec<f32> = lanes.to_vec();
                bounds.extend([
                    0.0,
                    lanes.iter().copied().fold(f32::INFINITY, f32::min) * 0.5,
                ]);
                for bound in bounds {
                    let want = lanes
                        .iter()
                        .enumerate()
                        .fold(0u32, |m, (l, &v)| m | (((v <= bound) as u32) << l));
                    assert_eq!(low_check::<false>(&low, reference, y, x0, bound).0, want);
                    #[cfg(target_arch = "x86_64")]
                    if std::arch::is_x86_feature_detected!("avx2") {
                        // SAFETY: AVX2 checked just above.
                        let (mask, _) = unsafe { low_check_avx2(&low, reference, y, x0, bound) };
                        assert_eq!(mask, want, "({y}, {x0}) bound {bound}");
                    }
                }
                for (l, &got) in lanes.iter().enumerate().take(geo.pw - x0) {
                    let block = coeffs.block(y * geo.pw + x0 + l);
                    let mut acc = [0.0f32; 8];
                    for chunk in 0..2 {
                        for j in 0..8 {
                            let d = reference[chunk * 8 + j] - block[chunk * 8 + j];
                            acc[j] += d * d;
                        }
                    }
                    let want = acc.iter().sum::<f32>();
                    assert_eq!(got.to_bits(), want.to_bits(), "({y}, {})", x0 + l);
                    assert!(got <= squared_distance(reference, block));
                }
            }
        }
    }

    #[test]
    fn centre_out_visits_every_row_once_nearest_first() {
        assert_eq!(
            centre_out(5, 3, 9).collect::<Vec<_>>(),
            [5, 6, 4, 7, 3, 8, 9]
        );
        assert_eq!(centre_out(0, 0, 2).collect::<Vec<_>>(), [0, 1, 2]);
        assert_eq!(centre_out(4, 0, 4).collect::<Vec<_>>(), [4, 3, 2, 1, 0]);
        assert_eq!(centre_out(7, 7, 7).collect::<Vec<_>>(), [7]);
    }

    #[test]
    fn group_starts_with_reference_even_among_identical_blocks() {
        // Constant image: every block is at distance 0; the reference must still be first.
        let (h, w) = (20usize, 20usize);
        let config = Bm3dConfig::default();
        let geo = Geometry::new(h, w, 8, &config);
        let tr = Transforms::new(8, 2.0);
        let coeffs = BlockCoeffs::compute(&vec![1.0; h * w], &geo, &tr);
        let noisy = [coeffs];
        let p = StepParams {
            matching: &noisy[0],
            low: None,
            tau_sum: 1.0,
            max_group: 16,
            noisy: &[BlockSource::Stored(&noisy[0])],
            basic: None,
            sigmas: &[1.0],
            block_variance: None,
            lambda_3d: 2.7,
            profiles: &[vec![1.0; 64]],
        };
        let mut s = Scratch::new(64, 16);
        find_group::<false>(&p, &geo, 6, 6, &mut s);
        assert_eq!(s.group.len(), 16);
        assert_eq!(s.group[0], 6 * geo.pw + 6);
        let mut unique = s.group.clone();
        unique.sort_unstable();
        unique.dedup();
        assert_eq!(unique.len(), 16);
    }
}
