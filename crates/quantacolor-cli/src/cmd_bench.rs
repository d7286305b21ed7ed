//! `quantacolor bench`: the project's quality and speed benchmarks. Every ratio is against a
//! baseline measured in the same run; nothing here is asserted by the test suite.

use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand};
use quantacolor::burst::{reconstruct_burst, reconstruct_burst_with_motion, BurstConfig};
use quantacolor::cfa::colorspad_cfa;
use quantacolor::denoise::chroma::{denoise_linear, DenoiseConfig, DenoiseMethod};
use quantacolor::metrics::{evaluate, EvalOptions, Scores};
use quantacolor::naive::{reconstruct_naive, NaiveConfig};
use quantacolor::pipeline::{burst_config_for, denoise_input, ReconstructConfig};
use quantacolor::progress::{Progress, Silent};
use quantacolor::simulate::{
    simulate_with_cfa, FluxSpec, MotionConfig, Scene, SimulatedCapture, SimulationConfig,
};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

#[derive(Debug, Args)]
pub struct BenchArgs {
    #[command(subcommand)]
    pub command: BenchCommand,
}

#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// Quality suite on real photographs: burst vs naive long/short vs true-motion merge;
    /// writes a Markdown table.
    Quality {
        /// Folder with kodim02/04/07/12.png and the OpenEXR samples (the project's
        /// shared/data/scenes).
        #[arg(long, default_value = "../shared/data/scenes")]
        scenes: PathBuf,
        /// Markdown output.
        #[arg(long, default_value = "BENCHMARKS.md")]
        out: PathBuf,
    },
    /// Denoising: PSNR/SSIM of none, plain colour BM3D and chroma-BM3D over a grid of σ gains
    /// (the tuning tool for `luma_gain` / `chroma_gain`), on built-in chart captures, or on the
    /// quality suite's scenes with --scenes.
    Denoise {
        /// Folder with the quality suite's scenes (default: built-in chart captures only).
        #[arg(long)]
        scenes: Option<PathBuf>,
        /// Luma σ gains to try (comma-separated).
        #[arg(long, value_delimiter = ',', default_value = "1")]
        luma_gains: Vec<f32>,
        /// Chroma σ gains to try (comma-separated).
        #[arg(long, value_delimiter = ',', default_value = "1")]
        chroma_gains: Vec<f32>,
        /// TOML with burst (align + merge) parameters to use instead of the defaults (the
        /// `[burst]` table of report.toml, without the table header).
        #[arg(long)]
        burst_config: Option<PathBuf>,
    },
    /// Speed: align + merge of a simulated 10,000-frame capture, against the naive sum of the
    /// same frames in the same process.
    Speed {
        #[arg(long, default_value_t = 10_000)]
        frames: usize,
    },
}

pub fn run(args: &BenchArgs, progress: &dyn Progress) -> Result<()> {
    match &args.command {
        BenchCommand::Quality { scenes, out } => quality(scenes, out, progress),
        BenchCommand::Speed { frames } => speed(*frames, progress),
        BenchCommand::Denoise {
            scenes,
            luma_gains,
            chroma_gains,
            burst_config,
        } => {
            let burst = match burst_config {
                Some(path) => {
                    let text = std::fs::read_to_string(path)
                        .with_context(|| format!("{}: cannot read", path.display()))?;
                    toml::from_str::<BurstConfig>(&text)
                        .map_err(|e| anyhow::anyhow!("{}: {}", path.display(), e.message()))?
                }
                None => BurstConfig::default(),
            };
            denoise_grid(
                scenes.as_deref(),
                luma_gains,
                chroma_gains,
                &burst,
                progress,
            )
        }
    }
}

struct Case {
    scene: &'static str,
    motion: &'static str,
    frames: usize,
    flux: FluxSpec,
}

fn suite() -> Vec<Case> {
    let mean = FluxSpec::Mean { flux: 0.1 };
    let hdr = FluxSpec::Percentile {
        percentile: 50.0,
        peak: 0.1,
    };
    vec![
        Case {
            scene: "kodim02.png",
            motion: "handheld",
            frames: 512,
            flux: mean,
        },
        Case {
            scene: "kodim04.png",
            motion: "pan",
            frames: 512,
            flux: mean,
        },
        Case {
            scene: "kodim07.png",
            motion: "static",
            frames: 512,
            flux: mean,
        },
        Case {
            scene: "kodim12.png",
            motion: "object",
            frames: 512,
            flux: mean,
        },
        Case {
            scene: "ScanLines_StillLife.exr",
            motion: "handheld",
            frames: 2000,
            flux: hdr,
        },
        Case {
            scene: "ScanLines_Cannon.exr",
            motion: "pan",
            frames: 2000,
            flux: hdr,
        },
    ]
}

fn simulate_case(scenes: &Path, case: &Case, seed: u64) -> Result<SimulatedCapture> {
    let path = scenes.join(case.scene);
    let scene = Scene::load(&path)?;
    let config = SimulationConfig {
        frames: case.frames,
        flux: case.flux,
        motion: case.motion.parse::<MotionConfig>()?,
        hot_fraction: 0.02,
        seed,
        ..SimulationConfig::default()
    };
    Ok(simulate_with_cfa(
        &config,
        &scene,
        &colorspad_cfa(),
        &Silent,
    )?)
}

const METHODS: [&str; 7] = [
    "burst",
    "burst (true motion)",
    "naive long",
    "naive short",
    "burst, denoiser's merge, no denoising",
    "burst + BM3D",
    "burst + chroma-BM3D",
];

fn quality(scenes: &Path, out: &Path, progress: &dyn Progress) -> Result<()> {
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
    let mut table: Vec<(String, [Scores; 7])> = Vec::new();
    progress.start("quality suite", cases.len() as u64);
    for (i, case) in cases.iter().enumerate() {
        let sim = simulate_case(scenes, case, 100 + i as u64)
            .with_context(|| format!("simulating {}", case.scene))?;
        let capture = sim.to_capture()?;
        let reference = capture.reference_frame();
        let (h, w) = (capture.cfa.height(), capture.cfa.width());
        let config = BurstConfig::default();
        let burst = reconstruct_burst(&capture, reference, &config, &Silent)?;
        let oracle = |t: f64| sim.motion.dense_flow(t, h, w);
        let truth =
            reconstruct_burst_with_motion(&capture, reference, &config, Some(&oracle), &Silent)?;
        let long = reconstruct_naive(&capture, reference, &NaiveConfig::default())?;
        let short = reconstruct_naive(
            &capture,
            reference,
            &NaiveConfig {
                window: Some((case.frames / 16).max(1)),
            },
        )?;
        let gt = sim.ground_truth.view();
        // The merge the denoiser runs on (narrower colour kernels, see DenoiseConfig).
        let denoised_config = ReconstructConfig::default();
        let for_denoising = reconstruct_burst(
            &capture,
            reference,
            &burst_config_for(&denoised_config),
            &Silent,
        )?;
        let input = denoise_input(&capture, Some(&for_denoising), case.frames);
        let denoised = |method| -> Result<Scores> {
            let config = DenoiseConfig {
                method,
                ..denoised_config.denoise.clone()
            };
            let (out, _) = denoise_linear(for_denoising.merged.linear.view(), &input, &config)?;
            Ok(evaluate(out.view(), gt, &opts)?)
        };
        let scores = [
            evaluate(burst.merged.linear.view(), gt, &opts)?,
            evaluate(truth.merged.linear.view(), gt, &opts)?,
            evaluate(long.linear.view(), gt, &opts)?,
            evaluate(short.linear.view(), gt, &opts)?,
            evaluate(for_denoising.merged.linear.view(), gt, &opts)?,
            denoised(DenoiseMethod::Bm3d)?,
            denoised(DenoiseMethod::ChromaBm3d)?,
        ];
        table.push((
            format!("{} / {} / {} frames", case.scene, case.motion, case.frames),
            scores,
        ));
        progress.advance(1);
    }
    progress.finish();

    let mut md = String::new();
    writeln!(md, "# Benchmarks\n")?;
    writeln!(
        md,
        "Generated by `quantacolor bench quality --scenes ../shared/data/scenes` (do not edit by \
         hand). Simulated SPAD captures (paper Table 1) of 496x254 with the real colour-SPAD CFA \
         and 2 % hot pixels; 0.1 photons/pixel/frame (HDR scenes: median W pixel at 0.1). \
         Scores: 16-pixel border excluded, both images scaled so the ground truth's 99.5th \
         percentile is 1, clipped, sRGB-encoded; PSNR (dB) / SSIM. Naive short uses 1/16 of the \
         frames. Only the last two columns are denoised (paper §4.3): plain colour BM3D (one σ) \
         and chroma-BM3D, both with σ from the merge's noise model, on the merge the denoiser \
         runs on (colour kernels with spacing exponent 0.5 instead of 1, the column before them). \
         `reconstruct` runs burst + chroma-BM3D by default; `--denoise none` gives the first \
         column.\n"
    )?;
    writeln!(md, "| capture | {} |", METHODS.join(" | "))?;
    writeln!(md, "|---|{}", "---|".repeat(METHODS.len()))?;
    let mut sums = [(0.0, 0.0); 7];
    for (name, scores) in &table {
        let cells: Vec<String> = scores
            .iter()
            .map(|s| format!("{:.2} / {:.3}", s.psnr_srgb, s.ssim_srgb))
            .collect();
        writeln!(md, "| {name} | {} |", cells.join(" | "))?;
        for (sum, s) in sums.iter_mut().zip(scores) {
            sum.0 += s.psnr_srgb;
            sum.1 += s.ssim_srgb;
        }
    }
    let n = table.len() as f64;
    let means: Vec<(f64, f64)> = sums.iter().map(|s| (s.0 / n, s.1 / n)).collect();
    writeln!(
        md,
        "| **mean** | {} |",
        means
            .iter()
            .map(|m| format!("**{:.2} / {:.3}**", m.0, m.1))
            .collect::<Vec<_>>()
            .join(" | ")
    )?;
    let ssim_wins = table
        .iter()
        .filter(|(_, s)| s[0].ssim_srgb > s[2].ssim_srgb && s[0].ssim_srgb > s[3].ssim_srgb)
        .count();
    writeln!(md, "\nTargets (means over the suite):\n")?;
    writeln!(
        md,
        "- burst − naive long: {:+.2} dB (target >= +2 dB; paper +2.2 dB)",
        means[0].0 - means[2].0
    )?;
    writeln!(
        md,
        "- burst − naive short: {:+.2} dB (target >= +5 dB; paper +5.4 dB)",
        means[0].0 - means[3].0
    )?;
    writeln!(
        md,
        "- burst − true-motion merge: {:+.2} dB (target within 1 dB)",
        means[0].0 - means[1].0
    )?;
    writeln!(
        md,
        "- burst SSIM above both naive baselines on {ssim_wins} of {} captures",
        table.len()
    )?;
    writeln!(
        md,
        "- chroma-BM3D − the same merge without denoising: {:+.2} dB (target >= +1.5 dB)",
        means[6].0 - means[4].0
    )?;
    writeln!(
        md,
        "- chroma-BM3D − burst without denoising (default merge; end to end): {:+.2} dB",
        means[6].0 - means[0].0
    )?;
    let chroma_ssim_wins = table
        .iter()
        .filter(|(_, s)| s[6].ssim_srgb > s[5].ssim_srgb)
        .count();
    writeln!(
        md,
        "- chroma-BM3D − plain colour BM3D: SSIM {:+.4} on average, higher on {chroma_ssim_wins} of {} captures (target: higher); PSNR {:+.2} dB",
        means[6].1 - means[5].1,
        table.len(),
        means[6].0 - means[5].0
    )?;
    let tmp = out.with_extension("md.tmp");
    std::fs::write(&tmp, &md).with_context(|| format!("{}: cannot write", tmp.display()))?;
    std::fs::rename(&tmp, out).with_context(|| format!("{}: cannot write", out.display()))?;
    print!("{md}");
    Ok(())
}

fn speed(frames: usize, progress: &dyn Progress) -> Result<()> {
    let config = SimulationConfig {
        frames,
        flux: FluxSpec::Mean { flux: 0.1 },
        motion: "handheld".parse::<MotionConfig>()?,
        ..SimulationConfig::default()
    };
    eprintln!("simulating {frames} frames of 496x254 (not timed)");
    let sim = simulate_with_cfa(
        &config,
        &Scene::from_spec("builtin:chart")?,
        &colorspad_cfa(),
        progress,
    )?;
    let capture = sim.to_capture()?;
    let reference = capture.reference_frame();
    let start = Instant::now();
    let naive = reconstruct_naive(&capture, reference, &NaiveConfig::default())?;
    let naive_s = start.elapsed().as_secs_f64();
    let start = Instant::now();
    let burst = reconstruct_burst(&capture, reference, &BurstConfig::default(), &Silent)?;
    let burst_s = start.elapsed().as_secs_f64();
    std::hint::black_box((&naive, &burst));
    println!(
        "{frames} frames 496x254, {} threads: naive {naive_s:.3} s, burst (align + merge) {burst_s:.3} s, ratio {:.1}x",
        rayon::current_num_threads(),
        burst_s / naive_s
    );
    for t in &burst.timings {
        println!("  {:<32} {:.3} s", t.stage, t.seconds);
    }
    let input = denoise_input(&capture, Some(&burst), frames);
    let start = Instant::now();
    let denoised = denoise_linear(
        burst.merged.linear.view(),
        &input,
        &DenoiseConfig::default(),
    )?;
    let denoise_s = start.elapsed().as_secs_f64();
    std::hint::black_box(&denoised);
    println!(
        "  {:<32} {denoise_s:.3} s ({:.1}x the naive sum)",
        "denoise (chroma-bm3d)",
        denoise_s / naive_s
    );
    Ok(())
}

/// Built-in chart captures for tuning the denoiser (never the quality suite's scenes).
fn chart_captures() -> Result<Vec<(String, SimulatedCapture)>> {
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

fn denoise_grid(
    scenes: Option<&Path>,
    luma_gains: &[f32],
    chroma_gains: &[f32],
    burst_config: &BurstConfig,
    progress: &dyn Progress,
) -> Result<()> {
    let captures: Vec<(String, SimulatedCapture)> = match scenes {
        None => chart_captures()?,
        Some(dir) => suite()
            .iter()
            .enumerate()
            .map(|(i, case)| {
                let sim = simulate_case(dir, case, 100 + i as u64)
                    .with_context(|| format!("simulating {}", case.scene))?;
                Ok((
                    format!("{} / {} / {} frames", case.scene, case.motion, case.frames),
                    sim,
                ))
            })
            .collect::<Result<_>>()?,
    };
    let opts = EvalOptions {
        border: 16,
        normalize_percentile: Some(99.5),
    };
    // (method, luma gain, chroma gain) -> per-capture scores
    let mut settings: Vec<(DenoiseMethod, f32, f32)> = vec![(DenoiseMethod::None, 1.0, 1.0)];
    for &g in luma_gains {
        settings.push((DenoiseMethod::Bm3d, g, 1.0));
        for &c in chroma_gains {
            settings.push((DenoiseMethod::ChromaBm3d, g, c));
        }
    }
    let mut scores: Vec<Vec<Scores>> = vec![Vec::new(); settings.len()];
    progress.start("denoising grid", captures.len() as u64);
    for (name, sim) in &captures {
        let capture = sim.to_capture()?;
        let reference = capture.reference_frame();
        let burst = reconstruct_burst(&capture, reference, burst_config, &Silent)?;
        let input = denoise_input(&capture, Some(&burst), capture.frames.frame_count());
        let gt = sim.ground_truth.view();
        for (k, &(method, luma_gain, chroma_gain)) in settings.iter().enumerate() {
            let config = DenoiseConfig {
                method,
                luma_gain,
                chroma_gain,
                ..DenoiseConfig::default()
            };
            let start = Instant::now();
            let (out, report) = denoise_linear(burst.merged.linear.view(), &input, &config)?;
            let s = evaluate(out.view(), gt, &opts)?;
            eprintln!(
                "{name}: {method} luma×{luma_gain} chroma×{chroma_gain}: {:.2} dB / {:.4} ({:.2} s, σ {:?})",
                s.psnr_srgb,
                s.ssim_srgb,
                start.elapsed().as_secs_f64(),
                report.map(|r| r.sigmas)
            );
            scores[k].push(s);
        }
        progress.advance(1);
    }
    progress.finish();
    println!(
        "{:<12} {:>6} {:>7} {:>10} {:>10}",
        "method", "luma", "chroma", "mean PSNR", "mean SSIM"
    );
    let n = captures.len() as f64;
    for (k, (method, g, c)) in settings.iter().enumerate() {
        let psnr = scores[k].iter().map(|s| s.psnr_srgb).sum::<f64>() / n;
        let ssim = scores[k].iter().map(|s| s.ssim_srgb).sum::<f64>() / n;
        println!(
            "{:<12} {:>6} {:>7} {:>10.2} {:>10.4}",
            method.to_string(),
            g,
            c,
            psnr,
            ssim
        );
    }
    Ok(())
}
