//! `quantacolor inspect`: a capture's size, CFA, light level per channel, hot pixels and
//! suggested block size, with an optional naive-average preview.

#![forbid(unsafe_code)]

use crate::cmd_convert::open_capture;
use anyhow::Result;
use clap::Args;
use quantacolor::align::hot_pixels::HotPixelDetectConfig;
use quantacolor::capture::FrameWindow;
use quantacolor::display::{write_rendered, BitDepth, RenderOptions};
use quantacolor::naive::{reconstruct_naive, NaiveConfig};
use std::path::PathBuf;

#[derive(Debug, Args)]
pub struct InspectArgs {
    /// Capture directory.
    pub capture: PathBuf,
    /// Write a naive-average preview image (PNG or TIFF) of the inspected frames.
    #[arg(long)]
    pub preview: Option<PathBuf>,
    /// Inspect only frames A:B.
    #[arg(long, allow_hyphen_values = true)]
    pub frames: Option<FrameWindow>,
}

pub fn run(args: &InspectArgs) -> Result<()> {
    let mut capture = open_capture(&args.capture, args.frames.as_ref(), false)?;
    let (summary, mask) =
        quantacolor::inspect::summarize(&capture, &HotPixelDetectConfig::default())?;
    println!("capture       {}", args.capture.display());
    println!(
        "frames        {} of {}x{} (H x W), {:.3e} s each",
        summary.frames, summary.height, summary.width, summary.exposure_s
    );
    println!("channel  fraction  detections/frame  flux (λ, detections/frame)");
    for c in &summary.channels {
        println!(
            "{:>7}  {:>7.2}%  {:>16.5}  {:>10.5}",
            c.channel,
            100.0 * c.fraction,
            c.detections_per_frame,
            c.flux
        );
    }
    println!(
        "hot pixels    {} ({:.2} %, {})",
        summary.hot_pixels,
        100.0 * summary.hot_pixels as f64 / (summary.height * summary.width) as f64,
        match summary.hot_pixel_origin {
            quantacolor::inspect::HotPixelOrigin::Capture => "from the capture's mask",
            quantacolor::inspect::HotPixelOrigin::Detected => "detected from the frames",
        }
    );
    println!(
        "block size    {} frames (suggested)",
        summary.suggested_block_size
    );
    if let Some(path) = &args.preview {
        capture.hot_pixels = Some(mask);
        let reference = capture.reference_frame();
        let naive = reconstruct_naive(&capture, reference, &NaiveConfig::default())?;
        let options = RenderOptions {
            w_weights: capture.meta.w_weights,
            ..RenderOptions::default()
        };
        write_rendered(path, naive.linear.view(), &options, BitDepth::Eight)?;
    }
    Ok(())
}
