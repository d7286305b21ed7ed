//! `quantacolor eval`: PSNR and SSIM of an estimate against ground truth.

use anyhow::Result;
use clap::Args;
use quantacolor::capture::io;
use quantacolor::metrics::{evaluate, EvalOptions};
use std::path::PathBuf;

#[derive(Debug, Args)]
pub struct EvalArgs {
    /// Estimate, float32 (H, W, 3) .npy (e.g. OUT/linear.npy).
    pub estimate: PathBuf,
    /// Ground truth, float32 (H, W, 3) .npy (e.g. CAPTURE/ground_truth.npy).
    pub ground_truth: PathBuf,
    /// Pixels cropped from every border before scoring.
    #[arg(long, default_value_t = 0)]
    pub border: usize,
    /// Scale both images so this percentile of the ground truth is 1 (default 99.5; 0 = none).
    #[arg(long, default_value_t = 99.5)]
    pub normalize_percentile: f64,
}

pub fn run(args: &EvalArgs) -> Result<()> {
    let estimate = io::read_npy_3d::<f32>(&args.estimate)?;
    let truth = io::read_npy_3d::<f32>(&args.ground_truth)?;
    let opts = EvalOptions {
        border: args.border,
        normalize_percentile: (args.normalize_percentile > 0.0)
            .then_some(args.normalize_percentile),
    };
    let s = evaluate(estimate.view(), truth.view(), &opts)?;
    println!("psnr_linear = {:.3}", s.psnr_linear);
    println!("ssim_linear = {:.4}", s.ssim_linear);
    println!("psnr_srgb = {:.3}", s.psnr_srgb);
    println!("ssim_srgb = {:.4}", s.ssim_srgb);
    Ok(())
}
