//! `quantacolor display`: renders a linear reconstruction (OUT/linear.npy, (H, W, 3)) or a video
//! stack ((N, H, W, 3), from `reconstruct --video`) to 8/16-bit sRGB PNGs or 16-bit TIFFs:
//! colour correction -> noise-aware low-light blend -> exposure -> tone map -> sRGB (paper §7,
//! Fig. 14, Fig. 20; supplement §4 Eq. 9–10).

#![forbid(unsafe_code)]

use crate::output::StagedDir;
use anyhow::{bail, Context, Result};
use clap::{Args, ValueEnum};
use ndarray::{Array4, Axis};
use quantacolor::capture::io;
use quantacolor::capture::npy::{NpyDtype, NpyHeader};
use quantacolor::display::{
    frame_path, mesopic_params, output_is_tiff, render_stack, write_display, BitDepth, ColorMatrix,
    GlobalConfig, Mantiuk06Config, MesopicConfig, MesopicOffset, RenderOptions, ToneMap,
};
use quantacolor::output::{report_frames, report_w_weights};
use std::path::{Path, PathBuf};

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum ToneMapArg {
    /// Mantiuk et al. 2006 contrast mapping (contrast 0.3, saturation 0.8), as the paper's figures.
    Mantiuk06,
    /// Reinhard 2002 global operator (key 0.18 on the log-average luminance).
    Global,
    /// Exposure only (auto: 99.5th percentile to white), clipped.
    None,
}

impl ToneMapArg {
    /// The operator with its published defaults.
    pub fn to_tone_map(self) -> ToneMap {
        match self {
            ToneMapArg::Mantiuk06 => ToneMap::Mantiuk06(Mantiuk06Config::default()),
            ToneMapArg::Global => ToneMap::Global(GlobalConfig::default()),
            ToneMapArg::None => ToneMap::None,
        }
    }
}

#[derive(Debug, Args)]
pub struct DisplayArgs {
    /// Linear reconstruction, float32 .npy: an image (H, W, 3) (e.g. OUT/linear.npy) or a video
    /// stack (N, H, W, 3) (from `reconstruct --video`).
    pub linear: PathBuf,
    /// Output image: .png (8 or 16 bit) or .tif/.tiff (16 bit); written atomically. A video
    /// stack is written as numbered frames beside it: OUT_00000.png, OUT_00001.png, ...
    #[arg(long)]
    pub out: PathBuf,
    /// Tone-mapping operator.
    #[arg(long, value_enum, default_value_t = ToneMapArg::Global)]
    pub tonemap: ToneMapArg,
    /// Noise-aware low-light view (supplement Eq. 9–10): colour fades to grey where a W pixel
    /// collected fewer than 100·10^-L0 photon detections over the capture and is gone below
    /// 10^-L0 (photon-noise SNR 10 to 1 at L0 = 0). `auto` picks L0 from the noise measured in
    /// the image.
    #[arg(long, value_name = "L0|auto", allow_hyphen_values = true)]
    pub mesopic: Option<MesopicOffset>,
    /// Frames merged into the reconstruction, for --mesopic (default: frames_used of the
    /// report.toml beside the input).
    #[arg(long)]
    pub frames: Option<f64>,
    /// Exposure scale applied before tone mapping (default: automatic).
    #[arg(long)]
    pub exposure: Option<f32>,
    /// Colour matrix from `quantacolor calibrate-color` (a [color_matrix] TOML table).
    #[arg(long)]
    pub ccm: Option<PathBuf>,
    /// Bits per sample: 8 or 16 (TIFF needs 16; default: 16 for .tif/.tiff, else 8).
    #[arg(long)]
    pub bits: Option<u8>,
}

/// The report.toml beside `linear`, when there is one that parses.
fn report_beside(linear: &Path) -> Option<toml::Table> {
    let text = std::fs::read_to_string(linear.with_file_name("report.toml")).ok()?;
    toml::from_str(&text).ok()
}

/// Reads `path` as float32 (H, W, 3) (returned as a one-frame stack, `false`) or (N, H, W, 3)
/// (`true`); any other shape or dtype is one error naming the file and what it holds.
fn read_linear(path: &Path) -> Result<(Array4<f32>, bool)> {
    let bytes = std::fs::read(path).with_context(|| format!("{}: cannot read", path.display()))?;
    let header =
        NpyHeader::parse(&bytes).map_err(|m| anyhow::anyhow!("{}: {m}", path.display()))?;
    let shape = &header.shape;
    let fits = matches!(shape.len(), 3 | 4)
        && shape.last() == Some(&3)
        && shape.iter().all(|&d| d > 0)
        && header.dtype == NpyDtype::F32
        && !header.fortran_order;
    if !fits {
        bail!(
            "{}: expected float32 linear RGB of shape (H, W, 3) or a video stack (N, H, W, 3), found {} of shape {:?}",
            path.display(),
            header.descr,
            shape
        );
    }
    if shape.len() == 3 {
        let img = io::read_npy_3d::<f32>(path)?;
        return Ok((img.insert_axis(Axis(0)), false));
    }
    Ok((io::read_npy_4d::<f32>(path)?, true))
}

pub fn run(args: &DisplayArgs) -> Result<()> {
    let is_tiff = matches!(
        args.out
            .extension()
            .map(|e| e.to_string_lossy().to_ascii_lowercase())
            .as_deref(),
        Some("tif" | "tiff")
    );
    let bits = match args.bits {
        None if is_tiff => BitDepth::Sixteen,
        None | Some(8) => BitDepth::Eight,
        Some(16) => BitDepth::Sixteen,
        Some(b) => bail!("--bits must be 8 or 16, got {b}"),
    };
    output_is_tiff(&args.out, bits)?;
    if let Some(t) = args.frames {
        if !(t.is_finite() && t > 0.0) {
            bail!("--frames must be a positive number, got {t}");
        }
    }
    let (stack, is_video) = read_linear(&args.linear)?;
    let color_matrix = match &args.ccm {
        Some(p) => Some(ColorMatrix::read(p)?),
        None => None,
    };
    let report = report_beside(&args.linear);
    let options = RenderOptions {
        exposure: args.exposure,
        color_matrix,
        tonemap: args.tonemap.to_tone_map(),
        mesopic: args.mesopic.map(|l0| MesopicConfig {
            l0,
            frames: args.frames.or(report.as_ref().and_then(report_frames)),
        }),
        w_weights: report
            .as_ref()
            .and_then(report_w_weights)
            .unwrap_or([1.0, 1.0, 1.0]),
    };
    let context = || format!("rendering {}", args.linear.display());
    if options.mesopic.is_some() {
        let (n, h, w, _) = stack.dim();
        let tall = stack.view().into_shape_with_order((n * h, w, 3))?;
        if let Some(p) = mesopic_params(tall, &options).with_context(context)? {
            match p.effective_frames {
                Some(t_eff) => println!(
                    "noise-aware view: L0 = {:.2} (auto: the noise is that of {t_eff:.0} frames, {:.0} merged)",
                    p.l0, p.frames
                ),
                None => println!("noise-aware view: L0 = {}, {:.0} frames", p.l0, p.frames),
            }
        }
    }
    let display = render_stack(stack.view(), &options).with_context(context)?;
    if !is_video {
        write_display(&args.out, display.index_axis(Axis(0), 0), bits)?;
        crate::output::say(&format!("wrote {}", args.out.display()));
        return Ok(());
    }
    // All frames are staged, then moved into place together: an error leaves none of them.
    let dir = match args.out.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let dir = dir.canonicalize().with_context(|| {
        format!(
            "{}: cannot write the frames, no directory {}",
            args.out.display(),
            dir.display()
        )
    })?;
    let staged = StagedDir::new(&dir)?;
    let n = display.dim().0;
    for (i, frame) in display.axis_iter(Axis(0)).enumerate() {
        let name = frame_path(&args.out, i);
        let file = name.file_name().expect("frame_path keeps a file name");
        write_display(staged.path(&file.to_string_lossy()), frame, bits)?;
    }
    staged.commit()?;
    println!(
        "wrote {n} frames: {} .. {}",
        frame_path(&args.out, 0).display(),
        frame_path(&args.out, n - 1).display()
    );
    Ok(())
}
