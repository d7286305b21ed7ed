//! `quantacolor bench`: the project's quality and speed benchmarks. Every ratio is against a
//! baseline measured in the same run; nothing here is asserted by the test suite.

use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand};
use ndarray::{Array3, ArrayView3};
use quantacolor::burst::{
    reconstruct_burst, reconstruct_burst_with_motion, BurstConfig, BurstReconstruction,
    MotionOracle,
};
use quantacolor::capture::Capture;
use quantacolor::cfa::{self, colorspad_cfa, Pattern};
use quantacolor::denoise::chroma::{denoise_linear, DenoiseConfig, DenoiseMethod};
use quantacolor::metrics::{evaluate, evaluate_lpips, EvalOptions, Scores};
use quantacolor::naive::{reconstruct_naive, NaiveConfig};
use quantacolor::pipeline::{burst_config_for, denoise_input, reconstruct, ReconstructConfig};
use quantacolor::progress::{Progress, Silent};
use quantacolor::simulate::{
    ground_truth_at, simulate_with_cfa, FluxSpec, Motion, MotionConfig, Scene, SimulatedCapture,
    SimulationConfig,
};
use quantacolor::timing::StageTiming;
use quantacolor::video::{video_reference_frames, VideoReconstructor};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

#[derive(Debug, Args)]
pub struct BenchArgs {
    #[command(subcommand)]
    pub command: BenchCommand,
}

/// Which captures of the quality suite to run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum SuiteSet {
    /// The captures to tune parameters on.
    Tuning,
    /// Held-out captures (other photographs, other seeds) that check the tuning generalises.
    Validation,
    /// Both.
    All,
}

#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// Quality suite on real photographs, as a tuning set and a held-out validation set: burst
    /// vs true-motion merge vs naive long/short vs chroma-BM3D, alignment end-point error, and
    /// super-resolution (scale 2) against bicubic upsampling; writes a Markdown report.
    Quality {
        /// Folder with the photographs (kodim*.png) and OpenEXR samples (the project's
        /// shared/data/scenes).
        #[arg(long, default_value = "../shared/data/scenes")]
        scenes: PathBuf,
        /// Markdown output.
        #[arg(long, default_value = "BENCHMARKS.md")]
        out: PathBuf,
        /// Which set of captures to run (tuning runs are about half the time).
        #[arg(long, value_enum, default_value_t = SuiteSet::All)]
        set: SuiteSet,
        /// Only the captures whose id contains this text (debugging; see the ids on stderr).
        #[arg(long, hide = true)]
        only: Option<String>,
        /// TOML with burst (align + refine + merge) parameters to use instead of the defaults
        /// (the `[burst]` table of report.toml, without the table header): the tuning tool.
        #[arg(long)]
        burst_config: Option<PathBuf>,
    },
    /// Denoising: PSNR/SSIM of chroma-BM3D over a grid of σ gains and of the flat-area kernel
    /// of the merge it runs on (the tuning tool for `luma_gain`, `chroma_gain` and
    /// `merge_k_denoise`), against the default merge without denoising (end to end), on built-in
    /// chart captures, or on a set of the quality suite with --scenes.
    Denoise {
        /// Folder with the quality suite's scenes (default: built-in chart captures only).
        #[arg(long)]
        scenes: Option<PathBuf>,
        /// Which set of the quality suite (with --scenes).
        #[arg(long, value_enum, default_value_t = SuiteSet::Tuning)]
        set: SuiteSet,
        /// Only the captures whose id contains this text.
        #[arg(long)]
        only: Option<String>,
        /// Luma σ gains to try (comma-separated; default: the configured one).
        #[arg(long, value_delimiter = ',')]
        luma_gains: Vec<f32>,
        /// Chroma σ gains to try (comma-separated; default: the configured one).
        #[arg(long, value_delimiter = ',')]
        chroma_gains: Vec<f32>,
        /// Flat-area kernel stds (px) of the denoiser's merge to try (comma-separated;
        /// default: the configured one).
        #[arg(long, value_delimiter = ',')]
        merge_k_denoise: Vec<f32>,
        /// Numbers of coarse chroma scales to try (comma-separated; default: the configured).
        #[arg(long, value_delimiter = ',')]
        chroma_scales: Vec<usize>,
        /// Coarse σ factors to try (comma-separated; default: the configured one).
        #[arg(long, value_delimiter = ',')]
        coarse_sigma_factors: Vec<f32>,
        /// TOML with burst (align + merge) parameters to use instead of the defaults (the
        /// `[burst]` table of report.toml, without the table header).
        #[arg(long)]
        burst_config: Option<PathBuf>,
        /// TOML with denoising parameters to start from (the `[denoise]` table of report.toml,
        /// without the table header).
        #[arg(long)]
        denoise_config: Option<PathBuf>,
    },
    /// Speed: align + merge of a simulated 10,000-frame capture, against the naive sum of the
    /// same frames in the same process.
    Speed {
        #[arg(long, default_value_t = 10_000)]
        frames: usize,
        /// Timed rounds: each times the naive sum three times, then the default pipeline once
        /// (interleaved, so that both see the same machine); the medians are reported (the
        /// naive sum takes tens of milliseconds, so one run of it is at the mercy of the
        /// scheduler).
        #[arg(long, default_value_t = 5, value_parser = clap::value_parser!(u32).range(1..))]
        runs: u32,
        /// TOML with a full or partial reconstruction config (as `reconstruct --config`) to
        /// time instead of the default pipeline: how far a speed setting moves the ratio.
        #[arg(long)]
        config: Option<PathBuf>,
    },
    /// Video: `reconstruct --video` (motion estimated once, composed to every reference frame)
    /// against a full reconstruction per reference frame, in the same process, on a simulated
    /// chart capture; PSNR/SSIM of both against the simulator's ground truth at each reference
    /// frame, and of one against the other.
    Video {
        #[arg(long, default_value_t = 4000)]
        frames: usize,
        /// Frames between consecutive video reference frames.
        #[arg(long, default_value_t = 500)]
        stride: usize,
        /// Camera motion of the simulation (static, pan, handheld, fast-handheld, circular,
        /// object).
        #[arg(long, default_value = "handheld")]
        motion: MotionConfig,
        /// Denoising of both paths [default: chroma-bm3d, as `reconstruct`].
        #[arg(long)]
        denoise: Option<DenoiseMethod>,
        #[arg(long, default_value_t = 1)]
        seed: u64,
    },
}

pub fn run(args: &BenchArgs, progress: &dyn Progress) -> Result<()> {
    match &args.command {
        BenchCommand::Quality {
            scenes,
            out,
            set,
            only,
            burst_config,
        } => {
            let burst = read_burst_config(burst_config.as_deref())?;
            quality(scenes, out, *set, only.as_deref(), &burst, progress)
        }
        BenchCommand::Speed {
            frames,
            runs,
            config,
        } => {
            let (pipeline, name) = match config {
                Some(path) => (
                    crate::cmd_reconstruct::read_config(path)?,
                    format!("pipeline of {}", path.display()),
                ),
                None => (ReconstructConfig::default(), "default pipeline".to_string()),
            };
            speed(*frames, *runs as usize, (&pipeline, &name), progress)
        }
        BenchCommand::Video {
            frames,
            stride,
            motion,
            denoise,
            seed,
        } => video(*frames, *stride, motion, *denoise, *seed, progress),
        BenchCommand::Denoise {
            scenes,
            set,
            only,
            luma_gains,
            chroma_gains,
            merge_k_denoise,
            chroma_scales,
            coarse_sigma_factors,
            burst_config,
            denoise_config,
        } => {
            let burst = read_burst_config(burst_config.as_deref())?;
            let denoise = read_toml_config::<DenoiseConfig>(denoise_config.as_deref())?;
            let grid = DenoiseGrid {
                luma_gains: or_default(luma_gains, denoise.luma_gain),
                chroma_gains: or_default(chroma_gains, denoise.chroma_gain),
                merge_k_denoise: if merge_k_denoise.is_empty() {
                    vec![denoise.merge_k_denoise]
                } else {
                    merge_k_denoise.iter().map(|&k| Some(k)).collect()
                },
                chroma_scales: if chroma_scales.is_empty() {
                    vec![denoise.chroma_scales]
                } else {
                    chroma_scales.clone()
                },
                coarse_sigma_factors: or_default(coarse_sigma_factors, denoise.coarse_sigma_factor),
            };
            let captures = match scenes {
                None => chart_captures()?,
                Some(dir) => suite_captures(dir, *set, only.as_deref())?,
            };
            denoise_grid(&captures, &grid, &burst, &denoise, progress)
        }
    }
}

/// The colour filter array of a suite capture.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum CfaKind {
    /// The real colour-SPAD CFA (its top-left crop for smaller sensors).
    ColorSpad,
    /// RGGB Bayer.
    Bayer,
}

/// One capture of the quality suite.
struct Case {
    set: SuiteSet,
    scene: &'static str,
    /// Short motion name for the table.
    motion_name: &'static str,
    motion: MotionConfig,
    frames: usize,
    flux: FluxSpec,
    cfa: CfaKind,
    /// Sensor (height, width).
    size: (usize, usize),
    /// Pixel supersampling of the simulator: 2 for the 2x-detail captures (scored at scale 2
    /// as well).
    supersampling: usize,
    seed: u64,
}

impl Case {
    /// Table label.
    fn label(&self) -> String {
        let scene = self.scene.rsplit_once('.').map_or(self.scene, |(a, _)| a);
        let flux = match self.flux {
            FluxSpec::Mean { flux } => format!("{flux}"),
            FluxSpec::Percentile { percentile, peak } => format!("HDR p{percentile}={peak}"),
        };
        let mut label = format!(
            "{scene} / {} / {} fr / {flux}",
            self.motion_name, self.frames
        );
        if self.cfa == CfaKind::Bayer {
            label.push_str(" / Bayer");
        }
        if self.supersampling > 1 {
            let (h, w) = self.size;
            write!(label, " / {}x detail {w}x{h}", self.supersampling).ok();
        }
        label
    }

    /// Id for `--only` and the progress lines.
    fn id(&self) -> String {
        let set = if self.set == SuiteSet::Tuning {
            "t"
        } else {
            "v"
        };
        let scene = self.scene.rsplit_once('.').map_or(self.scene, |(a, _)| a);
        let motion = self.motion_name.replace(' ', "-");
        let mut id = format!("{set}-{scene}-{motion}-{}", self.frames);
        if self.cfa == CfaKind::Bayer {
            id.push_str("-bayer");
        }
        if let FluxSpec::Mean { flux } = self.flux {
            if flux < 0.1 {
                id.push_str("-dark");
            }
        }
        if self.supersampling > 1 {
            id.push_str("-2x");
        }
        id
    }
}

/// The quality suite. Tuning set: kodim02, kodim07, kodim15, ScanLines_StillLife, seeds 200+;
/// validation set: kodim04, kodim12, kodim22, ScanLines_Cannon, MultiResolution_Bonita, seeds
/// 300+. Each set has one capture of every kind (handheld, pan or static, moving object, fast
/// handheld, long HDR handheld, dark, Bayer, 2x detail).
fn suite() -> Vec<Case> {
    let mean = FluxSpec::Mean { flux: 0.1 };
    let dark = FluxSpec::Mean { flux: 0.02 };
    let hdr = FluxSpec::Percentile {
        percentile: 50.0,
        peak: 0.1,
    };
    let handheld = || "handheld".parse::<MotionConfig>().expect("known motion");
    let fast = MotionConfig::FastHandheld {
        amplitude_px: 40.0,
        rotation_deg: 2.0,
        cycles: 3.0,
    };
    let full = (254, 496);
    let small = (127, 248); // 2x-detail sensor: ~2.9 photograph pixels per sensor pixel
    let case = |set, scene, motion_name: &'static str, motion: MotionConfig, frames, flux| Case {
        set,
        scene,
        motion_name,
        motion,
        frames,
        flux,
        cfa: CfaKind::ColorSpad,
        size: full,
        supersampling: 1,
        seed: 0,
    };
    use SuiteSet::{Tuning as T, Validation as V};
    let mut cases = vec![
        case(T, "kodim02.png", "handheld", handheld(), 512, mean),
        case(T, "kodim07.png", "static", MotionConfig::Static, 512, mean),
        case(
            T,
            "kodim15.png",
            "object",
            "object".parse().expect("known"),
            512,
            mean,
        ),
        case(T, "kodim15.png", "fast handheld", fast.clone(), 512, mean),
        case(
            T,
            "ScanLines_StillLife.exr",
            "handheld",
            handheld(),
            2000,
            hdr,
        ),
        case(T, "kodim02.png", "handheld", handheld(), 2000, dark),
        Case {
            cfa: CfaKind::Bayer,
            ..case(T, "kodim07.png", "handheld", handheld(), 512, mean)
        },
        Case {
            size: small,
            supersampling: 2,
            ..case(T, "kodim15.png", "handheld", handheld(), 2000, mean)
        },
        case(
            V,
            "kodim04.png",
            "pan",
            "pan".parse().expect("known"),
            512,
            mean,
        ),
        case(
            V,
            "kodim12.png",
            "object",
            "object".parse().expect("known"),
            512,
            mean,
        ),
        case(V, "kodim22.png", "fast handheld", fast, 512, mean),
        case(
            V,
            "ScanLines_Cannon.exr",
            "pan",
            "pan".parse().expect("known"),
            2000,
            hdr,
        ),
        case(
            V,
            "MultiResolution_Bonita.exr",
            "handheld",
            handheld(),
            3000,
            hdr,
        ),
        case(V, "kodim12.png", "handheld", handheld(), 2000, dark),
        Case {
            cfa: CfaKind::Bayer,
            ..case(V, "kodim04.png", "handheld", handheld(), 512, mean)
        },
        Case {
            size: small,
            supersampling: 2,
            ..case(V, "kodim22.png", "handheld", handheld(), 2000, mean)
        },
    ];
    let (mut t, mut v) = (200, 300);
    for c in &mut cases {
        let next = if c.set == T { &mut t } else { &mut v };
        c.seed = *next;
        *next += 1;
    }
    cases
}

fn simulate_case(scenes: &Path, case: &Case) -> Result<SimulatedCapture> {
    let path = scenes.join(case.scene);
    let scene = Scene::load(&path)?;
    let (height, width) = case.size;
    let config = SimulationConfig {
        height,
        width,
        frames: case.frames,
        flux: case.flux,
        motion: case.motion.clone(),
        hot_fraction: 0.02,
        seed: case.seed,
        pixel_supersampling: case.supersampling,
        ..SimulationConfig::default()
    };
    let pattern = match case.cfa {
        CfaKind::ColorSpad => Pattern::Colorspad,
        CfaKind::Bayer => Pattern::Bayer,
    };
    let cfa = cfa::generate(&pattern, height, width, 0)?;
    Ok(simulate_with_cfa(&config, &scene, &cfa, &Silent)?)
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
const BURST: usize = 0;
const TRUE_MOTION: usize = 1;
const LONG: usize = 2;
const SHORT: usize = 3;
const DENOISER_MERGE: usize = 4;
const BM3D: usize = 5;
const CHROMA: usize = 6;

/// Scores of the 2x-detail captures against the 2x ground truth.
struct SuperResolution {
    /// The 1x burst upsampled by bicubic interpolation.
    bicubic: Scores,
    /// The burst merged at scale 2.
    scale2: Scores,
    /// The true-motion merge at scale 2 (what scale 2 can give with perfect alignment).
    scale2_true: Scores,
    /// The 1x ground truth upsampled by bicubic interpolation: how much of the 2x truth lies
    /// beyond what interpolation of a perfect 1x image recovers (lower = more sub-pixel detail).
    bicubic_truth: Scores,
}

/// One row of the report.
struct Row {
    case: usize,
    scores: [Scores; 7],
    /// LPIPS (AlexNet v0.1) of each column, on the same sRGB images as `scores`.
    lpips: [f64; 7],
    /// Median alignment end-point error, px.
    epe: f64,
    /// Median true motion, px (at the same pixels and frames).
    motion_px: f64,
    sr: Option<SuperResolution>,
    seconds: f64,
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
    (median(&mut errors), median(&mut magnitudes))
}

/// Median (upper median for an even count); NaN for no values.
fn median<T: Copy + Into<f64>>(values: &mut [T]) -> f64 {
    if values.is_empty() {
        return f64::NAN;
    }
    let mid = values.len() / 2;
    let (_, m, _) = values.select_nth_unstable_by(mid, |a, b| (*a).into().total_cmp(&(*b).into()));
    (*m).into()
}

/// Keys cubic convolution weight (a = −0.5) at distance `d`.
fn keys(d: f32) -> f32 {
    const A: f32 = -0.5;
    let d = d.abs();
    if d <= 1.0 {
        ((A + 2.0) * d - (A + 3.0)) * d * d + 1.0
    } else if d < 2.0 {
        ((A * d - 5.0 * A) * d + 8.0 * A) * d - 4.0 * A
    } else {
        0.0
    }
}

/// Bicubic (Keys, a = −0.5) upsampling of an (H, W, C) image by `scale` on the merge's scale-s
/// grid: output pixel (Y, X) interpolates the input at ((Y + ½)/s − ½, (X + ½)/s − ½); edges
/// are clamped.
fn bicubic_upsample(image: ArrayView3<f32>, scale: usize) -> Array3<f32> {
    // Taps (4 clamped source indices and weights) of every output coordinate along one axis.
    let taps = |n: usize| -> Vec<([usize; 4], [f32; 4])> {
        (0..n * scale)
            .map(|o| {
                let p = (o as f32 + 0.5) / scale as f32 - 0.5;
                let base = p.floor();
                let f = p - base;
                let mut idx = [0usize; 4];
                let mut wts = [0.0f32; 4];
                for k in 0..4 {
                    let i = base as isize - 1 + k as isize;
                    idx[k] = i.clamp(0, n as isize - 1) as usize;
                    wts[k] = keys(f - (k as f32 - 1.0));
                }
                (idx, wts)
            })
            .collect()
    };
    let (h, w, c) = image.dim();
    let (ty, tx) = (taps(h), taps(w));
    // Along x, then along y.
    let mut rows = Array3::<f32>::zeros((h, w * scale, c));
    for y in 0..h {
        for (xo, (idx, wts)) in tx.iter().enumerate() {
            for ch in 0..c {
                rows[[y, xo, ch]] = (0..4).map(|k| wts[k] * image[[y, idx[k], ch]]).sum();
            }
        }
    }
    let mut out = Array3::<f32>::zeros((h * scale, w * scale, c));
    for (yo, (idx, wts)) in ty.iter().enumerate() {
        for xo in 0..w * scale {
            for ch in 0..c {
                out[[yo, xo, ch]] = (0..4).map(|k| wts[k] * rows[[idx[k], xo, ch]]).sum();
            }
        }
    }
    out
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
    let (burst, scored) = score_methods(&capture, &sim, case, opts, burst_config, &oracle)?;
    let scores = scored.map(|(s, _)| s);
    let lpips = scored.map(|(_, l)| l);
    let (epe, motion_px) = median_epe(&burst, &sim.motion, case.frames, opts.border);
    let sr = super_resolution(&capture, &sim, case, opts, burst_config, &oracle, &burst)?;
    let row = Row {
        case: index,
        scores,
        lpips,
        epe,
        motion_px,
        sr,
        seconds: started.elapsed().as_secs_f64(),
    };
    log_case(case, &row, simulated_s);
    Ok(row)
}

/// Reconstructs `capture` by every method of [`METHODS`] (burst, burst at the true motion
/// `oracle`, naive long and short, the denoiser's merge alone and with both denoisers) and
/// scores each against the ground truth (PSNR / SSIM and LPIPS, one protocol); returns the
/// burst reconstruction with the scores, in [`METHODS`] order.
fn score_methods(
    capture: &Capture,
    sim: &SimulatedCapture,
    case: &Case,
    opts: &EvalOptions,
    burst_config: &BurstConfig,
    oracle: MotionOracle<'_>,
) -> Result<(BurstReconstruction, [(Scores, f64); 7])> {
    let reference = capture.reference_frame();
    let config = burst_config.clone();
    let burst = reconstruct_burst(capture, reference, &config, &Silent)?;
    let truth = reconstruct_burst_with_motion(capture, reference, &config, Some(oracle), &Silent)?;
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
    let denoised = |method| -> Result<(Scores, f64)> {
        let config = DenoiseConfig {
            method,
            ..denoised_config.denoise.clone()
        };
        let (out, _) = denoise_linear(for_denoising.merged.linear.view(), &input, &config)?;
        score(out.view())
    };
    let scored = [
        score(burst.merged.linear.view())?,
        score(truth.merged.linear.view())?,
        score(long.linear.view())?,
        score(short.linear.view())?,
        score(for_denoising.merged.linear.view())?,
        denoised(DenoiseMethod::Bm3d)?,
        denoised(DenoiseMethod::ChromaBm3d)?,
    ];
    Ok((burst, scored))
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
        "{}: {:.1} s (simulation {simulated_s:.1} s); burst {:.2} dB (LPIPS {:.3}), true \
         motion {:.2} dB, EPE {:.3} px (motion {:.2} px){}",
        case.id(),
        row.seconds,
        row.scores[BURST].psnr_srgb,
        row.lpips[BURST],
        row.scores[TRUE_MOTION].psnr_srgb,
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

/// The burst parameters of `path` (TOML, the `[burst]` table of report.toml), or the defaults.
fn read_burst_config(path: Option<&Path>) -> Result<BurstConfig> {
    read_toml_config(path)
}

/// A configuration table read from the TOML file `path`, or the defaults without one.
fn read_toml_config<T: serde::de::DeserializeOwned + Default>(path: Option<&Path>) -> Result<T> {
    match path {
        Some(path) => crate::config_file::read(path),
        None => Ok(T::default()),
    }
}

fn or_default(values: &[f32], default: f32) -> Vec<f32> {
    if values.is_empty() {
        vec![default]
    } else {
        values.to_vec()
    }
}

fn quality(
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

/// Mean of `f` over `rows`.
fn mean_of(rows: &[&Row], f: impl Fn(&Row) -> f64) -> f64 {
    rows.iter().map(|r| f(r)).sum::<f64>() / rows.len().max(1) as f64
}

/// The Markdown report: one section per set.
fn report(
    cases: &[Case],
    rows: &[Row],
    set: SuiteSet,
    only: Option<&str>,
    total_s: f64,
) -> Result<String> {
    let mut md = String::new();
    writeln!(md, "# Benchmarks\n")?;
    let mut command = "quantacolor bench quality --scenes ../shared/data/scenes".to_string();
    if set != SuiteSet::All {
        write!(
            command,
            " --set {}",
            if set == SuiteSet::Tuning {
                "tuning"
            } else {
                "validation"
            }
        )?;
    }
    if let Some(o) = only {
        write!(command, " --only {o}")?;
    }
    writeln!(
        md,
        "Generated by `{command}` (do not edit by hand; {} captures, {total_s:.0} s on {} \
         threads). Simulated SPAD captures (paper Table 1) of 496x254 with the real colour-SPAD \
         CFA (Bayer where marked) and 2 % hot pixels; 0.1 photons/pixel/frame (dark captures \
         0.02; HDR scenes: median W pixel at 0.1). Two sets: **tuning** (kodim02, kodim07, \
         kodim15, ScanLines_StillLife; seeds 200+) to tune parameters on, and **validation** \
         (kodim04, kodim12, kodim22, ScanLines_Cannon, MultiResolution_Bonita; seeds 300+), \
         held out to check that the tuning generalises. Each set holds a handheld capture, a pan \
         or static one, a moving object, fast handheld motion (40 px, 2°, 3 cycles over 512 \
         frames), a long HDR handheld capture, a dark capture, a Bayer capture and a 2x-detail \
         capture.\n",
        rows.len(),
        rayon::current_num_threads()
    )?;
    writeln!(
        md,
        "Scores: 16-pixel border excluded, both images scaled so the ground truth's 99.5th \
         percentile is 1, clipped, sRGB-encoded; PSNR (dB) / SSIM / LPIPS (AlexNet v0.1, the \
         paper's Table 2 metric; lower is better). Naive short uses 1/16 of the \
         frames. Only the BM3D columns are denoised (paper §4.3): plain colour BM3D (one σ) and \
         chroma-BM3D, both with σ from the merge's noise model, on the merge the denoiser runs \
         on (colour kernels with spacing exponent 0.5 instead of 1, the column before them). \
         `reconstruct` runs burst + chroma-BM3D by default; `--denoise none` gives the first \
         column. EPE: median alignment end-point error |merge flow − true flow| (px) over the \
         pixels (16-pixel border excluded) at 16 evenly spaced frames; for moving objects over \
         all pixels (camera and object). Motion: the median true displacement from the \
         reference frame over the same pixels and frames (the EPE of assuming no motion). Time: \
         wall-clock seconds for the capture (simulation and every column).\n"
    )?;
    writeln!(
        md,
        "2x-detail captures: a 248x127 sensor viewing the photograph at about 2.9 photograph \
         pixels per sensor pixel, the scene kept at half-pixel detail and each pixel integrating \
         it over its 2x2 sub-pixel area (`SimulationConfig::pixel_supersampling = 2`); the \
         1x columns are scored against the pixel-area ground truth, and the super-resolution \
         table against the 2x ground truth (496x254, each value the scene over its own \
         half-pixel area, 32-pixel border excluded): the burst merged at `--scale 2` against \
         the 1x burst upsampled by bicubic interpolation (Keys, a = −0.5). The last column \
         upsamples the 1x ground truth the same way: the ceiling of interpolation, and a \
         measure of how much detail the scene holds beyond a pixel.\n"
    )?;
    for section in [SuiteSet::Tuning, SuiteSet::Validation] {
        let set_rows: Vec<&Row> = rows
            .iter()
            .filter(|r| cases[r.case].set == section)
            .collect();
        if set_rows.is_empty() {
            continue;
        }
        report_set(&mut md, cases, &set_rows, section)?;
    }
    Ok(md)
}

/// One set's section of the report: the scores table, the super-resolution table (2x-detail
/// captures) and the summary against the targets.
fn report_set(md: &mut String, cases: &[Case], rows: &[&Row], section: SuiteSet) -> Result<()> {
    let title = if section == SuiteSet::Tuning {
        "Tuning set"
    } else {
        "Validation set"
    };
    writeln!(md, "## {title}\n")?;
    let means = write_scores_table(md, cases, rows)?;
    let sr_rows: Vec<(&Row, &SuperResolution)> = rows
        .iter()
        .filter_map(|r| r.sr.as_ref().map(|sr| (*r, sr)))
        .collect();
    write_super_resolution_table(md, cases, &sr_rows)?;
    write_summary(md, cases, rows, title, &means, &sr_rows)
}

/// The table of every method's PSNR / SSIM / LPIPS per capture, with EPE, motion and time, and
/// its mean row; returns the means (PSNR, SSIM, LPIPS) per method.
fn write_scores_table(
    md: &mut String,
    cases: &[Case],
    rows: &[&Row],
) -> Result<Vec<(f64, f64, f64)>> {
    writeln!(
        md,
        "| capture | {} | EPE (px) | motion (px) | time (s) |",
        METHODS.join(" | ")
    )?;
    writeln!(md, "|---|{}---|---|---|", "---|".repeat(METHODS.len()))?;
    for row in rows {
        let cells: Vec<String> = row
            .scores
            .iter()
            .zip(&row.lpips)
            .map(|(s, l)| format!("{:.2} / {:.3} / {l:.3}", s.psnr_srgb, s.ssim_srgb))
            .collect();
        writeln!(
            md,
            "| {} | {} | {:.3} | {:.2} | {:.0} |",
            cases[row.case].label(),
            cells.join(" | "),
            row.epe,
            row.motion_px,
            row.seconds
        )?;
    }
    let means: Vec<(f64, f64, f64)> = (0..METHODS.len())
        .map(|k| {
            (
                mean_of(rows, |r| r.scores[k].psnr_srgb),
                mean_of(rows, |r| r.scores[k].ssim_srgb),
                mean_of(rows, |r| r.lpips[k]),
            )
        })
        .collect();
    writeln!(
        md,
        "| **mean** | {} | | | |",
        means
            .iter()
            .map(|m| format!("**{:.2} / {:.3} / {:.3}**", m.0, m.1, m.2))
            .collect::<Vec<_>>()
            .join(" | ")
    )?;
    Ok(means)
}

/// The super-resolution table of the 2x-detail captures (nothing without them).
fn write_super_resolution_table(
    md: &mut String,
    cases: &[Case],
    sr_rows: &[(&Row, &SuperResolution)],
) -> Result<()> {
    if !sr_rows.is_empty() {
        writeln!(md, "\nSuper-resolution, against the 2x ground truth:\n")?;
        writeln!(
            md,
            "| capture | bicubic(burst 1x) | burst scale 2 | scale 2 − bicubic (dB) | scale 2, true motion | bicubic(1x ground truth) |"
        )?;
        writeln!(md, "|---|---|---|---|---|---|")?;
        for (row, sr) in sr_rows {
            writeln!(
                md,
                "| {} | {:.2} / {:.3} | {:.2} / {:.3} | {:+.2} | {:.2} / {:.3} | {:.2} / {:.3} |",
                cases[row.case].label(),
                sr.bicubic.psnr_srgb,
                sr.bicubic.ssim_srgb,
                sr.scale2.psnr_srgb,
                sr.scale2.ssim_srgb,
                sr.scale2.psnr_srgb - sr.bicubic.psnr_srgb,
                sr.scale2_true.psnr_srgb,
                sr.scale2_true.ssim_srgb,
                sr.bicubic_truth.psnr_srgb,
                sr.bicubic_truth.ssim_srgb
            )?;
        }
    }
    Ok(())
}

/// The set's summary: each target of the benchmark against the measured means.
fn write_summary(
    md: &mut String,
    cases: &[Case],
    rows: &[&Row],
    title: &str,
    means: &[(f64, f64, f64)],
    sr_rows: &[(&Row, &SuperResolution)],
) -> Result<()> {
    writeln!(
        md,
        "\nSummary ({}, {} captures):\n",
        title.to_lowercase(),
        rows.len()
    )?;
    write_merge_summary(md, cases, rows, means, sr_rows)?;
    write_denoise_summary(md, rows, means)
}

/// The summary's lines on the merge: against the true-motion merge and the naive baselines,
/// SSIM wins, motion errors and super-resolution.
fn write_merge_summary(
    md: &mut String,
    cases: &[Case],
    rows: &[&Row],
    means: &[(f64, f64, f64)],
    sr_rows: &[(&Row, &SuperResolution)],
) -> Result<()> {
    let n = rows.len();
    let gap = |r: &Row| r.scores[BURST].psnr_srgb - r.scores[TRUE_MOTION].psnr_srgb;
    let worst = rows
        .iter()
        .min_by(|a, b| gap(a).total_cmp(&gap(b)))
        .expect("non-empty set");
    writeln!(
        md,
        "- burst − true-motion merge: {:+.2} dB on average (target within 0.5 dB), worst {:+.2} dB \
         on {} (target no capture more than 1.5 dB below)",
        means[BURST].0 - means[TRUE_MOTION].0,
        gap(worst),
        cases[worst.case].label()
    )?;
    writeln!(
        md,
        "- burst − naive long: {:+.2} dB (target >= +2 dB; paper +2.2 dB)",
        means[BURST].0 - means[LONG].0
    )?;
    writeln!(
        md,
        "- burst − naive short: {:+.2} dB (target >= +5 dB; paper +5.4 dB)",
        means[BURST].0 - means[SHORT].0
    )?;
    let ssim_wins = rows
        .iter()
        .filter(|r| {
            r.scores[BURST].ssim_srgb > r.scores[LONG].ssim_srgb
                && r.scores[BURST].ssim_srgb > r.scores[SHORT].ssim_srgb
        })
        .count();
    writeln!(
        md,
        "- burst SSIM above both naive baselines on {ssim_wins} of {n} captures"
    )?;
    for (kind, target) in [("fast handheld", 0.5), ("handheld", 0.15)] {
        let epes: Vec<String> = rows
            .iter()
            .filter(|r| cases[r.case].motion_name == kind)
            .map(|r| format!("{:.3} px ({})", r.epe, cases[r.case].id()))
            .collect();
        if !epes.is_empty() {
            writeln!(
                md,
                "- median EPE, {kind}: {} (target <= {target} px)",
                epes.join(", ")
            )?;
        }
    }
    if !sr_rows.is_empty() {
        let diffs: Vec<f64> = sr_rows
            .iter()
            .map(|(_, sr)| sr.scale2.psnr_srgb - sr.bicubic.psnr_srgb)
            .collect();
        writeln!(
            md,
            "- 2x: scale 2 − bicubic(1x): {:+.2} dB on average over {} capture(s) (target >= +0.5 dB)",
            diffs.iter().sum::<f64>() / diffs.len() as f64,
            diffs.len()
        )?;
    }
    Ok(())
}

/// The summary's lines on denoising: chroma-BM3D against the merge it runs on, the default
/// merge, plain colour BM3D, and every method's LPIPS.
fn write_denoise_summary(md: &mut String, rows: &[&Row], means: &[(f64, f64, f64)]) -> Result<()> {
    let n = rows.len();
    writeln!(
        md,
        "- chroma-BM3D − the same merge without denoising: {:+.2} dB (target >= +1.5 dB)",
        means[CHROMA].0 - means[DENOISER_MERGE].0
    )?;
    writeln!(
        md,
        "- chroma-BM3D − burst without denoising (default merge; end to end): {:+.2} dB",
        means[CHROMA].0 - means[BURST].0
    )?;
    let chroma_ssim_wins = rows
        .iter()
        .filter(|r| r.scores[CHROMA].ssim_srgb > r.scores[BM3D].ssim_srgb)
        .count();
    writeln!(
        md,
        "- chroma-BM3D − plain colour BM3D: SSIM {:+.4} on average, higher on {chroma_ssim_wins} \
         of {n} captures (target: higher); PSNR {:+.2} dB",
        means[CHROMA].1 - means[BM3D].1,
        means[CHROMA].0 - means[BM3D].0
    )?;
    writeln!(
        md,
        "- mean LPIPS (lower is better): {}",
        METHODS
            .iter()
            .zip(means)
            .map(|(name, m)| format!("{name} {:.3}", m.2))
            .collect::<Vec<_>>()
            .join("; ")
    )?;
    let lpips_wins = rows
        .iter()
        .filter(|r| r.lpips[CHROMA] < r.lpips[BURST])
        .count();
    writeln!(
        md,
        "- chroma-BM3D (default) − burst without denoising: LPIPS {:+.3} on average, lower on \
         {lpips_wins} of {n} captures (target: every capture); mean SSIM {:.3} (target >= 0.85; \
         paper 0.788), mean LPIPS {:.3} (target <= 0.25; paper 0.267)\n",
        means[CHROMA].2 - means[BURST].2,
        means[CHROMA].1,
        means[CHROMA].2
    )?;
    Ok(())
}

/// Naive sums timed in each round of [`speed`]: it takes tens of milliseconds against about a
/// second for the pipeline, so more samples of it cost little and steady its median.
const NAIVE_RUNS_PER_ROUND: usize = 3;

/// One timed run of the default pipeline in [`speed`].
struct WholeRun {
    whole_s: f64,
    burst_s: f64,
    denoise_s: f64,
    blocks: usize,
    sub_blocks: usize,
    timings: Vec<StageTiming>,
}

/// Seconds of one timed call of `f`, with its result.
fn timed<T>(f: impl FnOnce() -> Result<T>) -> Result<(f64, T)> {
    let start = Instant::now();
    let out = f()?;
    Ok((start.elapsed().as_secs_f64(), out))
}

fn speed(
    frames: usize,
    runs: usize,
    (pipeline, name): (&ReconstructConfig, &str),
    progress: &dyn Progress,
) -> Result<()> {
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
    // Rounds of NAIVE_RUNS_PER_ROUND naive sums and one run of the default pipeline (its merge
    // takes the denoiser's kernel settings, as `reconstruct`), so that a slow spell of the
    // machine slows both sides of the ratio.
    let mut naive_times = Vec::with_capacity(runs * NAIVE_RUNS_PER_ROUND);
    let mut whole_runs = Vec::with_capacity(runs);
    for _ in 0..runs.max(1) {
        for _ in 0..NAIVE_RUNS_PER_ROUND {
            let (seconds, naive) = timed(|| {
                Ok(reconstruct_naive(
                    &capture,
                    reference,
                    &NaiveConfig::default(),
                )?)
            })?;
            std::hint::black_box(&naive);
            naive_times.push(seconds);
        }
        let (whole_s, (burst_s, burst, denoise_s)) = timed(|| {
            let (burst_s, burst) = timed(|| {
                Ok(reconstruct_burst(
                    &capture,
                    reference,
                    &burst_config_for(pipeline),
                    &Silent,
                )?)
            })?;
            let (denoise_s, denoised) = timed(|| {
                let input = denoise_input(&capture, Some(&burst), frames);
                Ok(denoise_linear(
                    burst.merged.linear.view(),
                    &input,
                    &pipeline.denoise,
                )?)
            })?;
            std::hint::black_box(&denoised);
            Ok((burst_s, burst, denoise_s))
        })?;
        // What the report needs of the run; the reconstruction is dropped untimed.
        whole_runs.push(WholeRun {
            whole_s,
            burst_s,
            denoise_s,
            blocks: burst.alignment.plan.len(),
            sub_blocks: burst.sub_blocks.len(),
            timings: burst.timings.clone(),
        });
    }
    let naive_s = median(&mut naive_times);
    whole_runs.sort_by(|a, b| a.whole_s.total_cmp(&b.whole_s));
    let whole_range = (
        whole_runs[0].whole_s,
        whole_runs[whole_runs.len() - 1].whole_s,
    );
    let WholeRun {
        whole_s,
        burst_s,
        denoise_s,
        blocks,
        sub_blocks,
        timings,
    } = whole_runs.swap_remove(whole_runs.len() / 2);
    println!(
        "{frames} frames 496x254, {} threads, medians of {runs} rounds: naive {naive_s:.3} s \
         ({} runs, {:.3}-{:.3} s), burst (align + merge) {burst_s:.3} s, ratio {:.1}x",
        rayon::current_num_threads(),
        naive_times.len(),
        naive_times.iter().copied().fold(f64::INFINITY, f64::min),
        naive_times.iter().copied().fold(0.0, f64::max),
        burst_s / naive_s
    );
    println!("  {blocks} alignment blocks, {sub_blocks} sub-blocks merged");
    for t in &timings {
        println!("  {:<32} {:.3} s", t.stage, t.seconds);
    }
    println!(
        "  {:<32} {denoise_s:.3} s ({:.1}x the naive sum)",
        format!("denoise ({})", pipeline.denoise.method),
        denoise_s / naive_s
    );
    println!(
        "whole {name} (align, merge, denoise): {whole_s:.3} s ({:.3}-{:.3} s), ratio \
         {:.1}x the naive sum",
        whole_range.0,
        whole_range.1,
        whole_s / naive_s
    );
    Ok(())
}

fn video(
    frames: usize,
    stride: usize,
    motion: &MotionConfig,
    denoise: Option<DenoiseMethod>,
    seed: u64,
    progress: &dyn Progress,
) -> Result<()> {
    let config = SimulationConfig {
        frames,
        flux: FluxSpec::Mean { flux: 0.1 },
        motion: motion.clone(),
        hot_fraction: 0.02,
        seed,
        ..SimulationConfig::default()
    };
    let scene = Scene::from_spec("builtin:chart")?;
    let cfa = colorspad_cfa();
    eprintln!("simulating {frames} frames of 496x254 (not timed)");
    let sim = simulate_with_cfa(&config, &scene, &cfa, progress)?;
    let capture = sim.to_capture()?;
    let references = video_reference_frames(frames, stride)?;
    if references.is_empty() {
        bail!("--stride {stride} leaves no reference frame in {frames} frames");
    }
    let truths = ground_truth_at(&config, &scene, &cfa, &references)?;
    let mut rc = ReconstructConfig::default();
    if let Some(d) = denoise {
        rc.denoise.method = d;
    }
    let opts = EvalOptions {
        border: 16,
        normalize_percentile: Some(99.5),
    };

    eprintln!(
        "per-reference path: {} full reconstructions",
        references.len()
    );
    let start = Instant::now();
    let mut old = Vec::new();
    for &r in &references {
        let cfg = ReconstructConfig {
            reference_frame: Some(r),
            ..rc.clone()
        };
        old.push(reconstruct(&capture, &cfg, &Silent)?.linear);
    }
    let old_s = start.elapsed().as_secs_f64();

    eprintln!("reuse path: motion once, then guide + merge + denoise per frame");
    let start = Instant::now();
    let reconstructor = VideoReconstructor::for_frames(&capture, &rc, &references, &Silent)?;
    let shared_s = start.elapsed().as_secs_f64();
    let mut new = Vec::new();
    let mut frame_stages: Vec<(String, f64)> = Vec::new();
    for &r in &references {
        let rec = reconstructor.frame(r, &Silent)?;
        for t in &rec.timings {
            match frame_stages.iter_mut().find(|(s, _)| *s == t.stage) {
                Some((_, total)) => *total += t.seconds,
                None => frame_stages.push((t.stage.clone(), t.seconds)),
            }
        }
        new.push(rec.linear);
    }
    let new_s = start.elapsed().as_secs_f64();
    let fallback = reconstructor.fallback_reason().map(str::to_string);
    let shared_stages = reconstructor.shared_timings().to_vec();
    drop(reconstructor);

    println!(
        "video: {frames} frames 496x254, {motion:?} motion, stride {stride} ({} reference \
         frames), denoise {}, {} threads",
        references.len(),
        rc.denoise.method,
        rayon::current_num_threads()
    );
    if let Some(reason) = &fallback {
        println!("  reuse path fell back to per-frame reconstruction: {reason}");
    }
    println!(
        "  per-reference path {old_s:.2} s ({:.2} s/frame); reuse path {new_s:.2} s \
         (shared motion {shared_s:.2} s + {:.2} s/frame): speed-up {:.2}x",
        old_s / references.len() as f64,
        (new_s - shared_s) / references.len() as f64,
        old_s / new_s
    );
    for t in &shared_stages {
        println!("    once:      {:<32} {:.3} s", t.stage, t.seconds);
    }
    for (stage, total) in &frame_stages {
        println!(
            "    per frame: {stage:<32} {:.3} s",
            total / references.len() as f64
        );
    }
    println!("  reference   PSNR/SSIM vs truth: per-reference    reuse     reuse vs per-reference");
    let (mut sum_old, mut sum_new) = (0.0, 0.0);
    for (i, &r) in references.iter().enumerate() {
        let a = evaluate(old[i].view(), truths[i].view(), &opts)?;
        let b = evaluate(new[i].view(), truths[i].view(), &opts)?;
        let c = evaluate(new[i].view(), old[i].view(), &opts)?;
        sum_old += a.psnr_srgb;
        sum_new += b.psnr_srgb;
        println!(
            "  {r:>9}   {:>24.2} dB {:.4}   {:.2} dB {:.4}   {:.2} dB",
            a.psnr_srgb, a.ssim_srgb, b.psnr_srgb, b.ssim_srgb, c.psnr_srgb
        );
    }
    let n = references.len() as f64;
    println!(
        "  mean PSNR (sRGB, border 16): per-reference {:.2} dB, reuse {:.2} dB ({:+.2} dB)",
        sum_old / n,
        sum_new / n,
        (sum_new - sum_old) / n
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

/// The settings `bench denoise` tries.
struct DenoiseGrid {
    luma_gains: Vec<f32>,
    chroma_gains: Vec<f32>,
    merge_k_denoise: Vec<Option<f32>>,
    chroma_scales: Vec<usize>,
    coarse_sigma_factors: Vec<f32>,
}

/// One setting of the grid.
#[derive(Debug, Clone, Copy, PartialEq)]
struct DenoiseSetting {
    merge_k_denoise: Option<f32>,
    luma_gain: f32,
    chroma_gain: f32,
    chroma_scales: usize,
    coarse_sigma_factor: f32,
}

/// The suite's captures of `set` (those whose id contains `only`), simulated.
fn suite_captures(
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

fn denoise_grid(
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
    fn settings(&self) -> Vec<DenoiseSetting> {
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_denoise_grid_tries_coarse_factors_only_with_coarse_scales() {
        let grid = DenoiseGrid {
            luma_gains: vec![1.0, 1.5],
            chroma_gains: vec![2.0],
            merge_k_denoise: vec![None],
            chroma_scales: vec![0, 1],
            coarse_sigma_factors: vec![0.5, 0.7],
        };
        let settings = grid.settings();
        // Per luma gain: scales 0 once, scales 1 with each factor.
        assert_eq!(settings.len(), 2 * (1 + 2));
        let factors: Vec<(usize, f32)> = settings[..3]
            .iter()
            .map(|s| (s.chroma_scales, s.coarse_sigma_factor))
            .collect();
        assert_eq!(factors, vec![(0, 0.5), (1, 0.5), (1, 0.7)]);
        assert!(settings[3..].iter().all(|s| s.luma_gain == 1.5));
    }

    #[test]
    fn keys_weights_interpolate_and_sum_to_one() {
        assert_eq!(keys(0.0), 1.0);
        assert_eq!(keys(1.0), 0.0);
        assert_eq!(keys(2.0), 0.0);
        for f in [0.1f32, 0.25, 0.5, 0.75] {
            let sum: f32 = (0..4).map(|k| keys(f - (k as f32 - 1.0))).sum();
            assert!((sum - 1.0).abs() < 1e-6, "{f}: {sum}");
        }
    }

    #[test]
    fn bicubic_reproduces_a_quadratic_away_from_the_edges() {
        // Keys' a = −0.5 kernel reproduces polynomials up to degree 2.
        let f = |y: f32, x: f32| 0.3 + 0.02 * y - 0.01 * x + 0.001 * x * x + 0.002 * x * y;
        let image =
            Array3::from_shape_fn((12, 14, 2), |(y, x, c)| f(y as f32, x as f32) + c as f32);
        let up = bicubic_upsample(image.view(), 2);
        assert_eq!(up.dim(), (24, 28, 2));
        for yo in 4..20 {
            for xo in 4..24 {
                let (y, x) = ((yo as f32 + 0.5) / 2.0 - 0.5, (xo as f32 + 0.5) / 2.0 - 0.5);
                for c in 0..2 {
                    let want = f(y, x) + c as f32;
                    assert!((up[[yo, xo, c]] - want).abs() < 1e-4, "({yo}, {xo}, {c})");
                }
            }
        }
        // Constants everywhere, edges included.
        let flat = Array3::from_elem((5, 7, 3), 0.7f32);
        assert!(bicubic_upsample(flat.view(), 2)
            .iter()
            .all(|v| (v - 0.7).abs() < 1e-6));
    }
}
