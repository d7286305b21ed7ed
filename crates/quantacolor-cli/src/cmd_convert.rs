//! `quantacolor convert` (real recordings -> capture directory), plus the `--frames` /
//! hot-pixel self-calibration shared by `reconstruct`, `align` and `inspect`.

#![forbid(unsafe_code)]

use anyhow::Result;
use clap::{Args, ValueEnum};
use quantacolor::align::hot_pixels::HotPixelDetectConfig;
use quantacolor::capture::readers::{RawFormat, SourceSpec, Spad512sOptions, Spad512sOrientation};
use quantacolor::capture::{io, Capture, FrameWindow};
use quantacolor::convert::{convert_input, ConvertRequest, HotPixelChoice};
use quantacolor::progress::Progress;
use std::path::{Path, PathBuf};

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum FromArg {
    /// SwissSPAD2 half array: .bin files of 512 frames of 256x512, LSB first.
    Swissspad2,
    /// SwissSPAD2 full array: .bin files of 256 frames of 512x512.
    #[value(name = "swissspad2-full")]
    Swissspad2Full,
    /// Pi Imaging SPAD512S: .bin files of 512x512 frames, MSB first.
    Spad512s,
    /// Photon-cube .npy: (T, H, W/8) packed MSB first, or an RGB cube (T, H, W/8, 3).
    Npy,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum OrientationArg {
    /// As stored in the file.
    Stored,
    /// Rows mirrored left-right (the MATLAB read_512Sbin.m view).
    FlipLr,
    /// Rotated 90° counter-clockwise (np.rot90; the Python reader's view).
    Rot90,
}

#[derive(Debug, Args)]
pub struct ConvertArgs {
    /// A .bin file, a directory tree of .bin files (read in natural path order), or a .npy.
    pub input: PathBuf,
    /// Input format.
    #[arg(long = "from", value_enum)]
    pub from: FromArg,
    /// Output capture directory.
    #[arg(long)]
    pub out: PathBuf,
    /// Replace the files of an existing, non-empty output directory (refused otherwise).
    #[arg(long)]
    pub overwrite: bool,
    /// Colour SwissSPAD2 (the paper's prototype): keep rows 2..256 and columns 0..496, swap
    /// column blocks 252..256 and 260..264, and use the sensor's shipped CFA and hot-pixel mask.
    #[arg(long)]
    pub colorspad: bool,
    /// CFA of the capture (.npy codes or a colour PNG); default: the colour SwissSPAD2 CFA with
    /// --colorspad, else all W (monochrome). Required for RGB photon cubes.
    #[arg(long)]
    pub cfa: Option<PathBuf>,
    /// Exposure of one binary frame, seconds (default 1e-5, recorded as assumed).
    #[arg(long)]
    pub exposure_s: Option<f64>,
    /// Frames to convert, A:B (A included, B excluded; either may be omitted).
    #[arg(long, allow_hyphen_values = true)]
    pub frames: Option<FrameWindow>,
    /// Hot-pixel mask, bool (H, W) .npy (default: the shipped mask with --colorspad, else
    /// detected from the frames).
    #[arg(long, conflicts_with = "no_hot_pixels")]
    pub hot_pixels: Option<PathBuf>,
    /// Write no hot-pixel mask (and detect none).
    #[arg(long)]
    pub no_hot_pixels: bool,
    /// SPAD512S: bytes after the frames of every file, ignored [default: 4].
    #[arg(long)]
    pub trailer_bytes: Option<usize>,
    /// SPAD512S: orientation of the frames in the capture [default: stored].
    #[arg(long, value_enum)]
    pub orientation: Option<OrientationArg>,
}

pub fn run_convert(args: &ConvertArgs, progress: &dyn Progress) -> Result<()> {
    crate::output::check_out_dir(&args.out, "--out", args.overwrite)?;
    let format = match args.from {
        FromArg::Swissspad2 => RawFormat::SwissSpad2,
        FromArg::Swissspad2Full => RawFormat::SwissSpad2Full,
        FromArg::Spad512s => RawFormat::Spad512s,
        FromArg::Npy => RawFormat::Npy,
    };
    if format != RawFormat::Spad512s && (args.trailer_bytes.is_some() || args.orientation.is_some())
    {
        anyhow::bail!("--trailer-bytes and --orientation apply to --from spad512s only");
    }
    let mut spad512s = Spad512sOptions::default();
    if let Some(n) = args.trailer_bytes {
        spad512s.trailer_bytes = n;
    }
    if let Some(o) = args.orientation {
        spad512s.orientation = match o {
            OrientationArg::Stored => Spad512sOrientation::Stored,
            OrientationArg::FlipLr => Spad512sOrientation::FlipLr,
            OrientationArg::Rot90 => Spad512sOrientation::Rot90,
        };
    }
    let request = ConvertRequest {
        source: SourceSpec {
            format: Some(format),
            colorspad: args.colorspad,
            spad512s,
        },
        cfa: match &args.cfa {
            Some(p) => Some(quantacolor::cfa::io::load(p)?),
            None => None,
        },
        hot_pixels: match (&args.hot_pixels, args.no_hot_pixels) {
            (Some(p), _) => HotPixelChoice::Mask(io::read_npy_2d::<bool>(p)?),
            (None, true) => HotPixelChoice::None,
            (None, false) => HotPixelChoice::Auto,
        },
        exposure_s: args.exposure_s,
        window: args.frames.unwrap_or_default(),
        detect: HotPixelDetectConfig::default(),
    };
    let summary = convert_input(&args.input, &args.out, &request, progress)?;
    println!(
        "{}: {} frames of {}x{} (frames {}..{} of the input); hot pixels: {}",
        args.out.display(),
        summary.frames,
        summary.height,
        summary.width,
        summary.first_frame,
        summary.first_frame + summary.frames,
        match (summary.hot_pixels, summary.hot_pixels_detected) {
            (None, _) => "none".to_string(),
            (Some(n), true) => format!("{n} detected"),
            (Some(n), false) => n.to_string(),
        }
    );
    Ok(())
}

/// Opens a capture for `reconstruct`, `align` and `inspect` (the library's
/// [`quantacolor::convert::open_capture`]).
pub fn open_capture(dir: &Path, frames: Option<&FrameWindow>, detect: bool) -> Result<Capture> {
    Ok(quantacolor::convert::open_capture(dir, frames, detect)?)
}
