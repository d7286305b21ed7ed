//! The burst reconstruction against ground truth on a simulated capture with known motion:
//! it must beat the naive long and short averages (paper Table 2) and come close to the same
//! merge driven by the simulator's true motion.

use quantacolor::burst::{reconstruct_burst, reconstruct_burst_with_motion, BurstConfig};
use quantacolor::cfa::colorspad_cfa;
use quantacolor::metrics::{evaluate, EvalOptions};
use quantacolor::naive::{reconstruct_naive, NaiveConfig};
use quantacolor::pipeline::{self, ReconstructConfig};
use quantacolor::progress::Silent;
use quantacolor::simulate::{
    simulate_with_cfa, FluxSpec, MotionConfig, Scene, SimulatedCapture, SimulationConfig,
};

/// A capture of the built-in `scene` through the real colour-SPAD CFA.
fn simulate_colorspad(scene: &str, config: &SimulationConfig) -> SimulatedCapture {
    let scene = Scene::from_spec(scene).unwrap();
    simulate_with_cfa(config, &scene, &colorspad_cfa(), &Silent).unwrap()
}

/// 256 static frames of the built-in HDR chart at a mean W flux of 0.1 (its dark parts under
/// one detection per pixel), colour-SPAD CFA.
fn dim_hdr_chart() -> SimulatedCapture {
    let config = SimulationConfig {
        frames: 256,
        seed: 1,
        ..SimulationConfig::default()
    };
    simulate_colorspad("builtin:chart-hdr", &config)
}

/// A handheld capture of the built-in chart (colour-SPAD CFA).
fn handheld_chart(frames: usize, flux: FluxSpec, seed: u64) -> SimulatedCapture {
    let config = SimulationConfig {
        frames,
        flux,
        motion: "handheld".parse::<MotionConfig>().unwrap(),
        seed,
        ..SimulationConfig::default()
    };
    simulate_colorspad("builtin:chart", &config)
}

/// The quality suite's protocol: 16-pixel border, 99.5th-percentile normalisation.
const SCORED: EvalOptions = EvalOptions {
    border: 16,
    normalize_percentile: Some(99.5),
};

#[test]
fn burst_beats_naive_and_approaches_true_motion() {
    let sim = handheld_chart(1024, FluxSpec::Mean { flux: 0.1 }, 5);
    let capture = sim.to_capture().unwrap();
    let reference = capture.reference_frame();
    let opts = SCORED;
    let score = |linear: &ndarray::Array3<f32>| {
        evaluate(linear.view(), sim.ground_truth.view(), &opts).unwrap()
    };
    let burst = reconstruct_burst(&capture, reference, &BurstConfig::default(), &Silent).unwrap();
    let (h, w) = (capture.cfa.height(), capture.cfa.width());
    let oracle = |t: f64| sim.motion.dense_flow(t, h, w);
    let truth_driven = reconstruct_burst_with_motion(
        &capture,
        reference,
        &BurstConfig::default(),
        Some(&oracle),
        &Silent,
    )
    .unwrap();
    let long = reconstruct_naive(&capture, reference, &NaiveConfig::default()).unwrap();
    let short = reconstruct_naive(
        &capture,
        reference,
        &NaiveConfig {
            window: Some(capture.frames.frame_count() / 16),
        },
    )
    .unwrap();
    let (b, t, l, s) = (
        score(&burst.merged.linear),
        score(&truth_driven.merged.linear),
        score(&long.linear),
        score(&short.linear),
    );
    println!(
        "PSNR/SSIM burst {:.2}/{:.3}, true motion {:.2}/{:.3}, naive long {:.2}/{:.3}, naive short {:.2}/{:.3}",
        b.psnr_srgb, b.ssim_srgb, t.psnr_srgb, t.ssim_srgb, l.psnr_srgb, l.ssim_srgb, s.psnr_srgb, s.ssim_srgb
    );
    assert!(b.psnr_srgb >= l.psnr_srgb + 2.0, "burst vs naive long");
    assert!(b.psnr_srgb >= s.psnr_srgb + 2.0, "burst vs naive short");
    assert!(b.ssim_srgb > l.ssim_srgb && b.ssim_srgb > s.ssim_srgb);
    assert!(
        b.psnr_srgb >= t.psnr_srgb - 1.5,
        "burst far below the true-motion merge"
    );
}

/// Pixels (16-pixel border excluded) whose mean over R, G, B is 5x darker than the median of
/// their 5x5 neighbourhood where the truth's is not: the isolated dark dots of issue 45.
fn isolated_dark_pixels(image: &ndarray::Array3<f32>, truth: &ndarray::Array3<f32>) -> usize {
    isolated_dark_pixels_where(image, truth).len()
}

/// Where [`isolated_dark_pixels`] are, (y, x).
fn isolated_dark_pixels_where(
    image: &ndarray::Array3<f32>,
    truth: &ndarray::Array3<f32>,
) -> Vec<(usize, usize)> {
    let (h, w, _) = image.dim();
    let mean = |a: &ndarray::Array3<f32>, y: usize, x: usize| {
        (a[[y, x, 0]] + a[[y, x, 1]] + a[[y, x, 2]]) / 3.0
    };
    let dark = |a: &ndarray::Array3<f32>, y: usize, x: usize| {
        let mut window: Vec<f32> = (y - 2..=y + 2)
            .flat_map(|yy| (x - 2..=x + 2).map(move |xx| (yy, xx)))
            .map(|(yy, xx)| mean(a, yy, xx))
            .collect();
        window.sort_by(f32::total_cmp);
        let median = window[12];
        median > 0.0 && 5.0 * mean(a, y, x) < median
    };
    (16..h - 16)
        .flat_map(|y| (16..w - 16).map(move |x| (y, x)))
        .filter(|&(y, x)| dark(image, y, x) && !dark(truth, y, x))
        .collect()
}

/// Issue 45: in the dark parts of an HDR capture (under one detection per pixel) a pixel's own
/// value says little about its noise; the noise-aware kernels judge it at the 3x3 mean, floored
/// at one detection, and must not narrow there into more dark dots than the range-based ones.
#[test]
fn noise_aware_kernels_add_no_dark_dots_to_dim_hdr_regions() {
    let sim = dim_hdr_chart();
    let capture = sim.to_capture().unwrap();
    let reference = capture.reference_frame();
    let dots = |config: &BurstConfig| {
        let burst = reconstruct_burst(&capture, reference, config, &Silent).unwrap();
        isolated_dark_pixels(&burst.merged.linear, &sim.ground_truth)
    };
    let mut range_only = BurstConfig::default();
    range_only.merge.kernels.detail_noise_sigmas = 0.0;
    let (aware, range) = (dots(&BurstConfig::default()), dots(&range_only));
    println!("isolated dark pixels: noise-aware {aware}, range-only {range}");
    assert!(range > 0, "the capture should be dark enough to show dots");
    assert!(
        aware as f64 <= range as f64 * 1.1,
        "noise-aware {aware} vs range-only {range}"
    );
}

/// Issue 45 item 4, on the default pipeline (burst and chroma-BM3D): on 256 static frames of the
/// HDR chart, whose dark parts get well under one detection per pixel, dark dots (pixels of
/// [`isolated_dark_pixels`] that are also 3x darker than their own truth) sit on thin dark
/// lines whose own pixels hold no photon. The detail kernel widens there as the flat one does
/// (`dark_snr`); measured 38 dots left of the merge's 473, against 82 of 1,259 before. Not
/// yet the target of 5 (docs/tuning.md).
#[test]
fn the_default_pipeline_removes_most_dark_dots_of_dim_hdr_regions() {
    let sim = dim_hdr_chart();
    let capture = sim.to_capture().unwrap();
    let output = pipeline::reconstruct(&capture, &ReconstructConfig::default(), &Silent).unwrap();
    let truth = &sim.ground_truth;
    let mean = |a: &ndarray::Array3<f32>, y: usize, x: usize| {
        (a[[y, x, 0]] + a[[y, x, 1]] + a[[y, x, 2]]) / 3.0
    };
    let dots = |image: &ndarray::Array3<f32>| {
        isolated_dark_pixels_where(image, truth)
            .into_iter()
            .filter(|&(y, x)| 3.0 * mean(image, y, x) < mean(truth, y, x))
            .count()
    };
    let merged = output.merged_linear.as_ref().expect("denoised by default");
    let (denoised, merged) = (dots(&output.linear), dots(merged));
    println!("dark dots: default {denoised}, its merge {merged}");
    assert!(merged >= 100, "the premise: a merge with dots ({merged})");
    assert!(
        10 * denoised <= merged,
        "{denoised} of the merge's {merged} remain"
    );
}

/// sRGB PSNR of the default burst merge and of the same merge with range-only kernels
/// (`detail_noise_sigmas = 0`, the kernels before issue 45) on a handheld capture of the
/// built-in chart at `flux`.
fn noise_aware_and_range_only(frames: usize, flux: FluxSpec, seed: u64) -> (f64, f64) {
    let sim = handheld_chart(frames, flux, seed);
    let capture = sim.to_capture().unwrap();
    let reference = capture.reference_frame();
    let opts = SCORED;
    let psnr = |config: &BurstConfig| {
        let burst = reconstruct_burst(&capture, reference, config, &Silent).unwrap();
        evaluate(burst.merged.linear.view(), sim.ground_truth.view(), &opts)
            .unwrap()
            .psnr_srgb
    };
    let mut range_only = BurstConfig::default();
    range_only.merge.kernels.detail_noise_sigmas = 0.0;
    (psnr(&BurstConfig::default()), psnr(&range_only))
}

/// Issue 45: where photons are plenty the kernels' detail transition follows the reference's
/// noise, not its range, so edges and textures keep the detail kernel and the merge is
/// sharper; in the dark the range decides and the result does not change much.
#[test]
fn noise_aware_kernels_sharpen_bright_captures_and_keep_dark_ones() {
    let bright = FluxSpec::Percentile {
        percentile: 99.0,
        peak: 4.0,
    };
    let (aware, range) = noise_aware_and_range_only(1000, bright, 21);
    println!("bright: noise-aware {aware:.2} dB, range-only {range:.2} dB");
    assert!(
        aware >= range + 0.3,
        "bright: noise-aware {aware:.2} dB vs range-only {range:.2} dB"
    );
    let (aware, range) = noise_aware_and_range_only(512, FluxSpec::Mean { flux: 0.02 }, 22);
    println!("dark: noise-aware {aware:.2} dB, range-only {range:.2} dB");
    assert!(
        aware >= range - 0.15,
        "dark: noise-aware {aware:.2} dB vs range-only {range:.2} dB"
    );
}
