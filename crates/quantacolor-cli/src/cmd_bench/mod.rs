//! `quantacolor bench`: the project's quality and speed benchmarks. Every ratio is against a
//! baseline measured in the same run; nothing here is asserted by the test suite.
//!
//! One file per subcommand: [`quality`] (with its captures in [`suite`] and its report in
//! [`markdown`]), [`speed`], [`video`], [`denoise`] and [`long`] (its child-process and disk
//! queries are in `crate::os_usage`, outside this module's `forbid(unsafe_code)`).

#![forbid(unsafe_code)]

mod denoise;
mod long;
mod markdown;
mod quality;
mod speed;
mod splat;
mod suite;
mod video;

use anyhow::Result;
use clap::{Args, Subcommand};
use denoise::{chart_captures, denoise_grid, suite_captures, DenoiseGrid};
use quantacolor::burst::BurstConfig;
use quantacolor::denoise::chroma::{DenoiseConfig, DenoiseMethod};
use quantacolor::pipeline::Profile;
use quantacolor::progress::Progress;
use quantacolor::simulate::MotionConfig;
use std::ffi::OsString;
use std::path::{Path, PathBuf};

#[derive(Debug, Args)]
pub struct BenchArgs {
    #[command(subcommand)]
    pub command: BenchCommand,
}

/// Which captures of the quality suite to run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum SuiteSet {
    /// The captures to tune parameters on.
    Tuning,
    /// Held-out captures (other photographs, other seeds) that check the tuning generalises.
    Validation,
    /// Both.
    All,
}

#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// Quality suite on real photographs, as a tuning set and a held-out validation set: burst
    /// vs true-motion merge vs naive long/short vs chroma-BM3D, alignment end-point error, and
    /// super-resolution (scale 2) against bicubic upsampling; writes a Markdown report.
    Quality {
        /// Folder with the photographs (kodim*.png) and OpenEXR samples (the project's
        /// shared/data/scenes).
        #[arg(long, default_value = "../shared/data/scenes")]
        scenes: PathBuf,
        /// Markdown output.
        #[arg(long, default_value = "BENCHMARKS.md")]
        out: PathBuf,
        /// Which set of captures to run (tuning runs are about half the time).
        #[arg(long, value_enum, default_value_t = SuiteSet::All)]
        set: SuiteSet,
        /// Only the captures whose id contains this text (debugging; see the ids on stderr).
        #[arg(long, hide = true)]
        only: Option<String>,
        /// TOML with burst (align + refine + merge) parameters to use instead of the defaults
        /// (the `[burst]` table of report.toml, without the table header): the tuning tool.
        #[arg(long)]
        burst_config: Option<PathBuf>,
    },
    /// Denoising: PSNR/SSIM of chroma-BM3D over a grid of σ gains and of the flat-area kernel
    /// of the merge it runs on (the tuning tool for `luma_gain`, `chroma_gain` and
    /// `merge_k_denoise`), against the default merge without denoising (end to end), on built-in
    /// chart captures, or on a set of the quality suite with --scenes.
    Denoise {
        /// Folder with the quality suite's scenes (default: built-in chart captures only).
        #[arg(long)]
        scenes: Option<PathBuf>,
        /// Which set of the quality suite (with --scenes).
        #[arg(long, value_enum, default_value_t = SuiteSet::Tuning)]
        set: SuiteSet,
        /// Only the captures whose id contains this text.
        #[arg(long)]
        only: Option<String>,
        /// Luma σ gains to try (comma-separated; default: the configured one).
        #[arg(long, value_delimiter = ',')]
        luma_gains: Vec<f32>,
        /// Chroma σ gains to try (comma-separated; default: the configured one).
        #[arg(long, value_delimiter = ',')]
        chroma_gains: Vec<f32>,
        /// Flat-area kernel stds (px) of the denoiser's merge to try (comma-separated;
        /// default: the configured one).
        #[arg(long, value_delimiter = ',')]
        merge_k_denoise: Vec<f32>,
        /// Numbers of coarse chroma scales to try (comma-separated; default: the configured).
        #[arg(long, value_delimiter = ',')]
        chroma_scales: Vec<usize>,
        /// Coarse σ factors to try (comma-separated; default: the configured one).
        #[arg(long, value_delimiter = ',')]
        coarse_sigma_factors: Vec<f32>,
        /// TOML with burst (align + merge) parameters to use instead of the defaults (the
        /// `[burst]` table of report.toml, without the table header).
        #[arg(long)]
        burst_config: Option<PathBuf>,
        /// TOML with denoising parameters to start from (the `[denoise]` table of report.toml,
        /// without the table header).
        #[arg(long)]
        denoise_config: Option<PathBuf>,
    },
    /// Speed: align + merge + denoise of simulated 10,000-frame handheld captures (the built-in
    /// chart and the quality suite's validation photographs, or --scene), every stage timed,
    /// against the naive sum of the same frames in the same process, and against the capture's
    /// own duration at the colour SwissSPAD2's 16,000 frames per second; then both again as
    /// whole `quantacolor reconstruct` processes (the capture written to the temporary folder).
    Speed {
        #[arg(long, default_value_t = 10_000)]
        frames: usize,
        /// Timed rounds: each times the naive sum three times, then the default pipeline once
        /// (interleaved, so that both see the same machine); the medians are reported (the
        /// naive sum takes tens of milliseconds, so one run of it is at the mercy of the
        /// scheduler).
        #[arg(long, default_value_t = 5, value_parser = clap::value_parser!(u32).range(1..))]
        runs: u32,
        /// TOML with a full or partial reconstruction config (as `reconstruct --config`) to
        /// time instead of the default pipeline: how far a speed setting moves the ratio.
        #[arg(long)]
        config: Option<PathBuf>,
        /// Named settings to time (as `reconstruct --profile`; --config goes over them).
        #[arg(long, default_value_t = Profile::Default)]
        profile: Profile,
        /// Scene to simulate the capture from instead of the default set (repeatable or
        /// comma-separated): an image file (PNG, EXR, ...) or builtin:chart. Each is a 496x254
        /// colour-SPAD capture of hand shake at 0.1 photons/pixel/frame, seed 1, as the chart.
        #[arg(long, value_delimiter = ',')]
        scene: Vec<String>,
        /// Folder of the quality suite's scenes: without --scene, its validation photographs
        /// are timed after the built-in chart (without the default folder, the chart only)
        /// [default: ../shared/data/scenes].
        #[arg(long, conflicts_with = "scene")]
        scenes: Option<PathBuf>,
    },
    /// Video: `reconstruct --video` (motion estimated once, composed to every reference frame)
    /// against a full reconstruction per reference frame, in the same process, on a simulated
    /// chart capture; PSNR/SSIM of both against the simulator's ground truth at each reference
    /// frame, and of one against the other.
    Video {
        #[arg(long, default_value_t = 4000)]
        frames: usize,
        /// Frames between consecutive video reference frames.
        #[arg(long, default_value_t = 500)]
        stride: usize,
        /// Camera motion of the simulation (static, pan, handheld, fast-handheld, circular,
        /// object).
        #[arg(long, default_value = "handheld")]
        motion: MotionConfig,
        /// Denoising of both paths [default: chroma-bm3d, as `reconstruct`].
        #[arg(long)]
        denoise: Option<DenoiseMethod>,
        #[arg(long, default_value_t = 1)]
        seed: u64,
    },
    /// Long recordings: `quantacolor reconstruct` (default settings, a child process per run)
    /// on 10,000 and 100,000 frames of hand shake, 100,000 frames in ten parts (nine camera
    /// jumps) and its first part alone, and 1,000,000 frames: seconds, µs per frame, peak RSS,
    /// ratio to the 10,000-frame time and sRGB PSNR. Captures are simulated once into --work
    /// and reused.
    Long(long::LongArgs),
}

pub fn run(args: &BenchArgs, progress: &dyn Progress) -> Result<()> {
    match &args.command {
        BenchCommand::Quality {
            scenes,
            out,
            set,
            only,
            burst_config,
        } => {
            let burst = read_burst_config(burst_config.as_deref())?;
            quality::quality(scenes, out, *set, only.as_deref(), &burst, progress)
        }
        BenchCommand::Speed {
            frames,
            runs,
            config,
            profile,
            scene,
            scenes,
        } => {
            let (pipeline, name) = match config {
                Some(path) => (
                    crate::cmd_reconstruct::read_config(path, *profile)?,
                    format!("pipeline of {} over the {profile} profile", path.display()),
                ),
                None => (profile.config()?, format!("{profile} pipeline")),
            };
            // The same selection for the whole `reconstruct` processes.
            let mut pipeline_args = vec![OsString::from("--profile"), profile.to_string().into()];
            if let Some(path) = config {
                pipeline_args.extend([OsString::from("--config"), path.clone().into()]);
            }
            // Every scene is loaded before anything is simulated, so a bad one fails at once.
            let scenes = speed::speed_scenes(scene, scenes.as_deref())?;
            speed::speed(
                &scenes,
                *frames,
                *runs as usize,
                (&pipeline, &name, &pipeline_args),
                progress,
            )
        }
        BenchCommand::Video {
            frames,
            stride,
            motion,
            denoise,
            seed,
        } => video::video(*frames, *stride, motion, *denoise, *seed, progress),
        BenchCommand::Long(args) => long::long(args, progress),
        BenchCommand::Denoise {
            scenes,
            set,
            only,
            luma_gains,
            chroma_gains,
            merge_k_denoise,
            chroma_scales,
            coarse_sigma_factors,
            burst_config,
            denoise_config,
        } => {
            let burst = read_burst_config(burst_config.as_deref())?;
            let denoise = read_toml_config::<DenoiseConfig>(denoise_config.as_deref())?;
            let grid = DenoiseGrid {
                luma_gains: or_default(luma_gains, denoise.luma_gain),
                chroma_gains: or_default(chroma_gains, denoise.chroma_gain),
                merge_k_denoise: if merge_k_denoise.is_empty() {
                    vec![denoise.merge_k_denoise]
                } else {
                    merge_k_denoise.iter().map(|&k| Some(k)).collect()
                },
                chroma_scales: if chroma_scales.is_empty() {
                    vec![denoise.chroma_scales]
                } else {
                    chroma_scales.clone()
                },
                coarse_sigma_factors: or_default(coarse_sigma_factors, denoise.coarse_sigma_factor),
            };
            let captures = match scenes {
                None => chart_captures()?,
                Some(dir) => suite_captures(dir, *set, only.as_deref())?,
            };
            denoise_grid(&captures, &grid, &burst, &denoise, progress)
        }
    }
}

/// The burst parameters of `path` (TOML, the `[burst]` table of report.toml), or the defaults.
fn read_burst_config(path: Option<&Path>) -> Result<BurstConfig> {
    read_toml_config(path)
}

/// A configuration table read from the TOML file `path`, or the defaults without one.
fn read_toml_config<T: serde::de::DeserializeOwned + Default>(path: Option<&Path>) -> Result<T> {
    match path {
        Some(path) => crate::config_file::read(path),
        None => Ok(T::default()),
    }
}

fn or_default(values: &[f32], default: f32) -> Vec<f32> {
    if values.is_empty() {
        vec![default]
    } else {
        values.to_vec()
    }
}

#[cfg(test)]
mod tests;
