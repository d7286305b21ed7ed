//! Sensor models of paper Table 1 (SPAD, jot, conventional CMOS), the light-level definition and
//! per-pixel dark-count maps with hot pixels.
#![forbid(unsafe_code)]

use crate::error::{Error, Result};
use ndarray::Array2;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

/// The kind of sensor. `FromStr` accepts `spad`, `jot` and `cmos`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum SensorKind {
    /// Single-photon avalanche diode: a binary frame is 1 when at least one photon (or dark
    /// count) is detected (paper Eq. 2).
    #[default]
    Spad,
    /// Quanta image sensor jot: photoelectrons plus Gaussian read noise, thresholded at 0.5 e-.
    Jot,
    /// Conventional CMOS: photoelectrons plus read noise, quantised to `bit_depth` bits.
    Cmos,
}

impl std::str::FromStr for SensorKind {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "spad" => Ok(SensorKind::Spad),
            "jot" => Ok(SensorKind::Jot),
            "cmos" => Ok(SensorKind::Cmos),
            other => Err(Error::invalid(format!(
                "unknown sensor '{other}' (expected spad, jot or cmos)"
            ))),
        }
    }
}

/// Parameters of one sensor (paper Table 1).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SensorModel {
    pub kind: SensorKind,
    /// Frames per second; the exposure of one frame is its inverse.
    pub frame_rate_hz: f64,
    /// Photon detection efficiency (SPAD) or quantum efficiency of the R, G, B filters.
    /// A W pixel sees R + G + B.
    pub quantum_efficiency: [f64; 3],
    /// Mean dark count rate of a normal (not hot) pixel, counts (or e-) per second.
    pub dark_count_rate_hz: f64,
    /// Read noise, electrons RMS (0 for a SPAD).
    pub read_noise_e: f64,
    /// Output bits per frame: 1 for SPAD and jot, 10 for the CMOS sensor.
    pub bit_depth: u32,
    /// Electrons per digital number of a multi-bit sensor (1 for the CMOS sensor, so its 10-bit
    /// full scale is about a 1000 e- full well; unused for binary sensors).
    pub gain_e_per_dn: f64,
    /// Digital number of zero electrons of a multi-bit sensor (the pedestal real sensors add so
    /// that read noise below zero is not clipped): 16 DN for the CMOS sensor, 6.7 σ of its read
    /// noise (this project's choice; Table 1 does not give one). 0 for binary sensors.
    pub black_level_dn: f64,
}

impl SensorModel {
    /// The sensor of paper Table 1: SPAD 24 kfps, PDE 9/14/13 %, 2 cps; jot 1 kfps, QE
    /// 71/79/69 %, 0.24 e- read noise, 0.16 e-/s; CMOS 240 fps, 10 bits, QE 59/65/48 %, 2.4 e-,
    /// 1 e-/s (with this project's 1 e-/DN gain and 16 DN black level).
    pub fn table1(kind: SensorKind) -> SensorModel {
        match kind {
            SensorKind::Spad => SensorModel {
                kind,
                frame_rate_hz: 24_000.0,
                quantum_efficiency: [0.09, 0.14, 0.13],
                dark_count_rate_hz: 2.0,
                read_noise_e: 0.0,
                bit_depth: 1,
                gain_e_per_dn: 1.0,
                black_level_dn: 0.0,
            },
            SensorKind::Jot => SensorModel {
                kind,
                frame_rate_hz: 1_000.0,
                quantum_efficiency: [0.71, 0.79, 0.69],
                dark_count_rate_hz: 0.16,
                read_noise_e: 0.24,
                bit_depth: 1,
                gain_e_per_dn: 1.0,
                black_level_dn: 0.0,
            },
            SensorKind::Cmos => SensorModel {
                kind,
                frame_rate_hz: 240.0,
                quantum_efficiency: [0.59, 0.65, 0.48],
                dark_count_rate_hz: 1.0,
                read_noise_e: 2.4,
                bit_depth: 10,
                gain_e_per_dn: 1.0,
                black_level_dn: 16.0,
            },
        }
    }

    /// Exposure time of one frame, seconds.
    pub fn exposure_s(&self) -> f64 {
        1.0 / self.frame_rate_hz
    }
}

/// Light level of the simulation, in detections (photoelectrons) per pixel per frame.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "mode", rename_all = "kebab-case")]
pub enum FluxSpec {
    /// The mean over the reference frame's pixels of the detections a W pixel would collect per
    /// frame (R + G + B, dark counts excluded) equals `flux`. This pins the bit density: a flat
    /// grey scene at flux F gives W bits at density 1 − exp(−F).
    Mean { flux: f64 },
    /// The `percentile`-th percentile (0–100) of those W detections equals `peak` (for HDR scenes
    /// whose mean is dominated by a light source).
    Percentile { percentile: f64, peak: f64 },
}

impl Default for FluxSpec {
    fn default() -> Self {
        FluxSpec::Mean { flux: 0.1 }
    }
}

impl FluxSpec {
    /// The gain that brings W detections `w` (unscaled, any order) to this light level.
    pub fn gain(&self, w: &[f32]) -> Result<f64> {
        let (target, level) = match *self {
            FluxSpec::Mean { flux } => {
                let mean = w.iter().map(|&v| v as f64).sum::<f64>() / w.len().max(1) as f64;
                (flux, mean)
            }
            FluxSpec::Percentile { percentile, peak } => {
                if !(0.0..=100.0).contains(&percentile) {
                    return Err(Error::invalid(format!(
                        "peak percentile {percentile} is outside 0..100"
                    )));
                }
                let mut sorted = w.to_vec();
                sorted.sort_by(f32::total_cmp);
                let i = ((percentile / 100.0) * (sorted.len().max(1) - 1) as f64).round() as usize;
                (peak, sorted.get(i).copied().unwrap_or(0.0) as f64)
            }
        };
        if !(target.is_finite() && target > 0.0) {
            return Err(Error::invalid(format!("flux {target} must be positive")));
        }
        if level.is_nan() || level <= 0.0 {
            return Err(Error::invalid(
                "the scene is black at the requested flux statistic; cannot scale it",
            ));
        }
        Ok(target / level)
    }
}

/// Per-pixel dark-count rates and the hot-pixel mask.
#[derive(Debug, Clone, PartialEq)]
pub struct DarkCountMap {
    /// Counts per second, (H, W).
    pub rates_hz: Array2<f64>,
    /// Hot pixels, (H, W).
    pub hot_pixels: Array2<bool>,
}

impl DarkCountMap {
    /// Normal pixels get `mean_hz · exp(σZ − σ²/2)` (lognormal with mean `mean_hz`, σ =
    /// `variation`); exactly `round(hot_fraction · H · W)` pixels, chosen at random, are hot with
    /// a rate uniform in `hot_range_hz`.
    pub fn generate(
        height: usize,
        width: usize,
        mean_hz: f64,
        variation: f64,
        hot_fraction: f64,
        hot_range_hz: [f64; 2],
        seed: u64,
    ) -> Result<DarkCountMap> {
        if !(0.0..=1.0).contains(&hot_fraction) {
            return Err(Error::invalid(format!(
                "hot-pixel fraction {hot_fraction} is outside 0..1"
            )));
        }
        if !(hot_range_hz[0] >= 0.0 && hot_range_hz[1] >= hot_range_hz[0]) {
            return Err(Error::invalid(format!(
                "hot-pixel rate range {hot_range_hz:?} must be 0 <= low <= high"
            )));
        }
        if !(mean_hz >= 0.0 && variation >= 0.0) {
            return Err(Error::invalid(
                "dark count rate and its variation must be >= 0",
            ));
        }
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut rates_hz = Array2::from_shape_fn((height, width), |_| {
            let z: f64 = StandardNormal.sample(&mut rng);
            mean_hz * (variation * z - 0.5 * variation * variation).exp()
        });
        let n = height * width;
        let hot = ((hot_fraction * n as f64).round() as usize).min(n);
        // Partial Fisher–Yates: the first `hot` entries of a random permutation.
        let mut order: Vec<usize> = (0..n).collect();
        for i in 0..hot {
            let j = rng.gen_range(i..n);
            order.swap(i, j);
        }
        let mut hot_pixels = Array2::from_elem((height, width), false);
        for &k in &order[..hot] {
            let (y, x) = (k / width, k % width);
            hot_pixels[[y, x]] = true;
            rates_hz[[y, x]] = if hot_range_hz[1] > hot_range_hz[0] {
                rng.gen_range(hot_range_hz[0]..hot_range_hz[1])
            } else {
                hot_range_hz[0]
            };
        }
        Ok(DarkCountMap {
            rates_hz,
            hot_pixels,
        })
    }

    /// Mean rate of the pixels that are not hot (0 when all are hot).
    pub fn mean_normal_rate(&self) -> f64 {
        let (sum, n) = self
            .rates_hz
            .iter()
            .zip(self.hot_pixels.iter())
            .filter(|(_, &h)| !h)
            .fold((0.0, 0usize), |(s, n), (&r, _)| (s + r, n + 1));
        if n == 0 {
            0.0
        } else {
            sum / n as f64
        }
    }
}

pub use crate::model::normal_tail;

/// Binary jot readout (paper Table 1): photoelectrons n ~ Poisson(mean) plus Gaussian read noise
/// of σ = `read_noise_e`, thresholded at 0.5 e-. The bit is 1 with probability
/// Σ_n P(n) · Q((0.5 − n)/σ); n = 0 and n = 1 are summed exactly and n ≥ 2 share the n = 2 term
/// (its miss probability Q(1.5/σ) is below 1e-9 at σ = 0.24 e-). Sampling one uniform against
/// this probability gives the same distribution as drawing n and the noise.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct JotReadout {
    /// P(bit | n = 0, 1, ≥ 2).
    fire: [f64; 3],
}

impl JotReadout {
    /// The readout of a jot with `read_noise_e` electrons RMS.
    pub fn new(read_noise_e: f64) -> JotReadout {
        let fire = if read_noise_e > 0.0 {
            [0.5, -0.5, -1.5].map(|z| normal_tail(z / read_noise_e))
        } else {
            [0.0, 1.0, 1.0]
        };
        JotReadout { fire }
    }

    /// Probability that the jot reads 1 at `mean` photoelectrons (signal plus dark).
    #[inline]
    pub fn one_probability(&self, mean: f64) -> f64 {
        let p0 = (-mean).exp();
        let p1 = mean * p0;
        p0 * self.fire[0] + p1 * self.fire[1] + (1.0 - p0 - p1).max(0.0) * self.fire[2]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn normal_tail_known_values() {
        assert!((normal_tail(0.0) - 0.5).abs() < 1e-7);
        assert!((normal_tail(1.959_964) - 0.025).abs() < 1e-6);
        assert!((normal_tail(-1.0) - 0.841_344_7).abs() < 1e-6);
    }

    #[test]
    fn jot_probability_limits() {
        // Without read noise a jot is a photon-number threshold at 1: same as a SPAD.
        let m: f64 = 0.3;
        assert!((JotReadout::new(0.0).one_probability(m) - (1.0 - (-m).exp())).abs() < 1e-12);
        // In the dark, only read noise above 0.5 e- fires: Q(0.5 / 0.24) ≈ 0.0186.
        assert!((JotReadout::new(0.24).one_probability(0.0) - 0.018_610).abs() < 1e-4);
    }

    #[test]
    fn flux_gain_mean_and_percentile() {
        let w = [1.0f32, 2.0, 3.0, 4.0, 100.0];
        let g = FluxSpec::Mean { flux: 1.1 }.gain(&w).unwrap();
        assert!((g - 1.1 / 22.0).abs() < 1e-12);
        let g = FluxSpec::Percentile {
            percentile: 50.0,
            peak: 6.0,
        }
        .gain(&w)
        .unwrap();
        assert!((g - 2.0).abs() < 1e-12);
        assert!(FluxSpec::Mean { flux: -1.0 }.gain(&w).is_err());
        assert!(FluxSpec::Mean { flux: 1.0 }.gain(&[0.0]).is_err());
    }
}
