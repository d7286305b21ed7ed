//! `quantacolor reconstruct`: capture directory -> linear.npy, linear.exr, preview.png,
//! report.toml.

use crate::output::StagedDir;
use anyhow::{Context, Result};
use clap::Args;
use quantacolor::capture::{io, Capture};
use quantacolor::display::{auto_exposure_scale, encode_srgb8};
use quantacolor::pipeline::{reconstruct, Method, ReconstructConfig, Reconstruction};
use quantacolor::progress::Progress;
use serde::Serialize;
use std::path::{Path, PathBuf};

#[derive(Debug, Args)]
pub struct ReconstructArgs {
    /// Capture directory (frames.npy, cfa.npy or cfa.png, capture.toml).
    pub capture: PathBuf,
    /// Output directory.
    #[arg(long)]
    pub out: PathBuf,
    /// Reconstruction method.
    #[arg(long, default_value = "naive")]
    pub method: Method,
    /// Reference frame (default: the capture's, else T/2).
    #[arg(long)]
    pub reference_frame: Option<usize>,
    /// Naive method: number of frames centred on the reference frame (default: all).
    #[arg(long)]
    pub window: Option<usize>,
}

#[derive(Serialize)]
struct Report<'a> {
    capture: String,
    method: String,
    reference_frame: usize,
    frames_used: usize,
    height: usize,
    width: usize,
    units: &'static str,
    preview_exposure_scale: f32,
    config: &'a ReconstructConfig,
    timings: &'a [quantacolor::pipeline::StageTiming],
}

pub fn run(args: &ReconstructArgs, progress: &dyn Progress) -> Result<()> {
    let capture = Capture::open(&args.capture)?;
    let mut config = ReconstructConfig {
        method: args.method,
        reference_frame: args.reference_frame,
        ..Default::default()
    };
    config.naive.window = args.window;
    let rec = reconstruct(&capture, &config, progress)?;
    write_reconstruction(&args.out, &args.capture, &config, &rec)?;
    Ok(())
}

/// Writes the reconstruction files into `out` (staged, then moved into place).
pub fn write_reconstruction(
    out: &Path,
    capture_dir: &Path,
    config: &ReconstructConfig,
    rec: &Reconstruction,
) -> Result<()> {
    let staged = StagedDir::new(out)?;
    io::write_npy(staged.path("linear.npy"), &rec.linear)?;
    io::write_exr_rgb(staged.path("linear.exr"), &rec.linear)?;
    let scale = auto_exposure_scale(rec.linear.view());
    io::write_png_rgb8(
        staged.path("preview.png"),
        &encode_srgb8(rec.linear.view(), scale),
    )?;
    let (height, width, _) = rec.linear.dim();
    let report = Report {
        capture: capture_dir.display().to_string(),
        method: config.method.to_string(),
        reference_frame: rec.reference_frame,
        frames_used: rec.frames_used,
        height,
        width,
        units: "mean photon detections per binary frame of an R, G or B pixel, dark counts removed",
        preview_exposure_scale: scale,
        config,
        timings: &rec.timings,
    };
    let text = toml::to_string_pretty(&report).context("serialising report.toml")?;
    std::fs::write(staged.path("report.toml"), text)
        .with_context(|| format!("{}: cannot write", staged.path("report.toml").display()))?;
    staged.commit()?;
    Ok(())
}
