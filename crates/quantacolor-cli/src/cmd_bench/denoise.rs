//! `bench denoise`: chroma-BM3D (paper §4.3) over a grid of σ gains, coarse scales and the
//! flat-area kernel of the merge it runs on, against the default merge without denoising.

#![forbid(unsafe_code)]

use super::suite::{simulate_case, suite};
use super::SuiteSet;
use anyhow::{bail, Context, Result};
use quantacolor::burst::{reconstruct_burst, BurstConfig};
use quantacolor::cfa::colorspad_cfa;
use quantacolor::denoise::chroma::{denoise_linear, DenoiseConfig};
use quantacolor::metrics::{evaluate, EvalOptions, Scores};
use quantacolor::pipeline::{burst_config_for, denoise_input, ReconstructConfig};
use quantacolor::progress::{Progress, Silent};
use quantacolor::simulate::{
    simulate_with_cfa, FluxSpec, MotionConfig, Scene, SimulatedCapture, SimulationConfig,
};
use std::path::Path;
use std::time::Instant;

/// Built-in chart captures for tuning the denoiser (never the quality suite's scenes).
pub(super) fn chart_captures() -> Result<Vec<(String, SimulatedCapture)>> {
    let mut out = Vec::new();
    for (i, (motion, frames, flux)) in [("handheld", 512, 0.1), ("pan", 2000, 0.02)]
        .into_iter()
        .enumerate()
    {
        let config = SimulationConfig {
            frames,
            flux: FluxSpec::Mean { flux },
            motion: motion.parse::<MotionConfig>()?,
            hot_fraction: 0.02,
            seed: 500 + i as u64,
            ..SimulationConfig::default()
        };
        let sim = simulate_with_cfa(
            &config,
            &Scene::from_spec("builtin:chart")?,
            &colorspad_cfa(),
            &Silent,
        )?;
        out.push((format!("chart / {motion} / {frames} frames / {flux}"), sim));
    }
    Ok(out)
}

/// The settings `bench denoise` tries.
pub(super) struct DenoiseGrid {
    pub(super) luma_gains: Vec<f32>,
    pub(super) chroma_gains: Vec<f32>,
    pub(super) merge_k_denoise: Vec<Option<f32>>,
    pub(super) chroma_scales: Vec<usize>,
    pub(super) coarse_sigma_factors: Vec<f32>,
}

/// One setting of the grid.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct DenoiseSetting {
    pub(super) merge_k_denoise: Option<f32>,
    pub(super) luma_gain: f32,
    pub(super) chroma_gain: f32,
    pub(super) chroma_scales: usize,
    pub(super) coarse_sigma_factor: f32,
}

/// The suite's captures of `set` (those whose id contains `only`), simulated.
pub(super) fn suite_captures(
    dir: &Path,
    set: SuiteSet,
    only: Option<&str>,
) -> Result<Vec<(String, SimulatedCapture)>> {
    let captures: Vec<(String, SimulatedCapture)> = suite()
        .iter()
        .filter(|case| set == SuiteSet::All || case.set == set)
        .filter(|case| only.is_none_or(|o| case.id().contains(o)))
        .map(|case| {
            let sim =
                simulate_case(dir, case).with_context(|| format!("simulating {}", case.scene))?;
            Ok((case.label(), sim))
        })
        .collect::<Result<_>>()?;
    if captures.is_empty() {
        bail!("no capture of the suite matches");
    }
    Ok(captures)
}

pub(super) fn denoise_grid(
    captures: &[(String, SimulatedCapture)],
    grid: &DenoiseGrid,
    burst_config: &BurstConfig,
    denoise: &DenoiseConfig,
    progress: &dyn Progress,
) -> Result<()> {
    let settings = grid.settings();
    let mut scores: Vec<Vec<Scores>> = vec![Vec::new(); settings.len()];
    let mut baseline: Vec<Scores> = Vec::new();
    progress.start("denoising grid", captures.len() as u64);
    for (name, sim) in captures {
        let (base, capture_scores) =
            score_denoise_settings(name, sim, grid, &settings, burst_config, denoise)?;
        baseline.push(base);
        for (i, s) in capture_scores {
            scores[i].push(s);
        }
        progress.advance(1);
    }
    progress.finish();
    print_denoise_table(&settings, &scores, &baseline);
    Ok(())
}

/// The scores of the grid's captures' evaluation: 16-px border, the truth's 99.5th percentile.
const DENOISE_EVAL: EvalOptions = EvalOptions {
    border: 16,
    normalize_percentile: Some(99.5),
};

impl DenoiseGrid {
    /// Every setting of the grid (one coarse σ factor only where there are no coarse scales).
    pub(super) fn settings(&self) -> Vec<DenoiseSetting> {
        let mut settings: Vec<DenoiseSetting> = Vec::new();
        for &merge_k_denoise in &self.merge_k_denoise {
            for &luma_gain in &self.luma_gains {
                for &chroma_gain in &self.chroma_gains {
                    for &chroma_scales in &self.chroma_scales {
                        for &coarse_sigma_factor in &self.coarse_sigma_factors {
                            settings.push(DenoiseSetting {
                                merge_k_denoise,
                                luma_gain,
                                chroma_gain,
                                chroma_scales,
                                coarse_sigma_factor,
                            });
                            if chroma_scales == 0 {
                                break;
                            }
                        }
                    }
                }
            }
        }
        settings
    }
}

/// One capture of the grid: the scores of the default merge without denoising (end to end),
/// and `(index in settings, scores)` of every setting (one merge per flat-area kernel, every
/// σ setting denoising it).
fn score_denoise_settings(
    name: &str,
    sim: &SimulatedCapture,
    grid: &DenoiseGrid,
    settings: &[DenoiseSetting],
    burst_config: &BurstConfig,
    denoise: &DenoiseConfig,
) -> Result<(Scores, Vec<(usize, Scores)>)> {
    let capture = sim.to_capture()?;
    let reference = capture.reference_frame();
    let gt = sim.ground_truth.view();
    let plain = reconstruct_burst(&capture, reference, burst_config, &Silent)?;
    let base = evaluate(plain.merged.linear.view(), gt, &DENOISE_EVAL)?;
    eprintln!(
        "{name}: no denoising {:.2} dB / {:.4}",
        base.psnr_srgb, base.ssim_srgb
    );
    let mut scores = Vec::new();
    for &k in &grid.merge_k_denoise {
        let config = ReconstructConfig {
            burst: burst_config.clone(),
            denoise: DenoiseConfig {
                merge_k_denoise: k,
                ..denoise.clone()
            },
            ..ReconstructConfig::default()
        };
        let burst = reconstruct_burst(&capture, reference, &burst_config_for(&config), &Silent)?;
        let input = denoise_input(&capture, Some(&burst), capture.frames.frame_count());
        for (i, setting) in settings
            .iter()
            .enumerate()
            .filter(|(_, s)| s.merge_k_denoise == k)
        {
            let config = DenoiseConfig {
                luma_gain: setting.luma_gain,
                chroma_gain: setting.chroma_gain,
                chroma_scales: setting.chroma_scales,
                coarse_sigma_factor: setting.coarse_sigma_factor,
                ..config.denoise.clone()
            };
            let start = Instant::now();
            let (out, report) = denoise_linear(burst.merged.linear.view(), &input, &config)?;
            let s = evaluate(out.view(), gt, &DENOISE_EVAL)?;
            eprintln!(
                "{name}: {setting:?}: {:.2} dB / {:.4} ({:+.2} dB; {:.2} s, σ {:?})",
                s.psnr_srgb,
                s.ssim_srgb,
                s.psnr_srgb - base.psnr_srgb,
                start.elapsed().as_secs_f64(),
                report.map(|r| r.sigmas)
            );
            scores.push((i, s));
        }
    }
    Ok((base, scores))
}

/// The grid's table: per setting the mean PSNR / SSIM over the captures, the mean gain over no
/// denoising and the smallest gain.
fn print_denoise_table(settings: &[DenoiseSetting], scores: &[Vec<Scores>], baseline: &[Scores]) {
    let n = baseline.len() as f64;
    let base_psnr = baseline.iter().map(|s| s.psnr_srgb).sum::<f64>() / n;
    let base_ssim = baseline.iter().map(|s| s.ssim_srgb).sum::<f64>() / n;
    println!(
        "{} captures; no denoising (default merge): {base_psnr:.2} dB / {base_ssim:.4}",
        baseline.len()
    );
    println!(
        "{:>9} {:>6} {:>7} {:>7} {:>7} {:>10} {:>10} {:>10} {:>10}",
        "merge k",
        "luma",
        "chroma",
        "scales",
        "coarse",
        "mean PSNR",
        "mean SSIM",
        "mean gain",
        "min gain"
    );
    for (k, setting) in settings.iter().enumerate() {
        let psnr = scores[k].iter().map(|s| s.psnr_srgb).sum::<f64>() / n;
        let ssim = scores[k].iter().map(|s| s.ssim_srgb).sum::<f64>() / n;
        let min_gain = scores[k]
            .iter()
            .zip(baseline)
            .map(|(s, b)| s.psnr_srgb - b.psnr_srgb)
            .fold(f64::INFINITY, f64::min);
        println!(
            "{:>9} {:>6} {:>7} {:>7} {:>7} {:>10.2} {:>10.4} {:>+10.2} {:>+10.2}",
            setting
                .merge_k_denoise
                .map_or("merge".into(), |k| k.to_string()),
            setting.luma_gain,
            setting.chroma_gain,
            setting.chroma_scales,
            setting.coarse_sigma_factor,
            psnr,
            ssim,
            psnr - base_psnr,
            min_gain
        );
    }
}
