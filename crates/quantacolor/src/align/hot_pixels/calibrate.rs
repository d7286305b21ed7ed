//! Hot pixels found: from dark frames (the dark-count rate map of supplement §1.4) or, for a
//! capture without a mask, from its own frames (this project's own heuristic).

#![forbid(unsafe_code)]

use crate::capture::BinaryFrames;
use crate::cfa::Cfa;
use crate::error::{Error, Result};
use crate::model::{
    detection_probability, mle_flux, mle_variance_from_probability, SATURATION_MARGIN,
};
use ndarray::Array2;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Dark-count rate of every pixel (counts per second, `(H, W)`) from frames captured in the dark:
/// the Bernoulli maximum-likelihood estimate λ = −ln(1 − k/T) / τ (paper Eq. 6 with no light),
/// where `k` is the pixel's count over all T frames and τ = `exposure_s` the exposure of one
/// binary frame in seconds. A pixel that fired in every frame gets the rate of k = T − ½.
pub fn dark_count_rate_map(frames: &BinaryFrames, exposure_s: f64) -> Result<Array2<f32>> {
    if exposure_s.is_nan() || exposure_s <= 0.0 || exposure_s.is_infinite() {
        return Err(Error::invalid(format!(
            "binary-frame exposure must be a positive number of seconds, got {exposure_s}"
        )));
    }
    let t = frames.frame_count() as f64;
    let sums = frames.sum_range(0..frames.frame_count());
    Ok(sums.mapv(|k| (mle_flux(k as f64, t, 0.0) / exposure_s) as f32))
}

/// Pixels whose dark-count rate exceeds `threshold_cps` (counts per second).
pub fn hot_pixel_mask(rate_map: &Array2<f32>, threshold_cps: f32) -> Array2<bool> {
    rate_map.mapv(|r| r > threshold_cps)
}

/// Settings of hot-pixel self-calibration ([`detect_hot_pixels`]). This detector is the
/// project's own heuristic (the paper calibrates hot pixels from dark frames, supplement §1.4).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct HotPixelDetectConfig {
    /// Nearest same-colour pixels a pixel is compared with (default 24: about the first three
    /// rings of a colour's sites, so that detail at the pixel pitch (gratings, dot patterns)
    /// has bright sites among them; with 8 the built-in chart's finest gratings were flagged).
    pub neighbours: usize,
    /// The pixel is compared with the `rank`-th brightest of those neighbours (default 3): a
    /// few neighbours on the same bright line, edge, grating or highlight keep a scene feature
    /// from being flagged, and one or two hot neighbours cannot hide a hot pixel.
    pub rank: usize,
    /// A hot pixel's flux exceeds the reference by at least this factor (default 1.5).
    pub min_ratio: f64,
    /// ... and by at least this many binomial standard deviations of the reference's estimate
    /// over the whole burst (default 6: about one false alarm per 10^9 pixels by noise alone).
    pub z: f64,
}

impl Default for HotPixelDetectConfig {
    fn default() -> Self {
        HotPixelDetectConfig {
            neighbours: 24,
            rank: 3,
            min_ratio: 1.5,
            z: 6.0,
        }
    }
}

/// The `k` nearest pixels (Euclidean, ties in row-major order) of `(y0, x0)` for which
/// `accept(y, x)` holds, excluding `(y0, x0)` itself.
pub(super) fn nearest_where(
    (h, w): (usize, usize),
    (y0, x0): (usize, usize),
    k: usize,
    accept: impl Fn(usize, usize) -> bool,
) -> Vec<(usize, usize)> {
    let (y0, x0) = (y0 as isize, x0 as isize);
    let max_r = h.max(w) as isize;
    let mut r: isize = 2;
    loop {
        let mut found: Vec<(isize, usize, usize)> = Vec::new();
        for y in (y0 - r).max(0)..=(y0 + r).min(h as isize - 1) {
            for x in (x0 - r).max(0)..=(x0 + r).min(w as isize - 1) {
                if (y, x) != (y0, x0) && accept(y as usize, x as usize) {
                    found.push(((y - y0).pow(2) + (x - x0).pow(2), y as usize, x as usize));
                }
            }
        }
        found.sort_unstable();
        if (found.len() >= k && found[k - 1].0 <= r * r) || r >= max_r {
            found.truncate(k);
            return found.into_iter().map(|(_, y, x)| (y, x)).collect();
        }
        r *= 2;
    }
}

/// Hot pixels found in an ordinary capture (no dark frames): pixels whose flux over the whole
/// burst is far above their same-colour neighbourhood. This is the project's own heuristic;
/// the paper's hot pixels come from a dark calibration ([`dark_count_rate_map`]).
///
/// Each pixel's flux λ̂ is the MLE of paper Eq. 6 from its count over all T frames. Its
/// reference is the `rank`-th largest λ̂ among its `neighbours` nearest same-colour pixels.
/// The pixel is hot when λ̂ > max(`min_ratio` · ref, ref + `z` · σ), σ being the binomial
/// standard deviation of the MLE at the reference flux over T frames (firing probability
/// floored at 2/T so that an all-dark neighbourhood does not make a handful of counts
/// significant). An R, G or B pixel must also exceed the physical bound set by its W
/// neighbours: behind filter c a pixel sees at most W / w_c, since W = wR·R + wG·G + wB·B
/// (the second largest W of its 3x3 neighbourhood is used).
///
/// Scene features are protected by the rank (a bright line or edge through the pixel also
/// lights at least two same-colour neighbours or the W neighbours) and by motion (a moving
/// camera smears them over the burst); a static single-pixel point of light cannot be told
/// from a hot pixel and is flagged, which costs only that pixel's own samples.
pub fn detect_hot_pixels(
    frames: &BinaryFrames,
    cfa: &Cfa,
    w_weights: [f64; 3],
    config: &HotPixelDetectConfig,
) -> Result<Array2<bool>> {
    let (h, w) = (cfa.height(), cfa.width());
    if (frames.height(), frames.width()) != (h, w) {
        return Err(Error::invalid(format!(
            "frames are {}x{}, the CFA is {h}x{w}",
            frames.height(),
            frames.width()
        )));
    }
    if config.neighbours == 0 || config.rank == 0 || config.rank > config.neighbours {
        return Err(Error::invalid(format!(
            "hot-pixel detection needs 1 <= rank ({}) <= neighbours ({})",
            config.rank, config.neighbours
        )));
    }
    if !(config.min_ratio.is_finite() && config.min_ratio >= 1.0 && config.z.is_finite()) {
        return Err(Error::invalid(format!(
            "hot-pixel detection needs min_ratio >= 1 and a finite z, got {} and {}",
            config.min_ratio, config.z
        )));
    }
    let t = frames.frame_count() as f64;
    let counts = frames.sum_range(0..frames.frame_count());
    let flux = counts.mapv(|k| mle_flux(k as f64, t, 0.0));
    let codes = cfa.codes();
    let w_code = crate::cfa::Channel::W.code();
    let p_floor = (2.0 / t).min(0.5);
    let mut mask = Array2::<bool>::from_elem((h, w), false);
    mask.axis_iter_mut(ndarray::Axis(0))
        .into_par_iter()
        .enumerate()
        .for_each(|(y, mut row)| {
            for x in 0..w {
                let code = codes[[y, x]];
                let same = nearest_where((h, w), (y, x), config.neighbours, |yy, xx| {
                    codes[[yy, xx]] == code
                });
                if same.len() < config.rank {
                    continue;
                }
                let mut values: Vec<f64> = same.iter().map(|&p| flux[p]).collect();
                values.sort_unstable_by(|a, b| b.total_cmp(a));
                let reference = values[config.rank - 1].max(0.0);
                let p = detection_probability(reference, 0.0)
                    .max(p_floor)
                    .min(1.0 - SATURATION_MARGIN / t);
                let sigma = mle_variance_from_probability(p, t).sqrt();
                let mut threshold =
                    (config.min_ratio * reference).max(reference + config.z * sigma);
                if code != w_code {
                    let weight = w_weights[code as usize];
                    let mut whites: Vec<f64> = (y.saturating_sub(1)..(y + 2).min(h))
                        .flat_map(|yy| {
                            (x.saturating_sub(1)..(x + 2).min(w)).map(move |xx| (yy, xx))
                        })
                        .filter(|&p| codes[p] == w_code)
                        .map(|p| flux[p])
                        .collect();
                    whites.sort_unstable_by(|a, b| b.total_cmp(a));
                    if weight > 0.0 && whites.len() >= 2 {
                        threshold = threshold.max(whites[1] / weight);
                    }
                }
                row[x] = flux[[y, x]] > threshold;
            }
        });
    Ok(mask)
}

/// Gives `capture` a hot-pixel mask detected from its own frames ([`detect_hot_pixels`]) when
/// it names none; returns how many were found, or `None` when the capture had a mask.
pub fn self_calibrate(
    capture: &mut crate::capture::Capture,
    config: &HotPixelDetectConfig,
) -> Result<Option<usize>> {
    if capture.hot_pixels.is_some() {
        return Ok(None);
    }
    let mask = detect_hot_pixels(
        &capture.frames,
        &capture.cfa,
        capture.meta.w_weights,
        config,
    )?;
    let n = mask.iter().filter(|&&m| m).count();
    capture.hot_pixels = Some(mask);
    Ok(Some(n))
}
