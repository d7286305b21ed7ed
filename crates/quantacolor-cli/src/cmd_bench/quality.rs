//! `bench quality`: every method of [`METHODS`] on each capture of the suite, scored against
//! the simulator's ground truth (PSNR / SSIM / LPIPS, paper §6), with alignment end-point error
//! and super-resolution at scale 2; the Markdown report is written by [`super::markdown`].

#![forbid(unsafe_code)]

use super::markdown::report;
use super::splat::{blur_sigma, true_motion_splat};
use super::suite::{simulate_case, suite, Case};
use super::SuiteSet;
use anyhow::{bail, Context, Result};
use ndarray::ArrayView3;
use quantacolor::burst::{
    reconstruct_burst, reconstruct_burst_with_motion, BurstConfig, BurstReconstruction,
    MotionOracle,
};
use quantacolor::capture::Capture;
use quantacolor::denoise::chroma::{denoise_linear, DenoiseConfig, DenoiseMethod};
use quantacolor::filters::bicubic_upsample;
use quantacolor::metrics::{evaluate, evaluate_lpips, measurable_light_ratio, EvalOptions, Scores};
use quantacolor::naive::{reconstruct_naive, NaiveConfig};
use quantacolor::pipeline::{burst_config_for, denoise_input, ReconstructConfig};
use quantacolor::progress::{Progress, Silent};
use quantacolor::simulate::{Motion, SimulatedCapture};
use quantacolor::stats::median_f64;
use std::path::Path;
use std::time::Instant;

pub(super) const METHODS: [&str; 8] = [
    "burst",
    "burst (true motion)",
    "true-motion splat",
    "naive long",
    "naive short",
    "burst, denoiser's merge, no denoising",
    "burst + BM3D",
    "burst + chroma-BM3D",
];
pub(super) const BURST: usize = 0;
pub(super) const TRUE_MOTION: usize = 1;
pub(super) const SPLAT: usize = 2;
pub(super) const LONG: usize = 3;
pub(super) const SHORT: usize = 4;
pub(super) const DENOISER_MERGE: usize = 5;
pub(super) const BM3D: usize = 6;
pub(super) const CHROMA: usize = 7;

/// Scores of the 2x-detail captures against the 2x ground truth.
pub(super) struct SuperResolution {
    /// The 1x burst upsampled by bicubic interpolation.
    pub(super) bicubic: Scores,
    /// The burst merged at scale 2.
    pub(super) scale2: Scores,
    /// The true-motion merge at scale 2 (what scale 2 can give with perfect alignment).
    pub(super) scale2_true: Scores,
    /// The 1x ground truth upsampled by bicubic interpolation: how much of the 2x truth lies
    /// beyond what interpolation of a perfect 1x image recovers (lower = more sub-pixel detail).
    pub(super) bicubic_truth: Scores,
}

/// PSNR / SSIM and LPIPS of every method of [`METHODS`], in order.
type MethodScores = [(Scores, f64); 8];

/// One row of the report.
pub(super) struct Row {
    pub(super) case: usize,
    pub(super) scores: [Scores; 8],
    /// LPIPS (AlexNet v0.1) of each column, on the same sRGB images as `scores`.
    pub(super) lpips: [f64; 8],
    /// Sharpness: the σ (px) of the Gaussian blur of the ground truth that the burst (without
    /// denoising) and the true-motion splat match best ([`blur_sigma`]).
    pub(super) blur_sigma: [f64; 2],
    /// Light kept over the measurable pixels ([`measurable_light_ratio`]) by the burst without
    /// denoising and by the default (burst + chroma-BM3D); `None` where nothing is measurable.
    pub(super) light: [Option<f64>; 2],
    /// Median alignment end-point error, px.
    pub(super) epe: f64,
    /// Median true motion, px (at the same pixels and frames).
    pub(super) motion_px: f64,
    pub(super) sr: Option<SuperResolution>,
    pub(super) seconds: f64,
}

/// Median over pixels (`border` excluded) and over 16 evenly spaced frames of the end-point
/// error |merge flow − true flow|, px, and of the true motion |true flow| (the error of
/// assuming no motion), px.
fn median_epe(
    burst: &BurstReconstruction,
    motion: &Motion,
    frames: usize,
    border: usize,
) -> (f64, f64) {
    const SAMPLES: usize = 16;
    let (h, w) = burst.alignment.grey[0].dim();
    let mut errors: Vec<f32> = Vec::new();
    let mut magnitudes: Vec<f32> = Vec::new();
    for k in 0..SAMPLES {
        let t = (k as f64 + 0.5) * frames as f64 / SAMPLES as f64 - 0.5;
        let est = burst.merge_flow(t);
        let truth = motion.dense_flow(t, h, w);
        for y in border..h.saturating_sub(border) {
            for x in border..w.saturating_sub(border) {
                let dy = est[[y, x, 0]] - truth[[y, x, 0]];
                let dx = est[[y, x, 1]] - truth[[y, x, 1]];
                errors.push(dy.hypot(dx));
                magnitudes.push(truth[[y, x, 0]].hypot(truth[[y, x, 1]]));
            }
        }
    }
    (median_f64(&mut errors), median_f64(&mut magnitudes))
}

/// Runs every method on one capture: simulate it, reconstruct and score every column
/// ([`score_methods`]), measure the alignment error, and score super-resolution on 2x-detail
/// captures ([`super_resolution`]).
fn run_case(
    scenes: &Path,
    index: usize,
    case: &Case,
    opts: &EvalOptions,
    burst_config: &BurstConfig,
) -> Result<Row> {
    let started = Instant::now();
    let sim = simulate_case(scenes, case).with_context(|| format!("simulating {}", case.scene))?;
    let simulated_s = started.elapsed().as_secs_f64();
    let capture = sim.to_capture()?;
    let (h, w) = (capture.cfa.height(), capture.cfa.width());
    let oracle = |t: f64| sim.motion.dense_flow(t, h, w);
    let (burst, scored, Sharpness { blur_sigma, light }) =
        score_methods(&capture, &sim, case, opts, burst_config, &oracle)?;
    let scores = scored.map(|(s, _)| s);
    let lpips = scored.map(|(_, l)| l);
    let (epe, motion_px) = median_epe(&burst, &sim.motion, case.frames, opts.border);
    let sr = super_resolution(&capture, &sim, case, opts, burst_config, &oracle, &burst)?;
    let row = Row {
        case: index,
        scores,
        lpips,
        blur_sigma,
        light,
        epe,
        motion_px,
        sr,
        seconds: started.elapsed().as_secs_f64(),
    };
    log_case(case, &row, simulated_s);
    Ok(row)
}

/// What [`score_methods`] measures beside the scores: [`Row::blur_sigma`] and [`Row::light`].
struct Sharpness {
    blur_sigma: [f64; 2],
    light: [Option<f64>; 2],
}

/// Reconstructs `capture` by every method of [`METHODS`] (burst, burst at the true motion
/// `oracle`, the independent true-motion splat, naive long and short, the denoiser's merge alone and with both denoisers) and
/// scores each against the ground truth (PSNR / SSIM and LPIPS, one protocol); returns the
/// burst reconstruction with the scores, in [`METHODS`] order, and the blur σ of the burst and
/// of the splat.
fn score_methods(
    capture: &Capture,
    sim: &SimulatedCapture,
    case: &Case,
    opts: &EvalOptions,
    burst_config: &BurstConfig,
    oracle: MotionOracle<'_>,
) -> Result<(BurstReconstruction, MethodScores, Sharpness)> {
    let reference = capture.reference_frame();
    let config = burst_config.clone();
    let burst = reconstruct_burst(capture, reference, &config, &Silent)?;
    let truth = reconstruct_burst_with_motion(capture, reference, &config, Some(oracle), &Silent)?;
    let splat = true_motion_splat(capture, &sim.motion)?;
    let long = reconstruct_naive(capture, reference, &NaiveConfig::default())?;
    let short = reconstruct_naive(
        capture,
        reference,
        &NaiveConfig {
            window: Some((case.frames / 16).max(1)),
        },
    )?;
    let gt = sim.ground_truth.view();
    // The merge the denoiser runs on (narrower colour kernels, see DenoiseConfig).
    let denoised_config = ReconstructConfig {
        burst: burst_config.clone(),
        ..ReconstructConfig::default()
    };
    let for_denoising = reconstruct_burst(
        capture,
        reference,
        &burst_config_for(&denoised_config),
        &Silent,
    )?;
    let input = denoise_input(capture, Some(&for_denoising), case.frames);
    // PSNR / SSIM and LPIPS of one reconstruction, under the same protocol.
    let score = |image: ArrayView3<f32>| -> Result<(Scores, f64)> {
        Ok((evaluate(image, gt, opts)?, evaluate_lpips(image, gt, opts)?))
    };
    let denoise = |method| -> Result<_> {
        let config = DenoiseConfig {
            method,
            ..denoised_config.denoise.clone()
        };
        Ok(denoise_linear(for_denoising.merged.linear.view(), &input, &config)?.0)
    };
    let chroma = denoise(DenoiseMethod::ChromaBm3d)?;
    let scored = [
        score(burst.merged.linear.view())?,
        score(truth.merged.linear.view())?,
        score(splat.view())?,
        score(long.linear.view())?,
        score(short.linear.view())?,
        score(for_denoising.merged.linear.view())?,
        score(denoise(DenoiseMethod::Bm3d)?.view())?,
        score(chroma.view())?,
    ];
    let light = |image: ArrayView3<f32>| {
        measurable_light_ratio(image, gt, capture.meta.w_weights, case.frames, opts.border)
    };
    let sharpness = Sharpness {
        blur_sigma: [
            blur_sigma(burst.merged.linear.view(), gt, opts)?,
            blur_sigma(splat.view(), gt, opts)?,
        ],
        light: [light(burst.merged.linear.view())?, light(chroma.view())?],
    };
    Ok((burst, scored, sharpness))
}

/// Super-resolution scores of a 2x-detail capture (`None` for the others): the burst merged at
/// the case's scale, estimated and true motion, against the 1x `burst` and the 1x ground truth
/// upsampled by bicubic interpolation, all against the 2x ground truth.
fn super_resolution(
    capture: &Capture,
    sim: &SimulatedCapture,
    case: &Case,
    opts: &EvalOptions,
    burst_config: &BurstConfig,
    oracle: MotionOracle<'_>,
    burst: &BurstReconstruction,
) -> Result<Option<SuperResolution>> {
    let Some(gt_hr) = &sim.ground_truth_hr else {
        return Ok(None);
    };
    let reference = capture.reference_frame();
    let s = case.supersampling;
    let hr_opts = EvalOptions {
        border: opts.border * s,
        ..*opts
    };
    let mut config_s = burst_config.clone();
    config_s.merge.accumulate.scale = s;
    let scaled = reconstruct_burst(capture, reference, &config_s, &Silent)?;
    let scaled_true =
        reconstruct_burst_with_motion(capture, reference, &config_s, Some(oracle), &Silent)?;
    let bicubic = bicubic_upsample(burst.merged.linear.view(), s);
    let gt = sim.ground_truth.view();
    Ok(Some(SuperResolution {
        bicubic: evaluate(bicubic.view(), gt_hr.view(), &hr_opts)?,
        scale2: evaluate(scaled.merged.linear.view(), gt_hr.view(), &hr_opts)?,
        scale2_true: evaluate(scaled_true.merged.linear.view(), gt_hr.view(), &hr_opts)?,
        bicubic_truth: evaluate(bicubic_upsample(gt, s).view(), gt_hr.view(), &hr_opts)?,
    }))
}

/// One line on stderr per capture: time, burst and true-motion scores, EPE, and scale 2.
fn log_case(case: &Case, row: &Row, simulated_s: f64) {
    eprintln!(
        "{}: {:.1} s (simulation {simulated_s:.1} s); burst {:.2} dB (LPIPS {:.3}, blur σ {:.2} \
         px), true motion {:.2} dB, splat {:.2} dB (blur σ {:.2} px), EPE {:.3} px (motion \
         {:.2} px){}",
        case.id(),
        row.seconds,
        row.scores[BURST].psnr_srgb,
        row.lpips[BURST],
        row.blur_sigma[0],
        row.scores[TRUE_MOTION].psnr_srgb,
        row.scores[SPLAT].psnr_srgb,
        row.blur_sigma[1],
        row.epe,
        row.motion_px,
        row.sr
            .as_ref()
            .map(|r| format!(
                ", scale 2 {:.2} dB vs bicubic {:.2} dB",
                r.scale2.psnr_srgb, r.bicubic.psnr_srgb
            ))
            .unwrap_or_default()
    );
}

pub(super) fn quality(
    scenes: &Path,
    out: &Path,
    set: SuiteSet,
    only: Option<&str>,
    burst_config: &BurstConfig,
    progress: &dyn Progress,
) -> Result<()> {
    if !scenes.is_dir() {
        bail!(
            "{}: scene folder not found (pass --scenes DIR with the project's shared/data/scenes)",
            scenes.display()
        );
    }
    let opts = EvalOptions {
        border: 16,
        normalize_percentile: Some(99.5),
    };
    let cases = suite();
    let selected: Vec<usize> = (0..cases.len())
        .filter(|&i| set == SuiteSet::All || cases[i].set == set)
        .filter(|&i| only.is_none_or(|o| cases[i].id().contains(o)))
        .collect();
    if selected.is_empty() {
        bail!("no capture of the suite matches");
    }
    let started = Instant::now();
    let mut rows: Vec<Row> = Vec::new();
    progress.start("quality suite", selected.len() as u64);
    for &i in &selected {
        rows.push(run_case(scenes, i, &cases[i], &opts, burst_config)?);
        progress.advance(1);
    }
    progress.finish();
    let total_s = started.elapsed().as_secs_f64();
    eprintln!("quality suite: {} captures in {total_s:.0} s", rows.len());

    let md = report(&cases, &rows, set, only, total_s)?;
    quantacolor::atomic::write_atomic_synced(out, |w| w.write_all(md.as_bytes()))?;
    print!("{md}");
    Ok(())
}
