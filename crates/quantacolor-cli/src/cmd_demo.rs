//! `quantacolor demo`: simulate the built-in chart under handheld motion, reconstruct it with
//! the burst method and the naive long/short baselines (paper Table 2), write `demo/` (with the
//! comparison page `index.html` of `quantacolor report`), print PSNR/SSIM.

#![forbid(unsafe_code)]

use crate::cmd_reconstruct::write_reconstruction;
use crate::output::StagedDir;
use anyhow::Result;
use clap::Args;
use ndarray::Array3;
use quantacolor::capture::{io, Capture};
use quantacolor::denoise::chroma::DenoiseMethod;
use quantacolor::display::{auto_exposure_scale, encode_srgb8, RenderOptions};
use quantacolor::metrics::{evaluate, EvalOptions, Scores};
use quantacolor::pipeline::{reconstruct, Method, ReconstructConfig};
use quantacolor::progress::Progress;
use quantacolor::report::{labelled_hstack, write_report_files, ReportConfig, ResultDir};
use quantacolor::simulate::{self, FluxSpec, MotionConfig, Scene, SimulationConfig};
use serde::Serialize;
use std::path::{Path, PathBuf};

#[derive(Debug, Args)]
pub struct DemoArgs {
    /// Output directory.
    #[arg(long, default_value = "demo")]
    pub out: PathBuf,
    /// Replace the files of an existing, non-empty output directory (refused otherwise).
    #[arg(long)]
    pub overwrite: bool,
    /// Seed of the simulation.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
}

#[derive(Serialize)]
struct Row {
    method: String,
    frames_used: usize,
    seconds: f64,
    #[serde(flatten)]
    scores: Scores,
}

/// Border excluded from the scores, px (as the project benchmark).
const SCORE_BORDER: usize = 16;

/// The methods the demo compares: name, method, frames used (all when `None`).
fn demo_methods(frames: usize) -> [(&'static str, Method, Option<usize>); 3] {
    let short = (frames / 16).max(1);
    [
        ("burst", Method::Burst, None),
        ("naive-long", Method::Naive, None),
        ("naive-short", Method::Naive, Some(short)),
    ]
}

pub fn run(args: &DemoArgs, progress: &dyn Progress) -> Result<()> {
    // The demo replaces its own earlier output (rerunning the README's first command); any
    // other directory is kept unless --overwrite.
    let earlier_demo = ["metrics.toml", "comparison.png"]
        .iter()
        .all(|f| args.out.join(f).is_file());
    crate::output::check_out_dir(&args.out, "--out", args.overwrite || earlier_demo)?;
    let (capture_dir, frames, truth) = simulate_chart(args, progress)?;
    let capture = Capture::open(&capture_dir)?;
    let methods = demo_methods(frames);
    let mut panels = Panels::new(&truth);
    let mut rows = Vec::new();
    for (name, method, window) in methods {
        rows.extend(reconstruct_and_score(
            args,
            &capture_dir,
            &capture,
            (name, method, window),
            &truth,
            &mut panels,
            progress,
        )?);
    }
    write_comparison(args, &methods, &panels, &truth, &rows, progress)?;
    print_table(&rows);
    crate::output::say(&format!(
        "wrote {} and {}",
        args.out.join("comparison.png").display(),
        args.out.join("index.html").display()
    ));
    Ok(())
}

/// Simulates the built-in chart under handheld motion into `out/capture`; returns that
/// directory, the number of frames and the ground truth.
fn simulate_chart(
    args: &DemoArgs,
    progress: &dyn Progress,
) -> Result<(PathBuf, usize, Array3<f32>)> {
    let config = SimulationConfig {
        frames: 512,
        height: 254,
        width: 496,
        cfa: "rgbw-75-bluenoise".into(),
        flux: FluxSpec::Mean { flux: 0.1 },
        motion: "handheld".parse::<MotionConfig>()?,
        seed: args.seed,
        ..SimulationConfig::default()
    };
    eprintln!(
        "simulating builtin:chart, handheld motion, {} frames of {}x{}, {} photons/pixel/frame, CFA {}",
        config.frames, config.width, config.height, 0.1, config.cfa
    );
    let sim = simulate::simulate(&config, &Scene::from_spec("builtin:chart")?, progress)?;
    let capture_dir = args.out.join("capture");
    sim.write(&capture_dir)?;
    Ok((capture_dir, config.frames, sim.ground_truth))
}

/// The images of `comparison.png` (sRGB at the truth's exposure) and their labels.
struct Panels {
    scale: f32,
    images: Vec<Array3<u8>>,
    labels: Vec<Vec<String>>,
}

impl Panels {
    fn new(truth: &Array3<f32>) -> Self {
        let scale = auto_exposure_scale(truth.view());
        Panels {
            scale,
            images: vec![encode_srgb8(truth.view(), scale)],
            labels: vec![vec!["ground truth".into()]],
        }
    }

    fn push(&mut self, image: &Array3<f32>, name: String, scores: &Scores) {
        self.images.push(encode_srgb8(image.view(), self.scale));
        self.labels.push(vec![
            name,
            format!("PSNR {:.2} SSIM {:.3}", scores.psnr_srgb, scores.ssim_srgb),
        ]);
    }
}

/// Reconstructs the capture with one method into `out/<name>`, scores it (and the burst's
/// merge before denoising) against the truth and adds its panels.
fn reconstruct_and_score(
    args: &DemoArgs,
    capture_dir: &Path,
    capture: &Capture,
    (name, method, window): (&str, Method, Option<usize>),
    truth: &Array3<f32>,
    panels: &mut Panels,
    progress: &dyn Progress,
) -> Result<Vec<Row>> {
    let opts = EvalOptions {
        border: SCORE_BORDER,
        normalize_percentile: Some(99.5),
    };
    let mut rc = ReconstructConfig {
        method,
        ..Default::default()
    };
    rc.naive.window = window;
    if method == Method::Naive {
        // The baselines of paper Table 2 are plain sums.
        rc.denoise.method = DenoiseMethod::None;
    }
    let rec = reconstruct(capture, &rc, progress)?;
    let preview = RenderOptions {
        w_weights: capture.meta.w_weights,
        ..RenderOptions::default()
    };
    write_reconstruction(
        &args.out.join(name),
        capture_dir,
        capture,
        &rc,
        &rec,
        &preview,
    )?;
    let seconds = rec.timings.iter().map(|t| t.seconds).sum();
    let mut rows = Vec::new();
    if let Some(merged) = &rec.merged_linear {
        let denoise_seconds: f64 = rec
            .timings
            .iter()
            .filter(|t| t.stage == "denoise")
            .map(|t| t.seconds)
            .sum();
        let scores = evaluate(merged.view(), truth.view(), &opts)?;
        panels.push(merged, format!("{name} (no denoise)"), &scores);
        rows.push(Row {
            method: format!("{name}-before-denoise"),
            frames_used: rec.frames_used,
            seconds: seconds - denoise_seconds,
            scores,
        });
    }
    let scores = evaluate(rec.linear.view(), truth.view(), &opts)?;
    panels.push(&rec.linear, name.to_string(), &scores);
    rows.push(Row {
        method: name.to_string(),
        frames_used: rec.frames_used,
        seconds,
        scores,
    });
    Ok(rows)
}

/// Writes `comparison.png`, the comparison page over the methods' results, the ground truth and
/// `metrics.toml` into `out`, all at once.
fn write_comparison(
    args: &DemoArgs,
    methods: &[(&str, Method, Option<usize>)],
    panels: &Panels,
    truth: &Array3<f32>,
    rows: &[Row],
    progress: &dyn Progress,
) -> Result<()> {
    let staged = StagedDir::new(&args.out)?;
    let views: Vec<_> = panels.images.iter().map(|i| i.view()).collect();
    io::write_png_rgb8(
        staged.path("comparison.png"),
        &labelled_hstack(&views, &panels.labels, 4, 255),
    )?;
    // The comparison page over the three results (report::write_report_files).
    let results = methods
        .iter()
        .map(|(name, _, _)| ResultDir::open(&args.out.join(name)))
        .collect::<Result<Vec<_>, _>>()?;
    let page = ReportConfig {
        title: "quantacolor demo: builtin:chart, handheld".into(),
        border: SCORE_BORDER,
        ..ReportConfig::default()
    };
    write_report_files(staged.dir(), &results, Some(truth.view()), &page, progress)?;
    io::write_npy(staged.path("ground_truth.npy"), truth)?;
    #[derive(Serialize)]
    struct Table<'a> {
        layout: &'static str,
        scoring: &'static str,
        methods: &'a [Row],
    }
    let table = Table {
        layout: "comparison.png: ground truth | burst without denoising | burst (chroma-bm3d) | naive long | naive short (1/16 of the frames), same exposure, method and sRGB PSNR/SSIM under each; index.html: the comparison page (quantacolor report)",
        scoring: "16-pixel border excluded, normalized so the ground truth's 99.5th percentile is 1, clipped to [0, 1]",
        methods: rows,
    };
    std::fs::write(staged.path("metrics.toml"), toml::to_string_pretty(&table)?)?;
    staged.commit()?;
    Ok(())
}

/// The scores and times of every method on standard output.
fn print_table(rows: &[Row]) {
    println!(
        "{:<22} {:>7} {:>9} {:>9} {:>9} {:>9} {:>8}",
        "method", "frames", "PSNR lin", "SSIM lin", "PSNR sRGB", "SSIM sRGB", "time s"
    );
    for r in rows {
        println!(
            "{:<22} {:>7} {:>9.2} {:>9.4} {:>9.2} {:>9.4} {:>8.2}",
            r.method,
            r.frames_used,
            r.scores.psnr_linear,
            r.scores.ssim_linear,
            r.scores.psnr_srgb,
            r.scores.ssim_srgb,
            r.seconds
        );
    }
}
