//! The burst reconstruction against ground truth on a simulated capture with known motion:
//! it must beat the naive long and short averages (paper Table 2) and come close to the same
//! merge driven by the simulator's true motion.

use quantacolor::burst::{reconstruct_burst, reconstruct_burst_with_motion, BurstConfig};
use quantacolor::cfa::colorspad_cfa;
use quantacolor::metrics::{evaluate, EvalOptions};
use quantacolor::naive::{reconstruct_naive, NaiveConfig};
use quantacolor::progress::Silent;
use quantacolor::simulate::{simulate_with_cfa, FluxSpec, MotionConfig, Scene, SimulationConfig};

#[test]
fn burst_beats_naive_and_approaches_true_motion() {
    let cfa = colorspad_cfa();
    let config = SimulationConfig {
        frames: 1024,
        flux: FluxSpec::Mean { flux: 0.1 },
        motion: "handheld".parse::<MotionConfig>().unwrap(),
        seed: 5,
        ..SimulationConfig::default()
    };
    let sim = simulate_with_cfa(
        &config,
        &Scene::from_spec("builtin:chart").unwrap(),
        &cfa,
        &Silent,
    )
    .unwrap();
    let capture = sim.to_capture().unwrap();
    let reference = capture.reference_frame();
    let opts = EvalOptions {
        border: 16,
        normalize_percentile: Some(99.5),
    };
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
            window: Some(config.frames / 16),
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

/// sRGB PSNR of the default burst merge and of the same merge with range-only kernels
/// (`detail_noise_sigmas = 0`, the kernels before issue 45) on a handheld capture of the
/// built-in chart at `flux`.
fn noise_aware_and_range_only(frames: usize, flux: FluxSpec, seed: u64) -> (f64, f64) {
    let cfa = colorspad_cfa();
    let config = SimulationConfig {
        frames,
        flux,
        motion: "handheld".parse::<MotionConfig>().unwrap(),
        seed,
        ..SimulationConfig::default()
    };
    let sim = simulate_with_cfa(
        &config,
        &Scene::from_spec("builtin:chart").unwrap(),
        &cfa,
        &Silent,
    )
    .unwrap();
    let capture = sim.to_capture().unwrap();
    let reference = capture.reference_frame();
    let opts = EvalOptions {
        border: 16,
        normalize_percentile: Some(99.5),
    };
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
