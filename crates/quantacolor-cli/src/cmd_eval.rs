//! `quantacolor eval`: PSNR, SSIM and LPIPS of an estimate against ground truth (paper §6,
//! Table 2). LPIPS (AlexNet v0.1, weights built into the library) scores the same sRGB images
//! as `psnr_srgb` / `ssim_srgb` (`metrics::evaluate_lpips`).

#![forbid(unsafe_code)]

use anyhow::{bail, Result};
use clap::Args;
use ndarray::Array3;
use quantacolor::capture::io;
use quantacolor::metrics::{evaluate, evaluate_lpips, EvalOptions, LPIPS_MIN_SIZE};
use std::path::{Path, PathBuf};

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
    /// Skip LPIPS (the slowest score, ~0.2 s per 496x254 pair on 2 cores).
    #[arg(long)]
    pub no_lpips: bool,
}

pub fn run(args: &EvalArgs) -> Result<()> {
    let estimate = read_image(&args.estimate, "linear.npy")?;
    let truth = read_image(&args.ground_truth, "ground_truth.npy")?;
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
    if !args.no_lpips {
        let (h, w, c) = estimate.dim();
        let side = h.min(w).saturating_sub(2 * args.border);
        if c == 3 && side >= LPIPS_MIN_SIZE {
            let l = evaluate_lpips(estimate.view(), truth.view(), &opts)?;
            println!("lpips_srgb = {l:.4}");
        } else {
            eprintln!(
                "note: no LPIPS: it needs RGB images of at least {LPIPS_MIN_SIZE}x{LPIPS_MIN_SIZE} \
                 pixels after the border crop (got {h}x{w}x{c}, border {})",
                args.border
            );
        }
    }
    Ok(())
}

/// An (H, W, 3) float32 image from `path`; a directory (a reconstruction or capture folder given
/// where its file was meant) is an error naming the file inside it that was probably meant.
fn read_image(path: &Path, usual_file: &str) -> Result<Array3<f32>> {
    if path.is_dir() {
        bail!(
            "{} is a directory: give the .npy file inside it (e.g. {})",
            path.display(),
            path.join(usual_file).display()
        );
    }
    Ok(io::read_npy_3d::<f32>(path)?)
}
