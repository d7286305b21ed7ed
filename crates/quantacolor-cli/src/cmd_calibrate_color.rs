//! `quantacolor calibrate-color`: fits a colour-correction matrix (paper §7, Fig. 14) from a
//! reconstruction of the built-in ColorChecker chart (`simulate --scene builtin:chart`, then
//! `reconstruct`), with the patches located from the chart layout for the image's (H, W).

#![forbid(unsafe_code)]

use anyhow::Result;
use clap::Args;
use quantacolor::capture::io;
use quantacolor::display::{chart_patch_means, ColorMatrix};
use std::path::PathBuf;

#[derive(Debug, Args)]
pub struct CalibrateColorArgs {
    /// Linear reconstruction of the built-in chart, float32 (H, W, 3) .npy.
    pub linear: PathBuf,
    /// Output TOML file with a [color_matrix] table (for `display --ccm`).
    #[arg(long)]
    pub out: PathBuf,
    /// Fit a 3x4 affine matrix (with an offset per channel) instead of 3x3.
    #[arg(long)]
    pub affine: bool,
}

pub fn run(args: &CalibrateColorArgs) -> Result<()> {
    let linear = io::read_npy_3d::<f32>(&args.linear)?;
    let means = chart_patch_means(linear.view())
        .map_err(|e| anyhow::anyhow!("{}: {e}", args.linear.display()))?;
    let fit = ColorMatrix::fit(&means, args.affine)
        .map_err(|e| anyhow::anyhow!("{}: {e}", args.linear.display()))?;
    fit.matrix.write(&args.out)?;
    let r = fit.residual;
    println!(
        "exposure gain (neutral patches) = {:.6}",
        fit.matrix.gain.unwrap_or(1.0)
    );
    println!(
        "mean delta E76: {:.3} before, {:.3} after",
        r.delta_e_before, r.delta_e_after
    );
    println!(
        "RMS linear error: {:.5} before, {:.5} after",
        r.rms_before, r.rms_after
    );
    crate::output::say(&format!("wrote {}", args.out.display()));
    Ok(())
}
