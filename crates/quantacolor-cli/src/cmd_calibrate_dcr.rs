//! `quantacolor calibrate-dcr`: per-pixel dark count rates and a hot-pixel mask from a dark
//! capture.

#![forbid(unsafe_code)]

use anyhow::{Context, Result};
use clap::Args;
use quantacolor::align::{dark_count_rate_map, hot_pixel_mask};
use quantacolor::capture::{io, Capture};
use std::path::PathBuf;

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

pub fn run(args: &CalibrateDcrArgs) -> Result<()> {
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
