//! Noise-aware low-light visualisation (supplement §4, Eq. 9–10): in the dark, colour vision
//! fades (mesopic/scotopic vision), and the chrominance of a photon-starved reconstruction is
//! mostly noise. Each pixel's colour is blended toward the neutral grey of the same luminance
//! with weight
//!
//! `p(x, y) = clamp((log10 W(x, y) + L0 − C2) / (C1 − C2), 0, 1)`, `C1 = 0`, `C2 = −2`  (Eq. 9)
//!
//! `out = p · RGB + (1 − p) · grey`, `grey = W / (wR + wG + wB)` in every channel  (Eq. 10)
//!
//! The grey keeps `wR·R + wG·G + wB·B` unchanged, so the blend preserves the luminance used to
//! compute `p`.
//!
//! **The unit of W (our definition; the supplement does not state one).** Eq. 9 and 10 are the
//! paper's; the unit is the project's: `W` counts the photon detections a W (clear) pixel
//! collects over the whole capture, in hundreds:
//!
//! `W = T · (wR·R + wG·G + wB·B) / 100`
//!
//! with `R, G, B` the linear reconstruction in detections per frame and `T` the frames merged.
//! With photon (shot) noise the pixel's SNR is `sqrt(100 W)`, so Eq. 9 reads
//! `p = clamp(log10 SNR + L0/2, 0, 1)`: at `L0 = 0` colour is kept in full from SNR 10 (100
//! detections) and gone at SNR 1 (one detection), fading linearly in log SNR between. This ties
//! the view to the noise it is meant to hide, at any frame count and frame rate. At the paper's
//! light levels (thousands of frames at about 0.02–0.1 detections per frame, supplement Fig. 9)
//! an average pixel collects 40–1000 detections and keeps most of its colour (p = 0.8–1), while
//! shadows a decade or two darker fade to grey; with W in detections per frame instead, a
//! capture at 0.02 detections per frame would render almost entirely grey (p = 0.15).
//!
//! `L0` shifts the fade in decades of detections: `L0 = 1` keeps colour down to ten times fewer
//! detections, `L0 = −1` fades it ten times earlier. [`auto_offset`] picks `L0` from the image's
//! measured noise (project heuristic): `L0 = log10(T_eff / T)`, where `T_eff` is the frame count
//! whose photon noise equals the noise measured in the image, so a merge or denoiser that
//! averaged more than `T` frames' worth of noise away keeps proportionally more colour.
#![deny(unsafe_code)]

use crate::error::{Error, Result};
use crate::stats::{median, select_floor_rank};
use ndarray::{Array2, Array3, ArrayView2, ArrayView3, Axis, Zip};
use serde::{Deserialize, Serialize};

/// `C1` of Eq. 9: log10 of `W` (hundreds of detections, plus `L0`) at and above which colour is
/// kept in full.
pub const MESOPIC_C1: f64 = 0.0;
/// `C2` of Eq. 9: log10 of `W` (plus `L0`) at and below which the pixel is grey.
pub const MESOPIC_C2: f64 = -2.0;
/// Detections per unit of `W` (see the module doc).
pub const DETECTIONS_PER_W_UNIT: f64 = 100.0;

/// The offset `L0` of Eq. 9: a number, or chosen from the image's noise ([`auto_offset`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum MesopicOffset {
    Fixed(f32),
    Auto,
}

impl std::str::FromStr for MesopicOffset {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        if s.eq_ignore_ascii_case("auto") {
            return Ok(MesopicOffset::Auto);
        }
        match s.trim().parse::<f32>() {
            Ok(v) if v.is_finite() => Ok(MesopicOffset::Fixed(v)),
            _ => Err(Error::invalid(format!(
                "L0 must be a finite number or 'auto', got '{s}'"
            ))),
        }
    }
}

impl std::fmt::Display for MesopicOffset {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            MesopicOffset::Fixed(v) => write!(f, "{v}"),
            MesopicOffset::Auto => f.write_str("auto"),
        }
    }
}

/// Serialised as a number or the string "auto".
impl Serialize for MesopicOffset {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        match self {
            MesopicOffset::Fixed(v) => s.serialize_f32(*v),
            MesopicOffset::Auto => s.serialize_str("auto"),
        }
    }
}

impl<'de> Deserialize<'de> for MesopicOffset {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        #[derive(Deserialize)]
        #[serde(untagged)]
        enum Raw {
            Number(f64),
            Text(String),
        }
        match Raw::deserialize(d)? {
            Raw::Number(v) if v.is_finite() => Ok(MesopicOffset::Fixed(v as f32)),
            Raw::Number(v) => Err(serde::de::Error::custom(format!(
                "L0 must be finite, got {v}"
            ))),
            Raw::Text(t) => t.parse().map_err(serde::de::Error::custom),
        }
    }
}

/// Options of the noise-aware view.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MesopicConfig {
    /// `L0` of Eq. 9.
    pub l0: MesopicOffset,
    /// Frames merged into the reconstruction (`T` of the module doc; report.toml's
    /// `frames_used`). Needed for a fixed `L0`; with [`MesopicOffset::Auto`] and no frame count
    /// the measured `T_eff` is used directly.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub frames: Option<f64>,
}

/// The resolved parameters of a blend: `W = frames · w/100` and the offset `l0`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MesopicParams {
    pub l0: f64,
    pub frames: f64,
    /// `T_eff` measured from the noise, when `L0` was automatic.
    pub effective_frames: Option<f64>,
}

impl MesopicConfig {
    /// `L0` and `T` for `linear` (H, W, 3): checks the frame count and runs [`auto_offset`]
    /// when asked.
    pub fn resolve(&self, linear: ArrayView3<f32>, w_weights: [f64; 3]) -> Result<MesopicParams> {
        if let Some(t) = self.frames {
            if !(t.is_finite() && t > 0.0) {
                return Err(Error::invalid(format!(
                    "noise-aware view: the frame count must be positive, got {t}"
                )));
            }
        }
        match (self.l0, self.frames) {
            (MesopicOffset::Fixed(l0), Some(frames)) => Ok(MesopicParams {
                l0: l0 as f64,
                frames,
                effective_frames: None,
            }),
            (MesopicOffset::Fixed(_), None) => Err(Error::invalid(
                "noise-aware view with a fixed L0 needs the number of frames merged (report.toml's frames_used beside the image, or --frames); --mesopic auto measures it from the noise",
            )),
            (MesopicOffset::Auto, frames) => {
                let t_eff = effective_frames(linear, w_weights)?;
                Ok(match frames {
                    Some(t) => MesopicParams {
                        l0: (t_eff / t).log10(),
                        frames: t,
                        effective_frames: Some(t_eff),
                    },
                    None => MesopicParams {
                        l0: 0.0,
                        frames: t_eff,
                        effective_frames: Some(t_eff),
                    },
                })
            }
        }
    }
}

/// Colour weight `p` of Eq. 9 for `W` (hundreds of detections over the capture) and offset
/// `l0`; 0 for `w <= 0` or NaN, 1 for `+∞`.
pub fn mesopic_weight(w: f64, l0: f64) -> f64 {
    if w == f64::INFINITY {
        return 1.0;
    }
    if w.is_nan() || w <= 0.0 {
        return 0.0;
    }
    ((w.log10() + l0 - MESOPIC_C2) / (MESOPIC_C1 - MESOPIC_C2)).clamp(0.0, 1.0)
}

fn check_rgb(linear: ArrayView3<f32>) -> Result<()> {
    if linear.dim().2 != 3 {
        return Err(Error::invalid(format!(
            "expected an (H, W, 3) RGB image, got shape {:?}",
            linear.dim()
        )));
    }
    Ok(())
}

fn check_weights(w_weights: [f64; 3]) -> Result<f64> {
    let sum: f64 = w_weights.iter().sum();
    if w_weights.iter().any(|w| !(w.is_finite() && *w >= 0.0)) || sum.is_nan() || sum <= 0.0 {
        return Err(Error::invalid(format!(
            "noise-aware view needs non-negative luminance weights with a positive sum, got {w_weights:?}"
        )));
    }
    Ok(sum)
}

/// Applies Eq. 9–10 to a linear (H, W, 3) image in detections per frame of an R, G or B pixel,
/// merged from `frames` binary frames, with luminance weights `w_weights` (the W pixel's
/// response to R, G, B; `[1, 1, 1]` for simulated captures).
pub fn mesopic_blend(
    linear: ArrayView3<f32>,
    params: &MesopicParams,
    w_weights: [f64; 3],
) -> Result<Array3<f32>> {
    check_rgb(linear)?;
    let sum = check_weights(w_weights)?;
    let (l0, frames) = (params.l0, params.frames);
    if !(l0.is_finite() && frames.is_finite() && frames > 0.0) {
        return Err(Error::invalid(format!(
            "noise-aware view needs a finite L0 and a positive frame count, got L0 = {l0}, T = {frames}"
        )));
    }
    let scale = frames / DETECTIONS_PER_W_UNIT;
    let mut out = Array3::<f32>::zeros(linear.dim());
    Zip::from(out.lanes_mut(Axis(2)))
        .and(linear.lanes(Axis(2)))
        .par_for_each(|mut o, px| {
            let rgb = [px[0] as f64, px[1] as f64, px[2] as f64];
            let w: f64 = (0..3).map(|c| w_weights[c] * rgb[c]).sum();
            let p = mesopic_weight(w * scale, l0);
            let grey = w / sum;
            for c in 0..3 {
                o[c] = (p * rgb[c] + (1.0 - p) * grey) as f32;
            }
        });
    Ok(out)
}

/// Quantile of |residual| that [`effective_frames`] reads the noise from: lower than the median
/// so that texture and edges (large residuals) count even less.
pub const NOISE_QUANTILE: f64 = 0.3;
/// That quantile of |N(0, 1)|: Φ⁻¹(0.65).
const NOISE_QUANTILE_OF_UNIT_NORMAL: f64 = 0.385_32;

/// Box-binning factors at which [`effective_frames`] measures the noise.
pub const NOISE_SCALES: [usize; 3] = [1, 2, 4];

/// Mean of `b` x `b` cells (the last partial row and column dropped).
fn bin(x: ArrayView2<f32>, b: usize) -> Array2<f32> {
    let (h, w) = (x.dim().0 / b, x.dim().1 / b);
    Array2::from_shape_fn((h, w), |(i, j)| {
        let mut s = 0.0f32;
        for y in i * b..(i + 1) * b {
            for xx in j * b..(j + 1) * b {
                s += x[[y, xx]];
            }
        }
        s / (b * b) as f32
    })
}

/// The number of frames `T_eff` whose photon noise matches the noise measured in `linear`
/// (H, W, 3; detections per frame), project heuristic behind `--mesopic auto`.
///
/// Photon noise of a mean over `T` frames has variance `λ/T` (Poisson; the binomial MLE is
/// close below ~0.3 detections per frame, where the blend acts). For every channel and for
/// [`NOISE_SCALES`] `b` (the image binned `b` x `b`, variance `λ/(T b²)` for white noise), the
/// residual to the 3x3 mean, `r = x − mean₃ₓ₃(x)` (variance `8/9` of the pixel's for white
/// noise), is normalised by `sqrt(mean₃ₓ₃)` and its spread taken robustly (the 30th
/// percentile of its absolute value over that of a unit normal, so edges and texture barely
/// count): `T_b = (8/9) / (b² σ²)`. The median of
/// the `T_b` is returned: a demosaic, a merge's kernels or a denoiser leave correlated noise
/// that the pixel scale underrates (too large a `T_1`), while texture inflates the coarsest
/// scale's residuals (too small a `T_4`); for white photon noise all three agree. Measured on
/// simulated naive captures: 0.2–0.3 below the L0 of the noise against the ground truth (the
/// chart's texture reads as noise, so auto errs toward less colour). Pixels darker
/// than 10⁻⁶ of the channel's median are skipped.
/// Errors when there are too few lit pixels to measure (under 64 at the finest scale).
pub fn effective_frames(linear: ArrayView3<f32>, w_weights: [f64; 3]) -> Result<f64> {
    check_rgb(linear)?;
    check_weights(w_weights)?;
    let mut estimates = Vec::new();
    for &b in &NOISE_SCALES {
        let mut z: Vec<f32> = Vec::new();
        for c in 0..3 {
            let plane = linear
                .index_axis(Axis(2), c)
                .mapv(|v| if v.is_finite() { v } else { 0.0 });
            let x = bin(plane.view(), b);
            let (h, w) = x.dim();
            if h < 3 || w < 3 {
                continue;
            }
            let mut lit: Vec<f32> = x.iter().copied().filter(|v| *v > 0.0).collect();
            let floor = median(&mut lit).unwrap_or(0.0) * 1e-6;
            for y in 1..h - 1 {
                for xx in 1..w - 1 {
                    let m = x.slice(ndarray::s![y - 1..y + 2, xx - 1..xx + 2]).sum() / 9.0;
                    if m > floor && m > 0.0 {
                        z.push((x[[y, xx]] - m) / m.sqrt());
                    }
                }
            }
        }
        if z.len() < 64 {
            if b == 1 {
                return Err(Error::invalid(
                    "noise-aware view: too few lit pixels to measure the noise (--mesopic auto); give L0",
                ));
            }
            continue;
        }
        let mut abs: Vec<f32> = z.iter().map(|v| v.abs()).collect();
        let q = select_floor_rank(&mut abs, NOISE_QUANTILE).expect("at least 64 residuals");
        let sigma = q as f64 / NOISE_QUANTILE_OF_UNIT_NORMAL;
        let t_b = if sigma > 0.0 {
            (8.0 / 9.0) / ((b * b) as f64 * sigma * sigma)
        } else {
            f64::INFINITY
        };
        estimates.push(t_b);
    }
    estimates.sort_by(f64::total_cmp);
    let best = estimates
        .get(estimates.len().saturating_sub(1) / 2)
        .copied()
        .unwrap_or(f64::INFINITY);
    if !best.is_finite() {
        return Err(Error::invalid(
            "noise-aware view: the image has no measurable noise (--mesopic auto); give L0",
        ));
    }
    Ok(best)
}

/// `L0 = log10(T_eff / frames)` (see [`effective_frames`]).
pub fn auto_offset(linear: ArrayView3<f32>, w_weights: [f64; 3], frames: f64) -> Result<f64> {
    MesopicConfig {
        l0: MesopicOffset::Auto,
        frames: Some(frames),
    }
    .resolve(linear, w_weights)
    .map(|p| p.l0)
}
