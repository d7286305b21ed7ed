//! `quantacolor reconstruct`: capture directory -> linear.npy, linear.exr, preview.png,
//! report.toml.

#![forbid(unsafe_code)]

use crate::cmd_display::ToneMapArg;
use crate::output::StagedDir;
use anyhow::Result;
use clap::Args;
use quantacolor::capture::{io, Capture};
use quantacolor::denoise::chroma::DenoiseMethod;
use quantacolor::display::{ColorMatrix, MesopicConfig, MesopicOffset, RenderOptions};
use quantacolor::pipeline::{
    reconstruct, Method, Profile, ReconstructConfig, ReconstructOverrides, Reconstruction,
};
use quantacolor::progress::Progress;
use quantacolor::video::{
    reconstruct_frame, FrameProgress, VideoPlan, VideoReconstructor, VideoReport, VideoWriter,
};
use std::path::{Path, PathBuf};

#[derive(Debug, Args)]
pub struct ReconstructArgs {
    /// Capture directory (frames.npy, cfa.npy or cfa.png, capture.toml).
    pub capture: PathBuf,
    /// Output directory.
    #[arg(long)]
    pub out: PathBuf,
    /// Replace the files of an existing, non-empty output directory (refused otherwise).
    #[arg(long)]
    pub overwrite: bool,
    /// Reconstruction method: burst (align + joint demosaic-merge) or naive (plain sum of the
    /// frames, not denoised unless --denoise is given).
    #[arg(long)]
    pub method: Option<Method>,
    /// TOML file with a full or partial reconstruction config (see report.toml for the keys),
    /// laid over the profile; command-line options override it.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Named settings: default, or fast (longer sub-blocks, one refinement pass, BM3D's fast
    /// profile: about 1.4x faster, 0.1-0.2 dB lower; docs/speed.md).
    /// report.toml lists the settings that ran.
    #[arg(long, default_value_t = Profile::Default)]
    pub profile: Profile,
    /// Denoising (paper §4.3): chroma-bm3d (BM3D in the W-weighted YCbCr, chroma filtered
    /// harder), bm3d (plain colour BM3D, one σ) or none [default: chroma-bm3d; none with --method
    /// naive].
    #[arg(long)]
    pub denoise: Option<DenoiseMethod>,
    /// σ of Y (of all channels for bm3d) in the variance-stabilised domain, where one merged
    /// binomial count has σ 1 (default: the merge's noise model; see report.toml).
    #[arg(long)]
    pub sigma_y: Option<f32>,
    /// σ of Cb and Cr in the variance-stabilised domain (chroma-bm3d; default: noise model).
    #[arg(long)]
    pub sigma_c: Option<f32>,
    /// Burst method: frames per temporal block for alignment (default: from T and light level).
    #[arg(long)]
    pub block_size: Option<usize>,
    /// Burst method: output grid scale (2 = super-resolution).
    #[arg(long)]
    pub scale: Option<usize>,
    /// Burst method: largest camera motion inside one sub-block, px (smaller = more, shorter
    /// sub-blocks; default 0.35).
    #[arg(long)]
    pub max_sub_block_motion: Option<f64>,
    /// Write intermediate stages (block grey images, flow, camera motion camera.npy as
    /// `quantacolor align` writes it, reference, merged planes) as .npy.
    #[arg(long)]
    pub dump_stages: Option<PathBuf>,
    /// Reconstruct a video: one image per reference frame, every `--stride` frames (the paper's
    /// supplementary videos), each from the --window frames around it. Writes frame_NNNNN.png,
    /// linear.npy (N, H, W, 3) and video.toml as the frames are made (memory of one frame).
    #[arg(long)]
    pub video: bool,
    /// Video: `per-frame` estimates the motion again for every reference frame (a full
    /// reconstruction each); `shared` estimates the camera motion once, at the reference frame,
    /// and composes it to every video frame (per frame only the moving-object alignment, the
    /// merge and the denoiser run): 1.6x faster on 4000 frames at stride 500, 0.1–0.4 dB lower
    /// on average (`quantacolor bench video`).
    #[arg(long, value_enum, default_value_t = VideoMotion::PerFrame)]
    pub video_motion: VideoMotion,
    /// Frames between consecutive video reference frames.
    #[arg(long, default_value_t = 256)]
    pub stride: usize,
    /// Reference frame (default: the capture's, else T/2).
    #[arg(long)]
    pub reference_frame: Option<usize>,
    /// Number of frames centred on the reference frame: the frames the naive method sums, and
    /// with --video the frames each video frame is reconstructed from, whatever the method
    /// (time linear in the recording's length; default: all frames).
    #[arg(long)]
    pub window: Option<usize>,
    /// Tone mapping of preview.png (re-render later with `quantacolor display`).
    #[arg(long, value_enum, default_value_t = ToneMapArg::Global)]
    pub tonemap: ToneMapArg,
    /// Noise-aware low-light view of preview.png (supplement Eq. 9–10): offset L0 in decades
    /// of detections, or `auto` (L0 from the measured noise); see `quantacolor display --help`.
    #[arg(long, value_name = "L0|auto", allow_hyphen_values = true)]
    pub mesopic: Option<MesopicOffset>,
    /// Colour matrix for preview.png from `quantacolor calibrate-color`.
    #[arg(long)]
    pub ccm: Option<PathBuf>,
    /// Use only frames A:B of the capture (they become frames 0..B-A).
    #[arg(long, allow_hyphen_values = true)]
    pub frames: Option<quantacolor::capture::FrameWindow>,
    /// Do not detect hot pixels when the capture names no mask.
    #[arg(long)]
    pub no_hot_pixel_detection: bool,
}

pub fn run(args: &ReconstructArgs, progress: &dyn Progress) -> Result<()> {
    crate::output::check_out_dir(&args.out, "--out", args.overwrite)?;
    if let Some(dir) = &args.dump_stages {
        crate::output::check_out_dir(dir, "--dump-stages", args.overwrite)?;
    }
    let config = config_from_args(args)?;
    let capture = crate::cmd_convert::open_capture(
        &args.capture,
        args.frames.as_ref(),
        !args.no_hot_pixel_detection,
    )?;
    if args.video {
        return write_video(args, &capture, &config, progress);
    }
    let rec = reconstruct(&capture, &config, progress)?;
    if let Some(dir) = &args.dump_stages {
        dump_stages(dir, &capture, &rec)?;
    }
    let preview = preview_options(args, &capture, rec.frames_used)?;
    write_reconstruction(&args.out, &args.capture, &capture, &config, &rec, &preview)?;
    Ok(())
}

/// Render options of preview.png from the command line, for a reconstruction merged from
/// `frames_used` frames.
pub fn preview_options(
    args: &ReconstructArgs,
    capture: &Capture,
    frames_used: usize,
) -> Result<RenderOptions> {
    Ok(RenderOptions {
        exposure: None,
        color_matrix: match &args.ccm {
            Some(p) => Some(ColorMatrix::read(p)?),
            None => None,
        },
        tonemap: args.tonemap.to_tone_map(),
        mesopic: args.mesopic.map(|l0| MesopicConfig {
            l0,
            frames: Some(frames_used as f64),
        }),
        w_weights: capture.meta.w_weights,
    })
}

/// The reconstruction config: the profile, then `--config`, then the other options.
pub fn config_from_args(args: &ReconstructArgs) -> Result<ReconstructConfig> {
    let mut config = match &args.config {
        Some(path) => read_config(path, args.profile)?,
        None => args.profile.config()?,
    };
    ReconstructOverrides {
        method: args.method,
        reference_frame: args.reference_frame,
        window: args.window,
        block_size: args.block_size,
        scale: args.scale,
        denoise: args.denoise,
        sigma_y: args.sigma_y,
        sigma_c: args.sigma_c,
        max_sub_block_motion: args.max_sub_block_motion,
    }
    .apply(&mut config, &|key| format!("--{}", key.replace('_', "-")))?;
    Ok(config)
}

/// A full or partial reconstruction config from the TOML file `path` laid over `profile`'s
/// settings, every stage's settings checked before any work (a bad denoiser setting would
/// otherwise surface after the merge); errors name the file.
pub fn read_config(path: &Path, profile: Profile) -> Result<ReconstructConfig> {
    let config: ReconstructConfig = crate::config_file::read_over(profile.toml(), path)?;
    config
        .denoise
        .bm3d_config()
        .validate()
        .map_err(|e| anyhow::anyhow!("{}: [denoise]: {e}", path.display()))?;
    config
        .burst
        .validate()
        .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
    Ok(config)
}

/// Writes the intermediate stages of a burst reconstruction as .npy files into `dir`.
fn dump_stages(dir: &Path, capture: &Capture, rec: &Reconstruction) -> Result<()> {
    let Some(burst) = &rec.burst else {
        anyhow::bail!("--dump-stages needs --method burst");
    };
    let staged = StagedDir::new(dir)?;
    // Raw block sums (before hot-pixel correction), uint32 (n_blocks, H, W).
    let sums: Vec<_> = burst
        .alignment
        .plan
        .blocks
        .iter()
        .map(|r| capture.frames.sum_range(r.clone()))
        .collect();
    let views: Vec<_> = sums.iter().map(|s| s.view()).collect();
    io::write_npy(
        staged.path("block_sums.npy"),
        &ndarray::stack(ndarray::Axis(0), &views)?,
    )?;
    let greys: Vec<_> = burst.alignment.grey.iter().map(|g| g.view()).collect();
    io::write_npy(
        staged.path("grey_blocks.npy"),
        &ndarray::stack(ndarray::Axis(0), &greys)?,
    )?;
    io::write_npy(staged.path("flow.npy"), &burst.alignment.flow)?;
    io::write_npy(staged.path("reference.npy"), &burst.merged.reference)?;
    io::write_npy(
        staged.path("merged_planes_rgbw.npy"),
        &burst.merged.planes.flux,
    )?;
    io::write_npy(
        staged.path("effective_frames_rgbw.npy"),
        &burst.merged.planes.effective_frames,
    )?;
    if let Some(merged) = &rec.merged_linear {
        io::write_npy(staged.path("merged_linear.npy"), merged)?;
    }
    let maps = burst.robustness_maps()?;
    let robustness: Vec<_> = maps.iter().map(|r| r.view()).collect();
    io::write_npy(
        staged.path("robustness.npy"),
        &ndarray::stack(ndarray::Axis(0), &robustness)?,
    )?;
    quantacolor::align::write_alignment(staged.path(""), &burst.alignment)?;
    // The camera motion of every frame, as `quantacolor align` writes it (docs/motion.md).
    io::write_npy(
        staged.path("camera.npy"),
        &burst.motion.camera_matrices(capture.frames.frame_count()),
    )?;
    staged.commit()?;
    Ok(())
}

/// Writes the reconstruction files into `out` (the library's
/// [`quantacolor::output::write_reconstruction`], with the capture named as given).
pub fn write_reconstruction(
    out: &Path,
    capture_dir: &Path,
    capture: &Capture,
    config: &ReconstructConfig,
    rec: &Reconstruction,
    preview: &RenderOptions,
) -> Result<()> {
    quantacolor::output::write_reconstruction(
        out,
        &capture_dir.display().to_string(),
        capture,
        config,
        rec,
        preview,
    )?;
    Ok(())
}

/// How `--video` gets the motion of each frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum VideoMotion {
    /// A full reconstruction per reference frame.
    PerFrame,
    /// The camera motion estimated once and composed to every frame ([`VideoReconstructor`]).
    Shared,
}

/// Reconstructions with a sliding reference frame, written as numbered PNGs with one shared
/// exposure plus the linear stack; with `--video-motion shared` the motion is estimated once
/// for all of them ([`VideoReconstructor`]).
fn write_video(
    args: &ReconstructArgs,
    capture: &Capture,
    config: &ReconstructConfig,
    progress: &dyn Progress,
) -> Result<()> {
    let plan = VideoPlan::new(capture.frames.frame_count(), args.stride, args.window)?;
    let video = match args.video_motion {
        VideoMotion::Shared if !plan.whole_capture() => anyhow::bail!(
            "--video-motion shared estimates one motion over the whole capture; with --window \
             use --video-motion per-frame (each frame reconstructed from its own window)"
        ),
        VideoMotion::Shared => Some(VideoReconstructor::for_frames(
            capture,
            config,
            &plan.reference_frames(),
            progress,
        )?),
        VideoMotion::PerFrame => None,
    };
    let mut writer = VideoWriter::create(&args.out, plan.frames.len())?;
    for frame in &plan.frames {
        let progress = FrameProgress::new(progress, frame, &plan);
        let rec = match &video {
            Some(video) => video.frame(frame.reference_frame, &progress)?,
            None => reconstruct_frame(capture, config, frame, &progress)?,
        };
        writer.push(rec.linear.view())?;
    }
    let mut report = VideoReport::new(args.capture.display().to_string(), config, &plan);
    if let Some(video) = &video {
        match video.fallback_reason() {
            None => report.motion_anchor_frame = Some(video.anchor_frame()),
            Some(reason) => report.per_frame_reason = Some(reason.to_string()),
        }
    }
    writer.finish(report)?;
    Ok(())
}
