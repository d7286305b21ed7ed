//! Tone mapping of linear RGB to display-referred linear RGB in [0, 1] (paper §7: the figures of
//! HDR scenes use Mantiuk et al. 2006). Luminance here is Rec. 709 / sRGB `Y` (the image is
//! linear sRGB after colour correction).
#![forbid(unsafe_code)]

use super::exposure::{auto_exposure_scale, percentile};
use super::mantiuk::{display_luminance, process_log_luminance, Mantiuk06Config};
use crate::error::{Error, Result};
use ndarray::{Array2, Array3, ArrayView3, Axis, Zip};
use serde::{Deserialize, Serialize};

/// Rec. 709 / sRGB luminance weights.
pub const REC709_LUMA: [f32; 3] = [0.2126, 0.7152, 0.0722];

/// Parameters of the global operator: Reinhard et al. 2002, "Photographic tone reproduction for
/// digital images", Eq. 1–4: the exposure maps the log-average luminance to `key`, then
/// `L_d = L (1 + L / L_white²) / (1 + L)`, colour ratios kept.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct GlobalConfig {
    /// Key: the display value of the log-average luminance (Reinhard's `a`; 0.18 = middle grey).
    pub key: f32,
    /// Percentile of scaled luminance taken as the white point `L_white` (100 = the maximum).
    pub white_percentile: f64,
}

impl Default for GlobalConfig {
    fn default() -> Self {
        GlobalConfig {
            key: 0.18,
            white_percentile: 99.9,
        }
    }
}

/// The tone-mapping operator.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "operator", rename_all = "lowercase")]
pub enum ToneMap {
    /// Mantiuk et al. 2006 contrast mapping (see [`super::mantiuk`]).
    Mantiuk06(Mantiuk06Config),
    /// Reinhard 2002 global operator.
    Global(GlobalConfig),
    /// Exposure only, clipped at 1.
    None,
}

/// The global operator (see [`super::render::RenderOptions`] for why).
impl Default for ToneMap {
    fn default() -> Self {
        ToneMap::Global(GlobalConfig::default())
    }
}

/// The operator named `mantiuk06`, `global` or `none`, with its published defaults (the names
/// of `--tonemap`).
impl std::str::FromStr for ToneMap {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "mantiuk06" => Ok(ToneMap::Mantiuk06(Mantiuk06Config::default())),
            "global" => Ok(ToneMap::Global(GlobalConfig::default())),
            "none" => Ok(ToneMap::None),
            other => Err(Error::invalid(format!(
                "unknown tone map '{other}' (available: mantiuk06, global, none)"
            ))),
        }
    }
}

fn luminance(px: &[f32]) -> f32 {
    REC709_LUMA[0] * px[0] + REC709_LUMA[1] * px[1] + REC709_LUMA[2] * px[2]
}

/// Non-finite and negative values (noise after colour correction) become 0.
fn sanitise(linear: ArrayView3<f32>) -> Array3<f32> {
    linear.mapv(|v| if v.is_finite() { v.max(0.0) } else { 0.0 })
}

/// Tone maps a linear (H, W, 3) image to display-referred linear RGB in [0, 1].
///
/// `exposure` scales the input first; `None` picks it automatically: the 99.5th percentile of
/// the brightest channel to white for [`ToneMap::None`] ([`auto_exposure_scale`]), the key on the
/// log-average luminance for [`ToneMap::Global`]; Mantiuk06 is (up to its luminance floor)
/// invariant to the exposure.
pub fn tone_map(
    linear: ArrayView3<f32>,
    exposure: Option<f32>,
    op: &ToneMap,
) -> Result<Array3<f32>> {
    if linear.dim().2 != 3 {
        return Err(Error::invalid(format!(
            "expected an (H, W, 3) RGB image, got shape {:?}",
            linear.dim()
        )));
    }
    if let Some(e) = exposure {
        if !(e.is_finite() && e > 0.0) {
            return Err(Error::invalid(format!(
                "exposure must be a positive number, got {e}"
            )));
        }
    }
    let img = sanitise(linear);
    Ok(match op {
        ToneMap::None => {
            let s = exposure.unwrap_or_else(|| auto_exposure_scale(img.view()));
            img.mapv(|v| (v * s).clamp(0.0, 1.0))
        }
        ToneMap::Global(cfg) => global(img, exposure, None, cfg)?,
        ToneMap::Mantiuk06(cfg) => mantiuk06(img, exposure.unwrap_or(1.0), cfg)?,
    })
}

/// Exposure of the global operator: `key` over the log-average luminance (Reinhard Eq. 1; δ
/// avoids log 0); 1 for a black image.
fn key_exposure(lum: &[f32], key: f32) -> f64 {
    let max = lum.iter().copied().fold(0.0f32, f32::max) as f64;
    let delta = 1e-6 * max.max(f64::MIN_POSITIVE);
    let mean_log =
        lum.iter().map(|&l| (l as f64 + delta).ln()).sum::<f64>() / lum.len().max(1) as f64;
    let avg = mean_log.exp();
    if avg > 0.0 {
        key as f64 / avg
    } else {
        1.0
    }
}

/// The exposure [`ToneMap::Global`] with `cfg` would choose for `linear` (H, W, 3): to render
/// several images (e.g. reconstructions and their ground truth) at one exposure.
pub fn global_exposure(linear: ArrayView3<f32>, cfg: &GlobalConfig) -> f32 {
    let img = sanitise(linear);
    let lum: Vec<f32> = img
        .lanes(Axis(2))
        .into_iter()
        .map(|p| luminance(&[p[0], p[1], p[2]]))
        .collect();
    key_exposure(&lum, cfg.key) as f32
}

/// The global operator with both its settings given: `exposure` and the white point `white`
/// (scaled luminance), e.g. those [`global_exposure`] and [`global_white`] pick for a reference
/// image, so that several images render alike.
pub fn tone_map_global(
    linear: ArrayView3<f32>,
    exposure: f32,
    white: f32,
    cfg: &GlobalConfig,
) -> Result<Array3<f32>> {
    if !(exposure.is_finite() && exposure > 0.0 && white.is_finite() && white > 0.0) {
        return Err(Error::invalid(format!(
            "global tone map: exposure {exposure} and white point {white} must be positive"
        )));
    }
    global(sanitise(linear), Some(exposure), Some(white as f64), cfg)
}

/// The white point [`ToneMap::Global`] with `cfg` picks for `linear` at `exposure`: the
/// `white_percentile` of the scaled luminance (1 for a black image).
pub fn global_white(linear: ArrayView3<f32>, exposure: f32, cfg: &GlobalConfig) -> f32 {
    let img = sanitise(linear);
    let lum = img
        .lanes(Axis(2))
        .into_iter()
        .map(|p| luminance(&[p[0], p[1], p[2]]) * exposure);
    percentile(lum, cfg.white_percentile)
        .filter(|w| *w > 0.0)
        .unwrap_or(1.0)
}

fn global(
    mut img: Array3<f32>,
    exposure: Option<f32>,
    white: Option<f64>,
    cfg: &GlobalConfig,
) -> Result<Array3<f32>> {
    if !(cfg.key.is_finite() && cfg.key > 0.0 && (0.0..=100.0).contains(&cfg.white_percentile)) {
        return Err(Error::invalid(
            "global tone map: key must be positive, white percentile in 0..=100",
        ));
    }
    let lum: Vec<f32> = img
        .lanes(Axis(2))
        .into_iter()
        .map(|p| luminance(&[p[0], p[1], p[2]]))
        .collect();
    let scale = match exposure {
        Some(e) => e as f64,
        None => key_exposure(&lum, cfg.key),
    };
    let white = white.unwrap_or_else(|| {
        percentile(lum.iter().map(|&l| l * scale as f32), cfg.white_percentile)
            .filter(|w| *w > 0.0)
            .unwrap_or(1.0) as f64
    });
    Zip::from(img.lanes_mut(Axis(2))).par_for_each(|mut px| {
        let l = luminance(&[px[0], px[1], px[2]]) as f64 * scale;
        if l > 0.0 {
            let ld = l * (1.0 + l / (white * white)) / (1.0 + l);
            let k = (ld / l * scale) as f32;
            for c in 0..3 {
                px[c] = (px[c] * k).clamp(0.0, 1.0);
            }
        } else {
            px.fill(0.0);
        }
    });
    Ok(img)
}

/// Luminance floor relative to the 99.5th percentile (six decades below it) before the log.
const MANTIUK_FLOOR: f32 = 1e-6;

fn mantiuk06(img: Array3<f32>, exposure: f32, cfg: &Mantiuk06Config) -> Result<Array3<f32>> {
    let valid = cfg.contrast_factor > 0.0
        && cfg.contrast_factor <= 1.0
        && cfg.saturation_factor.is_finite()
        && cfg.saturation_factor >= 0.0
        && cfg.detail_factor.is_finite()
        && cfg.detail_factor > 0.0
        && cfg.tolerance > 0.0;
    if !valid {
        return Err(Error::invalid(
            "mantiuk06: contrast factor in (0, 1], saturation factor >= 0, detail factor > 0, tolerance > 0",
        ));
    }
    let (h, w, _) = img.dim();
    let lum = Array2::from_shape_fn((h, w), |(y, x)| {
        exposure * luminance(&[img[[y, x, 0]], img[[y, x, 1]], img[[y, x, 2]]])
    });
    let top = percentile(lum.iter().copied(), 99.5).unwrap_or(0.0);
    if top.is_nan() || top <= 0.0 {
        return Ok(Array3::zeros(img.dim()));
    }
    let floor = top * MANTIUK_FLOOR;
    let log_lum = lum.mapv(|l| l.max(floor).log10());
    let solution = process_log_luminance(log_lum.view(), cfg);
    let display = display_luminance(solution.log_luminance.view());
    let s = cfg.saturation_factor;
    let mut out = img;
    Zip::from(out.lanes_mut(Axis(2)))
        .and(&lum)
        .and(&display)
        .par_for_each(|mut px, &l, &ld| {
            let l = l / exposure;
            let floor = floor / exposure;
            for c in 0..3 {
                // (C / L)^s · L'; a pixel darker than the floor is shown grey.
                let ratio = if l > floor { px[c] / l } else { 1.0 };
                px[c] = (ratio.powf(s) * ld).clamp(0.0, 1.0);
            }
        });
    Ok(out)
}
