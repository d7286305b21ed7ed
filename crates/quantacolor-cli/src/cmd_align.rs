//! `quantacolor align`: the motion estimation of `quantacolor reconstruct` (paper §4.1 block
//! alignment, then this project's sub-block refinement, fast-motion tracking and photon
//! trajectory) on a capture, written as the block flow (flow.npy, flow.toml) and the camera
//! motion of every frame (camera.npy, docs/motion.md).

#![forbid(unsafe_code)]

use crate::output::StagedDir;
use anyhow::Result;
use clap::Args;
use quantacolor::align::write_alignment;
use quantacolor::burst::estimate_burst_motion;
use quantacolor::capture::io;
use quantacolor::pipeline::{Profile, ReconstructConfig};
use quantacolor::progress::Progress;
use std::path::PathBuf;

#[derive(Debug, Args)]
pub struct AlignArgs {
    /// Capture directory.
    pub capture: PathBuf,
    /// Output directory for flow.npy, flow.toml and camera.npy.
    #[arg(long)]
    pub out: PathBuf,
    /// Replace the files of an existing, non-empty output directory (refused otherwise).
    #[arg(long)]
    pub overwrite: bool,
    /// TOML file with a full or partial reconstruction config, as `quantacolor reconstruct
    /// --config` takes it (its [burst] settings and reference_frame apply); command-line
    /// options override it.
    #[arg(long)]
    pub config: Option<PathBuf>,
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
    crate::output::check_out_dir(&args.out, "--out", args.overwrite)?;
    let mut config = match &args.config {
        Some(path) => crate::cmd_reconstruct::read_config(path, Profile::Default)?,
        None => ReconstructConfig::default(),
    };
    if args.block_size.is_some() {
        config.burst.align.blocks.block_size = args.block_size;
    }
    let capture = crate::cmd_convert::open_capture(
        &args.capture,
        args.frames.as_ref(),
        !args.no_hot_pixel_detection,
    )?;
    let reference = args
        .reference_frame
        .or(config.reference_frame)
        .unwrap_or_else(|| capture.reference_frame());
    let estimate = estimate_burst_motion(&capture, reference, &config.burst, progress)?;
    let camera = estimate
        .motion
        .camera_matrices(capture.frames.frame_count());
    let staged = StagedDir::new(&args.out)?;
    write_alignment(staged.path(""), &estimate.alignment)?;
    io::write_npy(staged.path("camera.npy"), &camera)?;
    staged.commit()?;
    Ok(())
}
