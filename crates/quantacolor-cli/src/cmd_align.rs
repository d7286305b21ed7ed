//! `quantacolor align`: block-level alignment of a capture (paper §4.1) into flow.npy and
//! flow.toml.

#![forbid(unsafe_code)]

use crate::output::StagedDir;
use anyhow::Result;
use clap::Args;
use quantacolor::align::{align, write_alignment, AlignConfig};
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
    #[arg(long, allow_hyphen_values = true)]
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
