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
//!   default (`lambda_2d = 0`): with the DCT it measured worse here (docs/tuning.md). The block
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
//! serves both steps) are transformed when a group takes them ([`transforms::BlockSource`]): each
//! position is a group member only about once or twice per step, so that is cheaper than
//! storing every position (the same bits either way).
//! For 8×8 blocks the matching channel's first two coefficient rows are also stored as planes
//! over the positions (a quarter more), so that the first check of a candidate runs on eight
//! positions at once; matching stops summing a candidate once it cannot enter the group
//! ([`grouping::find_group`]). Both only skip work: the groups are those of the plain full
//! search.
//!
//! Parallelism and determinism: reference-block rows are processed in parallel with rayon; each
//! row aggregates into its own strip buffer (the rows its search window reaches), and strips are
//! summed into the image in row order afterwards (batches of at most 32 rows bound the memory),
//! so the result is bit-identical for any thread count.
//!
//! The files follow the algorithm: [`config`] (parameters, Table I), [`transforms`] (2D DCT,
//! 1D Haar, Kaiser window), [`grouping`] (block matching), [`filtering`] (hard thresholding and
//! Wiener shrinkage of a group), [`aggregation`] (weighted block estimates into the image),
//! [`steps`] (the two steps over the reference grid) and [`x86`] (the AVX2 kernels, each the
//! same bits as its portable reference). The instruction set is a [`crate::cpu::Isa`] taken
//! once at the entry ([`bm3d_multichannel_varying`], or the caller of [`bm3d_planes`]).

// `forbid` would reach into `x86`, the one child with unsafe code (it allows it).
#![deny(unsafe_code)]

mod aggregation;
mod config;
mod filtering;
mod grouping;
mod steps;
mod transforms;
mod x86;

pub use config::Bm3dConfig;

use crate::cpu::{self, Isa};
use crate::error::{Error, Result};
use config::NoiseRegime;
use filtering::coefficient_profile;
use grouping::LowPlanes;
use ndarray::{Array2, Array3, ArrayView2, ArrayView3};
use rayon::prelude::*;
use steps::{hard_threshold_step, wiener_step};
use transforms::{BlockCoeffs, BlockSource, Transforms};

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
        Isa::current(),
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
/// steps, their [`LowPlanes`], the aggregation sums and strips of [`steps::run_step`]), kept between
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
/// `buffers`, on the instruction set `isa` (the caller's one [`Isa::current`]).
pub(crate) fn bm3d_planes(
    noisy: ArrayView3<f32>,
    sigmas: &[f32],
    relative_variance: Option<ArrayView3<f32>>,
    config: &Bm3dConfig,
    first_channel: FirstChannel,
    buffers: &mut Bm3dBuffers,
    isa: Isa,
) -> Result<Array3<f32>> {
    check_inputs(noisy, sigmas, config)?;
    if sigmas.iter().all(|&s| s == 0.0) {
        return Ok(noisy.to_owned());
    }
    let (c, h, w) = noisy.dim();
    let n = config.block_size;
    let tr = Transforms::new(n, config.kaiser_beta, isa);
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

/// What both steps read: the noisy coefficients, noise model and geometry.
struct SharedParams<'a> {
    /// The noisy planes, one per channel.
    planes: &'a [Vec<f32>],
    block_variance: Option<&'a [Vec<f32>]>,
    profiles: &'a [Vec<f32>],
    geo: &'a Geometry,
    tr: &'a Transforms,
}

/// What differs between the two steps.
struct StepParams<'a> {
    /// Coefficients that matching compares (channel 0 of noisy or basic estimate).
    matching: &'a BlockCoeffs,
    /// The first [`grouping::LOW_COEFFS`] of `matching`'s coefficients as planes over the
    /// block positions (8 × 8 blocks only): the first check of [`grouping::find_group`].
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
    /// next, see [`grouping::find_group`]; never changes a result).
    previous_group: Vec<usize>,
    /// Distances of `previous_group`'s members to the current reference.
    warm: Vec<f32>,
    /// The positions (and two-row partial distances) that passed `find_group`'s first check
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

#[cfg(test)]
mod tests;
