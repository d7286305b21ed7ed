//! Bernoulli imaging model of a single-photon pixel: detection probability, the maximum-likelihood
//! flux estimate, its noise, SNR and dynamic range (paper §3, Eq. 1–6 and Eq. 9; §7); and the
//! Gaussian–Poisson model of a conventional multi-bit pixel that the paper compares against
//! (§6.1, §7), joined in [`PixelModel`], which the merge and the denoiser ask.
//!
//! During one binary frame a SPAD pixel receives a Poisson number of photon detections with mean
//! λ = φ·η·τ (Eq. 2–3) plus dark counts with mean `d`; it reports 1 if at least one avalanche
//! happened, so
//!
//! ```text
//! P(B = 1) = 1 − exp(−(λ + d))                       (Eq. 1–4)
//! ```
//!
//! With `S` ones in `n` independent frames, `S ~ Binomial(n, P(B = 1))` and the maximum-likelihood
//! estimate (Eq. 6) is
//!
//! ```text
//! λ̂ = −ln(1 − S/n) − d .
//! ```
//!
//! Two edge cases are defined here rather than left to the caller:
//! - `S = 0` gives `λ̂ = −d` (a small negative value). It is kept unclamped by [`mle_flux`]: the
//!   negative values are what make averages of many estimates (over pixels, blocks or runs)
//!   unbiased. [`mle_flux_nonneg`] clamps at 0 for display.
//! - `S = n` (every frame fired, "saturation") would give +∞. The count is replaced by
//!   `n − 0.5` — the half-count continuity correction — so the estimate is the finite
//!   `ln(2n) − d`, the largest flux the pixel can report; see [`saturation_flux`]. Counts above
//!   `n` or below 0 (impossible for true counts, possible for interpolated sums) are clamped to
//!   the same range.
//!
//! All fluxes are in photon detections per binary frame, as everywhere in this crate.
#![forbid(unsafe_code)]

use ndarray::{Array, ArrayView, Dimension, Zip};

use crate::error::{Error, Result};

/// Count margin below `n` used for saturated pixels (`S = n` is replaced by `n − 0.5`).
pub const SATURATION_MARGIN: f64 = 0.5;

/// Arrays with at least this many elements are converted in parallel with rayon.
const PARALLEL_MIN_ELEMENTS: usize = 1 << 16;

/// Probability that a pixel reports 1 in one binary frame, `1 − exp(−(λ + d))` (paper Eq. 1–4).
///
/// `lambda` is the mean number of photon detections per frame and `dark` the mean number of dark
/// counts per frame. Computed with `exp_m1` so it stays accurate for tiny fluxes.
pub fn detection_probability(lambda: f64, dark: f64) -> f64 {
    -(-(lambda + dark)).exp_m1()
}

/// Derivative of the detection probability with respect to the flux,
/// `dP(B = 1)/dλ = exp(−(λ + d)) = 1 − P(B = 1)` (paper Eq. 1–4 differentiated): the factor that
/// carries a flux noise into a bit-rate noise by the delta method (e.g. the denoiser's
/// variance-stabilising transform).
pub fn detection_probability_slope(lambda: f64, dark: f64) -> f64 {
    (-(lambda + dark)).exp()
}

/// Maximum-likelihood flux `λ̂ = −ln(1 − S/n) − d` from `ones` = S detections in `frames` = n
/// binary frames with `dark` dark counts per frame (paper Eq. 6).
///
/// Unclamped: `S = 0` gives `−d`, which keeps averages of estimates unbiased. `S = n` is replaced
/// by `n − 0.5` (see the module documentation), so the result is always finite for `n ≥ 1`.
/// Monotonically non-decreasing in `ones`. Returns NaN if `frames` is not positive.
pub fn mle_flux(ones: f64, frames: f64, dark: f64) -> f64 {
    if frames.is_nan() || frames <= 0.0 {
        return f64::NAN;
    }
    let max_ones = (frames - SATURATION_MARGIN).max(0.0);
    let s = ones.clamp(0.0, max_ones);
    -(-s / frames).ln_1p() - dark
}

/// [`mle_flux`] clamped at zero: the estimate for display, where a negative flux has no meaning.
pub fn mle_flux_nonneg(ones: f64, frames: f64, dark: f64) -> f64 {
    mle_flux(ones, frames, dark).max(0.0)
}

/// The largest flux an `n`-frame pixel can report, `ln(2n) − d`: the MLE at the saturation
/// replacement count `n − 0.5`.
pub fn saturation_flux(frames: f64, dark: f64) -> f64 {
    mle_flux(frames, frames, dark)
}

fn check_model_params(frames: f64, dark: f64) -> Result<()> {
    if !(frames.is_finite() && frames >= 1.0) {
        return Err(Error::invalid(format!(
            "number of binary frames must be a finite number >= 1, got {frames}"
        )));
    }
    if !(dark.is_finite() && dark >= 0.0) {
        return Err(Error::invalid(format!(
            "dark counts per frame must be finite and >= 0, got {dark}"
        )));
    }
    Ok(())
}

fn map_counts<D: Dimension>(
    counts: ArrayView<f32, D>,
    frames: f64,
    dark: f64,
    nonneg: bool,
) -> Result<Array<f32, D>> {
    check_model_params(frames, dark)?;
    let mut out = Array::<f32, D>::zeros(counts.raw_dim());
    let f = |o: &mut f32, &s: &f32| {
        let v = mle_flux(f64::from(s), frames, dark);
        *o = if nonneg { v.max(0.0) } else { v } as f32;
    };
    let zip = Zip::from(&mut out).and(&counts);
    if counts.len() >= PARALLEL_MIN_ELEMENTS {
        zip.par_for_each(f);
    } else {
        zip.for_each(f);
    }
    Ok(out)
}

/// [`mle_flux`] over an array of counts (any shape, e.g. an `(H, W)` block sum), all pixels
/// sharing `frames` and `dark`. Parallel with rayon for large arrays.
///
/// Errors if `frames < 1` or `dark < 0` (or either is not finite).
pub fn mle_flux_array<D: Dimension>(
    counts: ArrayView<f32, D>,
    frames: f64,
    dark: f64,
) -> Result<Array<f32, D>> {
    map_counts(counts, frames, dark, false)
}

/// [`mle_flux_nonneg`] over an array of counts; see [`mle_flux_array`].
pub fn mle_flux_nonneg_array<D: Dimension>(
    counts: ArrayView<f32, D>,
    frames: f64,
    dark: f64,
) -> Result<Array<f32, D>> {
    map_counts(counts, frames, dark, true)
}

/// [`mle_flux`] with a per-pixel number of frames, for merged images where each pixel has its
/// own (possibly fractional, weighted) count of contributing frames. Pixels with `frames <= 0`
/// (no data) get NaN. Errors on a shape mismatch or invalid `dark`.
pub fn mle_flux_per_pixel<D: Dimension>(
    counts: ArrayView<f32, D>,
    frames: ArrayView<f32, D>,
    dark: f64,
) -> Result<Array<f32, D>> {
    if counts.shape() != frames.shape() {
        return Err(Error::invalid(format!(
            "counts shape {:?} differs from frames shape {:?}",
            counts.shape(),
            frames.shape()
        )));
    }
    check_model_params(1.0, dark)?;
    let mut out = Array::<f32, D>::zeros(counts.raw_dim());
    let f = |o: &mut f32, &s: &f32, &n: &f32| {
        *o = mle_flux(f64::from(s), f64::from(n), dark) as f32;
    };
    let zip = Zip::from(&mut out).and(&counts).and(&frames);
    if counts.len() >= PARALLEL_MIN_ELEMENTS {
        zip.par_for_each(f);
    } else {
        zip.for_each(f);
    }
    Ok(out)
}

/// Asymptotic standard deviation of the MLE λ̂ from `frames` = n binary frames.
///
/// The Fisher information of one frame about λ is `p'² / (p(1 − p)) = 1 / (e^{λ+d} − 1)` with
/// `p = 1 − e^{−(λ+d)}`, so the Cramér–Rao bound — which the MLE attains as n grows, and which
/// the delta method applied to `−ln(1 − S/n)` gives identically — is
/// `Var(λ̂) ≈ (e^{λ+d} − 1) / n`. Dark counts do not add signal but do add noise, through the
/// exponent.
pub fn mle_std(lambda: f64, frames: f64, dark: f64) -> f64 {
    ((lambda + dark).exp_m1() / frames).sqrt()
}

/// Asymptotic variance of the MLE λ̂ (Eq. 6) written in the detection probability
/// `p = 1 − exp(−(λ + d))` of the pixel (Eq. 1–4): `Var(λ̂) ≈ p / ((1 − p)·n)`, the same
/// Cramér–Rao bound as [`mle_std`] (`p/(1 − p) = e^{λ+d} − 1`). Callers that work with bit
/// rates (the merge's noise model, hot-pixel detection) clamp `p` below 1 first, e.g. to the
/// saturation count `1 − 0.5/n`.
pub fn mle_variance_from_probability(p: f64, frames: f64) -> f64 {
    p / ((1.0 - p) * frames)
}

/// Signal-to-noise ratio of the flux estimate from n binary frames (paper Eq. 9):
///
/// ```text
/// SNR(λ) = λ / std(λ̂) = λ·√n / √(e^{λ+d} − 1)
/// ```
///
/// This is the form obtained from [`mle_std`] (Cramér–Rao / delta method), the SNR analysis of
/// Quanta Burst Photography (Ma et al. 2020) extended by dark counts; the paper text was not at
/// hand to compare symbol by symbol, so it is derived here and checked against Monte Carlo in
/// `tests/model_mle.rs` (within 5 % for λ in 1e-3..3, n = 2000). It is used rather
/// than a Poisson-only `√(nλ)` because it captures both ends of the SPAD's range: at low flux it
/// reduces to `λ√n / √(λ + d)` (shot noise plus dark-count noise), and at high flux the
/// exponential term models the loss of information as almost every frame fires. The SNR is
/// unimodal in λ, peaking where `2(1 − e^{−(λ+d)}) = λ` (λ ≈ 1.59 for d = 0). Linear ratio, not
/// dB; see [`ratio_to_db`].
pub fn snr(lambda: f64, frames: f64, dark: f64) -> f64 {
    let denom = (lambda + dark).exp_m1().sqrt();
    if denom == 0.0 {
        return 0.0;
    }
    lambda * frames.sqrt() / denom
}

/// Amplitude ratio to decibels, `20·log10(r)`.
pub fn ratio_to_db(ratio: f64) -> f64 {
    20.0 * ratio.log10()
}

/// Decibels to amplitude ratio, `10^(db/20)` (e.g. 20 dB -> 10).
pub fn db_to_ratio(db: f64) -> f64 {
    10f64.powf(db / 20.0)
}

/// The flux at which [`snr`] peaks for dark-count rate `dark` (independent of n): the root of
/// `2(1 − e^{−(λ+d)}) − λ`, found by bisection.
pub fn peak_snr_flux(dark: f64) -> f64 {
    // h(λ) = 2(1 − e^{−(λ+d)}) − λ is concave with h(0) >= 0 and h(2) < 0: one sign change.
    let h = |l: f64| 2.0 * detection_probability(l, dark) - l;
    let (mut lo, mut hi) = (0.0_f64, 2.0_f64);
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if h(mid) > 0.0 {
            lo = mid;
        } else {
            hi = mid;
        }
        if hi - lo <= 1e-15 * hi {
            break;
        }
    }
    0.5 * (lo + hi)
}

/// What sets the upper end of the dynamic range.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum UpperLimit {
    /// The SNR falls below the threshold before the pixel saturates.
    Snr,
    /// The expected count reaches `n − 0.5` ([`saturation_flux`]) first.
    Saturation,
}

/// Range of fluxes measurable with SNR at or above a threshold (paper §7).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DynamicRange {
    /// Smallest flux (detections per frame) with SNR >= threshold.
    pub min_flux: f64,
    /// Largest flux with SNR >= threshold and expected count <= n − 0.5.
    pub max_flux: f64,
    /// Which criterion set `max_flux`.
    pub upper_limit: UpperLimit,
    /// `20·log10(max_flux / min_flux)`.
    pub db: f64,
}

/// Bisection for the crossing of `snr = threshold` between `inside` (snr >= threshold) and
/// `outside` (snr < threshold); returns the point on the `inside` side to 1e-14 relative.
fn bisect_crossing(mut inside: f64, mut outside: f64, frames: f64, dark: f64, thr: f64) -> f64 {
    for _ in 0..300 {
        let mid = 0.5 * (inside + outside);
        if snr(mid, frames, dark) >= thr {
            inside = mid;
        } else {
            outside = mid;
        }
        if (inside - outside).abs() <= 1e-14 * inside.abs().max(outside.abs()) {
            break;
        }
    }
    inside
}

/// Dynamic range of an n-frame estimate (paper §7): the smallest and largest flux λ with
/// `snr(λ, n, d) >= snr_threshold` (a linear ratio, e.g. 1, or [`db_to_ratio`]`(20.0)`), both
/// found by bisection on either side of [`peak_snr_flux`]. The largest is further capped at the
/// saturation limit [`saturation_flux`] `= ln(2n) − d`, where the expected count reaches
/// `n − 0.5`, whichever is smaller.
///
/// Errors on invalid parameters or if even the peak SNR is below the threshold.
pub fn dynamic_range(frames: f64, dark: f64, snr_threshold: f64) -> Result<DynamicRange> {
    check_model_params(frames, dark)?;
    if !(snr_threshold.is_finite() && snr_threshold > 0.0) {
        return Err(Error::invalid(format!(
            "SNR threshold must be a positive finite ratio, got {snr_threshold}"
        )));
    }
    let peak = peak_snr_flux(dark);
    let peak_snr = snr(peak, frames, dark);
    if peak_snr < snr_threshold {
        return Err(Error::invalid(format!(
            "peak SNR {peak_snr:.4} (at {peak:.4} detections/frame with {frames} frames, dark \
             {dark}) is below the threshold {snr_threshold}"
        )));
    }
    // SNR -> 0 as λ -> 0, so 0 is outside (or on the boundary, handled by bisection).
    let min_flux = bisect_crossing(peak, 0.0, frames, dark, snr_threshold);
    let mut outside = 2.0 * peak.max(1.0);
    while snr(outside, frames, dark) >= snr_threshold {
        outside *= 2.0;
    }
    let snr_max = bisect_crossing(peak, outside, frames, dark, snr_threshold);
    let sat = saturation_flux(frames, dark);
    let (max_flux, upper_limit) = if sat < snr_max {
        (sat, UpperLimit::Saturation)
    } else {
        (snr_max, UpperLimit::Snr)
    };
    Ok(DynamicRange {
        min_flux,
        max_flux,
        upper_limit,
        db: ratio_to_db(max_flux / min_flux),
    })
}

/// Signal-to-noise ratio of the sum of `frames` conventional (multi-bit) frames, each with mean
/// `lambda` photoelectrons, `dark` dark electrons, Gaussian read noise `read_noise_e` (e- RMS) and
/// uniform quantisation of `step_e` electrons per digital number:
///
/// ```text
/// SNR(λ) = λ·√n / √(λ + d + σ_r² + q²/12)
/// ```
///
/// the Gaussian–Poisson model of a conventional sensor (paper §6.1 and §7 compare against it).
/// Saturation is not part of the SNR; [`conventional_dynamic_range`] caps the range at the full
/// well. Linear ratio, not dB.
pub fn conventional_snr(
    lambda: f64,
    frames: f64,
    dark: f64,
    read_noise_e: f64,
    step_e: f64,
) -> f64 {
    let var = lambda + dark + read_noise_e * read_noise_e + step_e * step_e / 12.0;
    if var <= 0.0 {
        return 0.0;
    }
    lambda * frames.sqrt() / var.sqrt()
}

/// Dynamic range of the `frames`-frame sum of a conventional sensor ([`conventional_snr`]): the
/// smallest λ with SNR >= `snr_threshold` (closed form, the positive root of
/// `n·λ² = t²·(λ + d + σ_r² + q²/12)`) up to the full well, where one frame's mean signal plus
/// dark electrons reaches `full_well_e` (`upper_limit` is then [`UpperLimit::Saturation`]).
///
/// Errors on invalid parameters or if the range is empty.
pub fn conventional_dynamic_range(
    frames: f64,
    dark: f64,
    read_noise_e: f64,
    step_e: f64,
    full_well_e: f64,
    snr_threshold: f64,
) -> Result<DynamicRange> {
    check_model_params(frames, dark)?;
    if !(read_noise_e.is_finite() && read_noise_e >= 0.0 && step_e.is_finite() && step_e >= 0.0) {
        return Err(Error::invalid(format!(
            "read noise {read_noise_e} e- and quantisation step {step_e} e- must be finite and >= 0"
        )));
    }
    if !(snr_threshold.is_finite() && snr_threshold > 0.0) {
        return Err(Error::invalid(format!(
            "SNR threshold must be a positive finite ratio, got {snr_threshold}"
        )));
    }
    let t2 = snr_threshold * snr_threshold;
    let floor = dark + read_noise_e * read_noise_e + step_e * step_e / 12.0;
    let min_flux = (t2 + (t2 * t2 + 4.0 * frames * t2 * floor).sqrt()) / (2.0 * frames);
    let max_flux = full_well_e - dark;
    if max_flux.is_nan() || max_flux <= min_flux {
        return Err(Error::invalid(format!(
            "full well {full_well_e} e- leaves no flux with SNR >= {snr_threshold} (smallest is \
             {min_flux:.4} e- per frame)"
        )));
    }
    Ok(DynamicRange {
        min_flux,
        max_flux,
        upper_limit: UpperLimit::Saturation,
        db: ratio_to_db(max_flux / min_flux),
    })
}

/// Upper tail of the standard normal, Q(z) = P(Z > z) (Abramowitz & Stegun 7.1.26 for erfc,
/// absolute error below 1.5e-7).
pub fn normal_tail(z: f64) -> f64 {
    let x = z.abs() / std::f64::consts::SQRT_2;
    let t = 1.0 / (1.0 + 0.327_591_1 * x);
    let poly = t
        * (0.254_829_592
            + t * (-0.284_496_736
                + t * (1.421_413_741 + t * (-1.453_152_027 + t * 1.061_405_429))));
    let erfc = poly * (-x * x).exp();
    if z >= 0.0 {
        0.5 * erfc
    } else {
        1.0 - 0.5 * erfc
    }
}

/// Equivalent dark counts per frame of a binary jot's read noise: a jot reads 1 when its
/// photoelectrons plus Gaussian read noise of σ = `read_noise_e` exceed 0.5 e- (paper Table 1),
/// so with no photon it still fires with probability Q(0.5/σ). To first order that is a Poisson
/// dark count of mean −ln(1 − Q(0.5/σ)) per frame, which the MLE of Eq. 6 removes like any
/// other dark count (this project's approximation; it ignores the Q(0.5/σ) chance of missing
/// a single photoelectron, a relative gain loss of 1.9 % at σ = 0.24 e-). 0 for σ = 0 (a SPAD).
pub fn read_noise_false_positive_dark(read_noise_e: f64) -> f64 {
    if read_noise_e > 0.0 {
        -(-normal_tail(0.5 / read_noise_e)).ln_1p()
    } else {
        0.0
    }
}

/// The Gaussian–Poisson model of a conventional (multi-bit) pixel (paper §6.1, the model the
/// paper's CMOS comparisons use): during one frame the pixel collects a Poisson number of
/// photoelectrons with mean λ (plus dark electrons d), adds Gaussian read noise of σ_r
/// electrons, and is digitised to `DN = black + e / gain` (rounded, clipped to
/// `0..=saturation_dn`). The flux estimate from the mean of n samples is the linear inversion
///
/// ```text
/// λ̂ = (mean DN − black)·gain − d,     Var(λ̂) = (λ + d + σ_r² + gain²/12) / n
/// ```
///
/// (shot noise + read noise + quantisation). Saturation: a sample at `saturation_dn` is a
/// clipped value; the merge averages it as it is, so a pixel that is saturated in every frame
/// reports [`GaussianPoisson::full_well_e`] − d, the largest flux it can report (the analogue of
/// the binary model's [`saturation_flux`]), never a wrapped or dark value.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GaussianPoisson {
    /// Electrons per digital number.
    pub gain_e_per_dn: f64,
    /// Read noise, electrons RMS.
    pub read_noise_e: f64,
    /// Digital number of zero electrons (pedestal).
    pub black_level_dn: f64,
    /// Largest digital number, `2^bit_depth − 1` (full scale; samples there are saturated).
    pub saturation_dn: f64,
}

impl GaussianPoisson {
    /// Electrons at full scale above the black level: the full well as the ADC sees it.
    pub fn full_well_e(&self) -> f64 {
        (self.saturation_dn - self.black_level_dn) * self.gain_e_per_dn
    }

    /// Noise variance of one frame beyond the photon shot noise, electrons²: read noise plus
    /// uniform quantisation (gain²/12).
    pub fn floor_variance_e2(&self) -> f64 {
        self.read_noise_e * self.read_noise_e + self.gain_e_per_dn * self.gain_e_per_dn / 12.0
    }
}

/// How a frame's samples relate to photon detections.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Readout {
    /// Binary frames (SPAD, jot): a sample is 0 or 1, Bernoulli with P(1) = 1 − exp(−(λ + d))
    /// (paper Eq. 1–6).
    Binary,
    /// Multi-bit frames of a conventional sensor: digital numbers ([`GaussianPoisson`]).
    GaussianPoisson(GaussianPoisson),
}

/// The photon model of one pixel of a capture: the single switch between the paper's binary
/// model (Eq. 2–6) and the Gaussian–Poisson model of a conventional sensor (§6.1). The merge,
/// its robustness and reference (noise of grey values), and the denoiser (noise of the merged
/// flux) all ask it, so both kinds of capture run through the same pipeline.
///
/// Fluxes are in detections per frame (photoelectrons per frame for a conventional sensor);
/// "samples" are what a frame holds per pixel (bits, or digital numbers).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PixelModel {
    /// Dark counts (binary) or dark electrons (conventional) per frame, `d`.
    pub dark_per_frame: f64,
    pub readout: Readout,
}

impl From<f64> for PixelModel {
    /// A binary pixel with `dark_per_frame` dark counts per frame.
    fn from(dark_per_frame: f64) -> Self {
        PixelModel::binary(dark_per_frame)
    }
}

impl PixelModel {
    /// A binary pixel (paper Eq. 2–6) with `dark_per_frame` dark counts per frame.
    pub fn binary(dark_per_frame: f64) -> Self {
        PixelModel {
            dark_per_frame,
            readout: Readout::Binary,
        }
    }

    /// Whether the frames are binary.
    pub fn is_binary(&self) -> bool {
        matches!(self.readout, Readout::Binary)
    }

    /// The largest sample a frame can hold: 1, or the saturation DN.
    pub fn max_sample(&self) -> f64 {
        match self.readout {
            Readout::Binary => 1.0,
            Readout::GaussianPoisson(g) => g.saturation_dn,
        }
    }

    /// Flux λ̂ (dark removed) from the mean sample per frame `mean` over `frames` frames (which
    /// may be fractional, e.g. a merge's effective number): binary, the MLE of Eq. 6
    /// ([`mle_flux`], unclamped, finite at saturation); conventional, the linear inversion of
    /// [`GaussianPoisson`], with a mean at or above full scale read as full scale.
    pub fn flux(&self, mean: f64, frames: f64) -> f64 {
        match self.readout {
            Readout::Binary => mle_flux(mean * frames, frames, self.dark_per_frame),
            Readout::GaussianPoisson(g) => {
                if frames.is_nan() || frames <= 0.0 {
                    return f64::NAN;
                }
                (mean.min(g.saturation_dn) - g.black_level_dn) * g.gain_e_per_dn
                    - self.dark_per_frame
            }
        }
    }

    /// The mean sample per frame at flux `lambda` (the expected value [`PixelModel::flux`]
    /// inverts; ignores clipping).
    pub fn mean_sample(&self, lambda: f64) -> f64 {
        match self.readout {
            Readout::Binary => detection_probability(lambda, self.dark_per_frame),
            Readout::GaussianPoisson(g) => {
                g.black_level_dn + (lambda + self.dark_per_frame) / g.gain_e_per_dn
            }
        }
    }

    /// The largest flux an estimate over `frames` frames can report: [`saturation_flux`] for
    /// binary frames, the full well minus dark for a conventional pixel.
    pub fn saturation_flux(&self, frames: f64) -> f64 {
        match self.readout {
            Readout::Binary => saturation_flux(frames, self.dark_per_frame),
            Readout::GaussianPoisson(g) => g.full_well_e() - self.dark_per_frame,
        }
    }

    /// Variance of one frame's sample whose mean is `mean` (samples²): binomial p(1 − p)
    /// (p clamped to [0, 1]); conventional, shot noise of the electrons above black, read
    /// noise and quantisation, in DN². The noise of grey values in the Wiener reference and
    /// the robustness weights (supplement Eq. 4–6).
    pub fn sample_variance(&self, mean: f64) -> f64 {
        match self.readout {
            Readout::Binary => {
                let p = mean.clamp(0.0, 1.0);
                p * (1.0 - p)
            }
            Readout::GaussianPoisson(g) => {
                let electrons = ((mean - g.black_level_dn) * g.gain_e_per_dn).max(0.0);
                (electrons + g.floor_variance_e2()) / (g.gain_e_per_dn * g.gain_e_per_dn)
            }
        }
    }

    /// Second-order (delta-method) bias E[λ̂] − λ of [`PixelModel::flux`] from a mean sample
    /// `mean` over `frames` frames: binary, ½·f''(p)·p(1 − p)/n = p / (2·n·(1 − p)) for the
    /// convex f(p) = −ln(1 − p) of Eq. 6, with the expected frames without a detection n·(1 − p)
    /// floored at one (the delta method says nothing closer to saturation); conventional, 0
    /// (the inversion is linear). [`crate::merge::MergeAccumulator`] removes it from the fluxes
    /// of single phase bins, whose few frames make it matter.
    pub fn flux_bias(&self, mean: f64, frames: f64) -> f64 {
        match self.readout {
            Readout::Binary => {
                let p = mean.clamp(0.0, 1.0);
                let zeros = (frames * (1.0 - p)).max(1.0);
                p / (2.0 * zeros)
            }
            Readout::GaussianPoisson(_) => 0.0,
        }
    }

    /// Asymptotic variance of the flux estimate λ̂ at flux `lambda` from `frames` frames:
    /// binary, the Cramér–Rao bound p/((1 − p)·n) of [`mle_std`] with p kept below the
    /// saturation count; conventional, (λ + d + σ_r² + gain²/12)/n.
    pub fn flux_variance(&self, lambda: f64, frames: f64) -> f64 {
        match self.readout {
            Readout::Binary => {
                let p = detection_probability(lambda.max(0.0), self.dark_per_frame)
                    .min(1.0 - SATURATION_MARGIN / frames);
                mle_variance_from_probability(p, frames)
            }
            Readout::GaussianPoisson(g) => {
                ((lambda + self.dark_per_frame).max(0.0) + g.floor_variance_e2()) / frames
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn detection_probability_known_points() {
        assert_eq!(detection_probability(0.0, 0.0), 0.0);
        assert!((detection_probability(std::f64::consts::LN_2, 0.0) - 0.5).abs() < 1e-15);
        // Dark counts and photons add in the Poisson rate.
        assert!((detection_probability(0.3, 0.2) - detection_probability(0.5, 0.0)).abs() < 1e-15);
        // Accurate for tiny rates (1 − e^{−x} ≈ x − x²/2).
        let x = 1e-12;
        assert!((detection_probability(x, 0.0) - x).abs() < 1e-24);
    }

    #[test]
    fn conventional_range_ends_at_snr_threshold_and_full_well() {
        let (n, d, r, q) = (240.0, 1.0 / 240.0, 2.4, 1.0);
        let dr = conventional_dynamic_range(n, d, r, q, 1023.0, 1.0).unwrap();
        assert!((conventional_snr(dr.min_flux, n, d, r, q) - 1.0).abs() < 1e-12);
        assert_eq!(dr.max_flux, 1023.0 - d);
        assert!((dr.db - ratio_to_db(dr.max_flux / dr.min_flux)).abs() < 1e-12);
        assert!(conventional_dynamic_range(n, d, r, q, 0.01, 1.0).is_err());
    }

    #[test]
    fn slope_is_the_derivative_and_variance_matches_mle_std() {
        for &(l, d) in &[(1e-3, 0.0), (0.2, 1e-3), (1.5, 0.01), (4.0, 0.0)] {
            let h = 1e-6;
            let fd =
                (detection_probability(l + h, d) - detection_probability(l - h, d)) / (2.0 * h);
            assert!(
                (detection_probability_slope(l, d) - fd).abs() < 1e-8,
                "λ {l} d {d}"
            );
            let n = 500.0;
            let p = detection_probability(l, d);
            let var = mle_variance_from_probability(p, n);
            assert!((var.sqrt() - mle_std(l, n, d)).abs() < 1e-9 * mle_std(l, n, d));
        }
    }

    #[test]
    fn mle_inverts_expected_count() {
        for &l in &[1e-4, 0.01, 0.5, 2.0, 5.0] {
            for &d in &[0.0, 1e-3] {
                let n = 1000.0;
                let s = n * detection_probability(l, d);
                assert!((mle_flux(s, n, d) - l).abs() < 1e-12 * l.max(1.0));
            }
        }
    }
}
