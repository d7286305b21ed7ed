//! Hand-run diagnostic of the denoiser's noise model (prints, asserts nothing, so ignored): per
//! brightness band of the ground truth, the measured RMS error of the merge in the stabilised
//! colour-transformed domain against the modelled per-pixel σ, before and after denoising.
//! `cargo test --release -p quantacolor --test denoise_diagnose -- --ignored --nocapture`
//! (QC_CASES="scene:motion:frames:flux;..." overrides the captures; scenes from ../shared/data;
//! QC_DENOISE is a TOML `[denoise]` table body applied on top of the default).

use ndarray::{Array3, Axis};
use quantacolor::burst::reconstruct_burst;
use quantacolor::cfa::colorspad_cfa;
use quantacolor::denoise::chroma::{
    denoise_linear, model_variance_map, stabilise, ColorTransform, DenoiseConfig,
};
use quantacolor::metrics::{evaluate, EvalOptions};
use quantacolor::pipeline::{burst_config_for, denoise_input, ReconstructConfig};
use quantacolor::progress::Silent;
use quantacolor::simulate::{simulate_with_cfa, FluxSpec, MotionConfig, Scene, SimulationConfig};

#[test]
#[ignore]
fn diagnose_noise_model() {
    let cases = std::env::var("QC_CASES").unwrap_or_else(|_| {
        "ScanLines_StillLife.exr:handheld:2000:hdr;kodim02.png:handheld:512:0.1;kodim02.png:handheld:2000:0.02".into()
    });
    let scenes =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data/scenes");
    let opts = EvalOptions {
        border: 16,
        normalize_percentile: Some(99.5),
    };
    let mut denoise = DenoiseConfig::default();
    if let Ok(extra) = std::env::var("QC_DENOISE") {
        denoise = toml::from_str(&extra).unwrap();
    }
    for (i, case) in cases.split(';').enumerate() {
        let parts: Vec<&str> = case.rsplitn(4, ':').collect();
        let (flux, frames, motion, scene_name) = (parts[0], parts[1], parts[2], parts[3]);
        let scene = Scene::load(scenes.join(scene_name)).unwrap();
        let flux = if flux == "hdr" {
            FluxSpec::Percentile {
                percentile: 50.0,
                peak: 0.1,
            }
        } else {
            FluxSpec::Mean {
                flux: flux.parse().unwrap(),
            }
        };
        let motion_config: MotionConfig = motion.parse().unwrap();
        let config = SimulationConfig {
            frames: frames.parse().unwrap(),
            flux,
            motion: motion_config,
            hot_fraction: 0.02,
            seed: 700 + i as u64,
            ..SimulationConfig::default()
        };
        let sim = simulate_with_cfa(&config, &scene, &colorspad_cfa(), &Silent).unwrap();
        let capture = sim.to_capture().unwrap();
        let reconstruct = ReconstructConfig {
            denoise: denoise.clone(),
            ..ReconstructConfig::default()
        };
        let burst = reconstruct_burst(
            &capture,
            capture.reference_frame(),
            &burst_config_for(&reconstruct),
            &Silent,
        )
        .unwrap();
        let input = denoise_input(&capture, Some(&burst), capture.frames.frame_count());
        let transform = ColorTransform::w_weighted_ycbcr(capture.meta.w_weights).unwrap();
        let merged = burst.merged.linear.view();
        let (denoised, report) = denoise_linear(merged, &input, &denoise).unwrap();
        let stab = stabilise(merged, &input, transform).unwrap();
        let variance = model_variance_map(
            &merged,
            input.noise.as_ref().unwrap(),
            &stab.stabiliser,
            &transform,
            input.w_weights,
        );
        let truth = stabilise(sim.ground_truth.view(), &input, transform)
            .unwrap()
            .planes;
        let after = stabilise(denoised.view(), &input, transform)
            .unwrap()
            .planes;
        let s_none = evaluate(merged, sim.ground_truth.view(), &opts).unwrap();
        let s_den = evaluate(denoised.view(), sim.ground_truth.view(), &opts).unwrap();
        println!(
            "\n== {case}: trials {} σ {:?} (report {:?}); sRGB PSNR none {:.2} → {:.2} dB, SSIM {:.3} → {:.3}",
            stab.stabiliser.trials(),
            stab.sigmas,
            report.map(|r| r.sigmas),
            s_none.psnr_srgb,
            s_den.psnr_srgb,
            s_none.ssim_srgb,
            s_den.ssim_srgb
        );
        band_table(&truth, &stab.planes, &after, &variance);
        // Near saturation (a W pixel above 5 detections per frame: p > 0.993, where the binary
        // frames hold little information): replace those pixels by the truth in both images to
        // see what denoising does elsewhere.
        let gt = &sim.ground_truth;
        let w = capture.meta.w_weights;
        let saturated =
            |y: usize, x: usize| (0..3).map(|c| w[c] * gt[[y, x, c]] as f64).sum::<f64>() > 5.0;
        let (h, wd, _) = gt.dim();
        let mut count = 0usize;
        let mut masked = [merged.to_owned(), denoised.clone()];
        for y in 0..h {
            for x in 0..wd {
                if saturated(y, x) {
                    count += 1;
                    for m in masked.iter_mut() {
                        for c in 0..3 {
                            m[[y, x, c]] = gt[[y, x, c]];
                        }
                    }
                }
            }
        }
        let [a, b] = masked.map(|m| evaluate(m.view(), gt.view(), &opts).unwrap().psnr_srgb);
        println!(
            "near-saturated pixels: {:.2} %; with them replaced by the truth: none {a:.2} dB, denoised {b:.2} dB",
            100.0 * count as f64 / (h * wd) as f64
        );
    }
}

/// Deciles of the truth's stabilised luma: RMS error of each channel before/after and the
/// median modelled σ.
fn band_table(truth: &Array3<f32>, before: &Array3<f32>, after: &Array3<f32>, var: &Array3<f32>) {
    let (_, h, w) = truth.dim();
    let b = 16;
    let mut pixels: Vec<(usize, usize)> = (b..h - b)
        .flat_map(|y| (b..w - b).map(move |x| (y, x)))
        .collect();
    pixels.sort_by(|p, q| truth[[0, p.0, p.1]].total_cmp(&truth[[0, q.0, q.1]]));
    println!(
        "band  Y-range         | Y: rms before/after σ | Cb: before/after σ | Cr: before/after σ"
    );
    for d in 0..10 {
        let band = &pixels[d * pixels.len() / 10..(d + 1) * pixels.len() / 10];
        let (lo, hi) = (truth[[0, band[0].0, band[0].1]], {
            let l = band[band.len() - 1];
            truth[[0, l.0, l.1]]
        });
        let mut line = format!("{d:>4}  {lo:>6.1}..{hi:>6.1} ");
        for ch in 0..3 {
            let rms = |img: &Array3<f32>| {
                let plane = img.index_axis(Axis(0), ch);
                let t = truth.index_axis(Axis(0), ch);
                (band
                    .iter()
                    .map(|&(y, x)| ((plane[[y, x]] - t[[y, x]]) as f64).powi(2))
                    .sum::<f64>()
                    / band.len() as f64)
                    .sqrt()
            };
            let mut s: Vec<f32> = band
                .iter()
                .map(|&(y, x)| var[[ch, y, x]])
                .filter(|v| v.is_finite())
                .collect();
            s.sort_by(f32::total_cmp);
            let sigma = s.get(s.len() / 2).map_or(f32::NAN, |v| v.sqrt());
            line += &format!("| {:>6.2} {:>6.2} {:>6.2} ", rms(before), rms(after), sigma);
        }
        println!("{line}");
    }
}
