//! `quantacolor align` and `quantacolor calibrate-dcr`.

use crate::output::StagedDir;
use anyhow::{Context, Result};
use clap::Args;
use quantacolor::align::{
    align, dark_count_rate_map, hot_pixel_mask, write_alignment, AlignConfig,
};
use quantacolor::capture::{io, Capture};
use quantacolor::progress::Progress;
use std::path::PathBuf;

#[derive(Debug, Args)]
pub struct AlignArgs {
    /// Capture directory.
    pub capture: PathBuf,
    /// Output directory for flow.npy and flow.toml.
    #[arg(long)]
    pub out: PathBuf,
    /// Reference frame (default: the capture's, else T/2).
    #[arg(long)]
    pub reference_frame: Option<usize>,
    /// Frames per temporal block (default: chosen from T and the light level, 100–1000).
    #[arg(long)]
    pub block_size: Option<usize>,
    /// Use only frames A:B of the capture (they become frames 0..B-A).
    #[arg(long)]
    pub frames: Option<quantacolor::capture::FrameWindow>,
    /// Do not detect hot pixels when the capture names no mask.
    #[arg(long)]
    pub no_hot_pixel_detection: bool,
}

pub fn run_align(args: &AlignArgs, progress: &dyn Progress) -> Result<()> {
    let capture = crate::cmd_convert::open_capture(
        &args.capture,
        args.frames.as_ref(),
        !args.no_hot_pixel_detection,
    )?;
    let reference = args
        .reference_frame
        .unwrap_or_else(|| capture.reference_frame());
    let mut config = AlignConfig::default();
    config.blocks.block_size = args.block_size;
    let alignment = align(
        &capture.frames,
        &capture.cfa,
        capture.hot_pixels.as_ref(),
        reference,
        &config,
        progress,
    )?;
    let staged = StagedDir::new(&args.out)?;
    write_alignment(staged.path(""), &alignment)?;
    staged.commit()?;
    Ok(())
}

#[derive(Debug, Args)]
pub struct CalibrateDcrArgs {
    /// Capture of dark frames (lens capped).
    pub dark_capture: PathBuf,
    /// Pixels whose dark count rate exceeds this (counts per second) are marked hot.
    #[arg(long, default_value_t = 30.0)]
    pub threshold_cps: f64,
    /// Output hot-pixel mask, bool (H, W) .npy; the rate map (float32 cps) is written beside it
    /// with `_rate` appended to the stem.
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run_calibrate_dcr(args: &CalibrateDcrArgs) -> Result<()> {
    if !(args.threshold_cps.is_finite() && args.threshold_cps >= 0.0) {
        anyhow::bail!("--threshold-cps must be a non-negative number");
    }
    let capture = Capture::open(&args.dark_capture)?;
    let rates = dark_count_rate_map(&capture.frames, capture.meta.exposure_s)?;
    let mask = hot_pixel_mask(&rates, args.threshold_cps as f32);
    let stem = args
        .out
        .file_stem()
        .with_context(|| format!("{}: not a file name", args.out.display()))?
        .to_string_lossy()
        .into_owned();
    let rate_path = args.out.with_file_name(format!("{stem}_rate.npy"));
    io::write_npy(&rate_path, &rates)?;
    io::write_npy(&args.out, &mask)?;
    let hot = mask.iter().filter(|&&m| m).count();
    println!(
        "{hot} hot pixels of {} ({:.2} %) above {} cps; mean rate {:.2} cps",
        mask.len(),
        100.0 * hot as f64 / mask.len() as f64,
        args.threshold_cps,
        rates.mean().unwrap_or(0.0)
    );
    Ok(())
}
