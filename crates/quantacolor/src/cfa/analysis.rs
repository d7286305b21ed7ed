//! Spectral analysis of a CFA in the luminance/chrominance model of Alleysson et al. 2005 and
//! Condat 2010 (paper §5, Fig. 9).
//!
//! **Model.** Write a colour `(R, G, B)` in opponent coordinates `L = (R + G + B)/3`,
//! `C1 = R − G`, `C2 = B − (R + G)/2`, so `R = L + C1/2 − C2/3`, `G = L − C1/2 − C2/3`,
//! `B = L + 2·C2/3`. A clear W pixel sees `W = k_W·L` ([`AnalysisConfig::w_gain`], 3 for an
//! ideal clear filter passing R + G + B). With `1_c` the indicator of channel `c`'s pixels,
//! `p_c` its fraction and `ĩ_c = 1_c − p_c`, the mosaic of a colour image is
//!
//! `m(x) = [DC luminance] + M_L(x)·L(x) + M_1(x)·C1(x) + M_2(x)·C2(x)`, with modulation functions
//!
//! - `M_L = (k_W − 1)·ĩ_W` (luminance modulation by the W/colour layout),
//! - `M_1 = (ĩ_R − ĩ_G)/2`,
//! - `M_2 = (2·ĩ_B − ĩ_R − ĩ_G)/3`,
//!
//! all with zero mean (the means make up the baseband luminance `Σ_c p_c·response_c`). The
//! spectrum of `M_1`, `M_2` says where the chrominance is carried: energy near zero frequency
//! overlaps the luminance baseband and aliases incoherently; isolated peaks (periodic patterns)
//! alias coherently (moiré), a smooth high-frequency spread (blue noise) aliases as fine noise.
//!
//! **Scores** (all on the chrominance power `P = |F M_1|² + |F M_2|²`, normalised so that
//! `Σ_f P = Σ_x M_1² + M_2²`):
//! - `baseband_fraction`: share of chroma energy at `|f| < baseband_radius` (1/8 cycle/pixel by
//!   default: half the Nyquist frequency of the 75 % W colour-site lattice);
//! - `peak_fraction`: share of chroma energy in the top `top_fraction` (0.1 %) of frequency bins:
//!   1 for periodic patterns (all energy at a few carriers), about
//!   `top_fraction·(1 + ln(1/top_fraction)) ≈ 0.8 %` for a white (i.i.d.) pattern;
//! - `peak_to_mean`: largest bin over the mean bin;
//! - `chroma_power`: mean of `M_1² + M_2²` per pixel (how much chrominance is modulated at all).
#![forbid(unsafe_code)]

use super::io::{save_png, save_text};
use super::{Cfa, Channel};
use crate::error::{Error, Result};
use image::GrayImage;
use ndarray::{Array2, Zip};
use rayon::prelude::*;
use rustfft::num_complex::Complex;
use rustfft::FftPlanner;
use std::path::Path;

/// Settings of [`analyze`].
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct AnalysisConfig {
    /// Radius of the luminance baseband, cycles/pixel.
    pub baseband_radius: f64,
    /// Share of frequency bins counted as "peaks" by `peak_fraction`.
    pub top_fraction: f64,
    /// Response of a W pixel relative to `L = (R + G + B)/3`.
    pub w_gain: f64,
}

impl Default for AnalysisConfig {
    fn default() -> Self {
        AnalysisConfig {
            baseband_radius: 0.125,
            top_fraction: 0.001,
            w_gain: 3.0,
        }
    }
}

/// Aliasing scores of one CFA (see the module documentation).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SpectralScores {
    pub chroma_power: f64,
    pub baseband_fraction: f64,
    pub peak_fraction: f64,
    pub peak_to_mean: f64,
}

/// Modulation functions and their power spectra (unshifted: bin `(0, 0)` is DC).
#[derive(Debug, Clone)]
pub struct Analysis {
    /// `M_L`, `M_1`, `M_2`, each `(H, W)`.
    pub modulation: [Array2<f64>; 3],
    /// `|F M_L|²/N`, `|F M_1|²/N`, `|F M_2|²/N`.
    pub power: [Array2<f64>; 3],
    /// Chrominance power `power[1] + power[2]`.
    pub chroma: Array2<f64>,
    pub scores: SpectralScores,
}

/// The luminance and chrominance modulation functions `[M_L, M_1, M_2]` of `cfa`.
pub fn modulation_functions(cfa: &Cfa, w_gain: f64) -> [Array2<f64>; 3] {
    let p = cfa.fractions();
    let ind = |c: Channel| -> Array2<f64> {
        let pc = p[c.index()];
        cfa.codes()
            .mapv(|code| if code == c.code() { 1.0 - pc } else { -pc })
    };
    let (r, g, b, w) = (
        ind(Channel::R),
        ind(Channel::G),
        ind(Channel::B),
        ind(Channel::W),
    );
    let ml = w.mapv(|v| (w_gain - 1.0) * v);
    let m1 = Zip::from(&r).and(&g).map_collect(|&r, &g| (r - g) / 2.0);
    let m2 = Zip::from(&r)
        .and(&g)
        .and(&b)
        .map_collect(|&r, &g, &b| (2.0 * b - r - g) / 3.0);
    [ml, m1, m2]
}

/// `|DFT(field)|² / N` (Parseval: the bins sum to `Σ field²`), unshifted.
pub fn power_spectrum(field: &Array2<f64>) -> Array2<f64> {
    let (h, w) = field.dim();
    let mut planner = FftPlanner::<f64>::new();
    let fft_w = planner.plan_fft_forward(w);
    let fft_h = planner.plan_fft_forward(h);
    let mut rows: Vec<Complex<f64>> = field.iter().map(|&v| Complex::new(v, 0.0)).collect();
    rows.par_chunks_mut(w).for_each(|row| fft_w.process(row));
    // Transpose so the columns become contiguous.
    let mut cols = vec![Complex::new(0.0, 0.0); h * w];
    for y in 0..h {
        for x in 0..w {
            cols[x * h + y] = rows[y * w + x];
        }
    }
    cols.par_chunks_mut(h).for_each(|col| fft_h.process(col));
    let n = (h * w) as f64;
    Array2::from_shape_fn((h, w), |(y, x)| cols[x * h + y].norm_sqr() / n)
}

/// Frequency in cycles/pixel of DFT bin `k` of a length-`n` axis, in `[-1/2, 1/2)`.
pub fn bin_frequency(k: usize, n: usize) -> f64 {
    let k = k as f64;
    let n_f = n as f64;
    if k < n_f / 2.0 {
        k / n_f
    } else {
        (k - n_f) / n_f
    }
}

/// Scores of a chrominance power spectrum.
pub fn score(chroma: &Array2<f64>, config: &AnalysisConfig) -> SpectralScores {
    let (h, w) = chroma.dim();
    let total: f64 = chroma.sum();
    let n = chroma.len();
    if total <= 0.0 {
        return SpectralScores {
            chroma_power: 0.0,
            baseband_fraction: 0.0,
            peak_fraction: 0.0,
            peak_to_mean: 0.0,
        };
    }
    let mut baseband = 0.0;
    for ((y, x), &p) in chroma.indexed_iter() {
        let (fy, fx) = (bin_frequency(y, h), bin_frequency(x, w));
        if (fy * fy + fx * fx).sqrt() < config.baseband_radius {
            baseband += p;
        }
    }
    let mut sorted: Vec<f64> = chroma.iter().copied().collect();
    sorted.sort_unstable_by(|a, b| b.total_cmp(a));
    let top = ((n as f64 * config.top_fraction).ceil() as usize).clamp(1, n);
    let peak: f64 = sorted[..top].iter().sum();
    SpectralScores {
        chroma_power: total / n as f64,
        baseband_fraction: baseband / total,
        peak_fraction: peak / total,
        peak_to_mean: sorted[0] / (total / n as f64),
    }
}

/// Modulation functions, spectra and scores of `cfa`.
pub fn analyze(cfa: &Cfa, config: &AnalysisConfig) -> Analysis {
    let modulation = modulation_functions(cfa, config.w_gain);
    let power = [
        power_spectrum(&modulation[0]),
        power_spectrum(&modulation[1]),
        power_spectrum(&modulation[2]),
    ];
    let chroma = &power[1] + &power[2];
    let scores = score(&chroma, config);
    Analysis {
        modulation,
        power,
        chroma,
        scores,
    }
}

/// Radially averaged power: `bins` annuli of equal width over `|f| ∈ [0, 1/√2]`, as
/// `(centre frequency in cycles/pixel, mean power in the annulus)`; empty annuli are skipped.
pub fn radial_profile(power: &Array2<f64>, bins: usize) -> Vec<(f64, f64)> {
    let (h, w) = power.dim();
    let f_max = 0.5f64.hypot(0.5);
    let mut sum = vec![0.0; bins];
    let mut count = vec![0usize; bins];
    for ((y, x), &p) in power.indexed_iter() {
        let f = bin_frequency(y, h).hypot(bin_frequency(x, w));
        let k = ((f / f_max * bins as f64) as usize).min(bins - 1);
        sum[k] += p;
        count[k] += 1;
    }
    (0..bins)
        .filter(|&k| count[k] > 0)
        .map(|k| {
            (
                (k as f64 + 0.5) * f_max / bins as f64,
                sum[k] / count[k] as f64,
            )
        })
        .collect()
}

/// Display range of [`spectrum_image`], dB relative to the reference power.
const DB_RANGE: (f64, f64) = (-30.0, 20.0);

/// A power spectrum as a grey picture: DC at the centre (`fftshift`), `10·log10(P / reference)`
/// mapped linearly from −30 dB (black) to +20 dB (white). Using the mean chrominance power per
/// bin as `reference` makes a white (i.i.d.) spectrum mid-grey and pictures comparable.
pub fn spectrum_image(power: &Array2<f64>, reference: f64) -> GrayImage {
    let (h, w) = power.dim();
    GrayImage::from_fn(w as u32, h as u32, |x, y| {
        let ky = (y as usize + h - h / 2) % h;
        let kx = (x as usize + w - w / 2) % w;
        let p = power[[ky, kx]];
        let v = if p > 0.0 && reference > 0.0 {
            let db = 10.0 * (p / reference).log10();
            ((db - DB_RANGE.0) / (DB_RANGE.1 - DB_RANGE.0)).clamp(0.0, 1.0)
        } else {
            0.0
        };
        image::Luma([(v * 255.0).round() as u8])
    })
}

/// Writes `dir/{pattern.png, luminance.png, chroma1.png, chroma2.png, chroma.png,
/// analysis.toml, radial.csv}` for `cfa` (every file atomically). `label` names the pattern in
/// `analysis.toml`.
pub fn write_analysis(
    dir: &Path,
    label: &str,
    cfa: &Cfa,
    config: &AnalysisConfig,
) -> Result<Analysis> {
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let a = analyze(cfa, config);
    let reference = a.chroma.mean().unwrap_or(0.0);
    save_png(&super::io::to_rgb_image(cfa), dir.join("pattern.png"))?;
    let lum_ref = a.power[0].mean().unwrap_or(0.0);
    save_png(
        &spectrum_image(&a.power[0], lum_ref),
        dir.join("luminance.png"),
    )?;
    save_png(
        &spectrum_image(&a.power[1], reference),
        dir.join("chroma1.png"),
    )?;
    save_png(
        &spectrum_image(&a.power[2], reference),
        dir.join("chroma2.png"),
    )?;
    save_png(
        &spectrum_image(&a.chroma, reference),
        dir.join("chroma.png"),
    )?;

    #[derive(serde::Serialize)]
    struct Report<'a> {
        pattern: &'a str,
        height: usize,
        width: usize,
        fractions: [f64; 4],
        config: &'a AnalysisConfig,
        scores: &'a SpectralScores,
        luminance_modulation_power: f64,
    }
    let report = Report {
        pattern: label,
        height: cfa.height(),
        width: cfa.width(),
        fractions: cfa.fractions(),
        config,
        scores: &a.scores,
        luminance_modulation_power: a.power[0].mean().unwrap_or(0.0),
    };
    let text = toml::to_string_pretty(&report)
        .map_err(|e| Error::invalid(format!("cannot serialise analysis: {e}")))?;
    let header = "# CFA spectral analysis (Alleysson et al. 2005 / Condat 2010; paper Fig. 9).\n\
                  # fractions: R, G, B, W. Scores on chrominance power |F M1|^2 + |F M2|^2.\n";
    save_text(&format!("{header}{text}"), dir.join("analysis.toml"))?;

    let mut csv = String::from("frequency_cycles_per_pixel,luminance_power,chroma_power\n");
    let lum = radial_profile(&a.power[0], 64);
    let chroma = radial_profile(&a.chroma, 64);
    for ((f, l), (_, c)) in lum.iter().zip(&chroma) {
        csv.push_str(&format!("{f:.6},{l:.6e},{c:.6e}\n"));
    }
    save_text(&csv, dir.join("radial.csv"))?;
    Ok(a)
}
