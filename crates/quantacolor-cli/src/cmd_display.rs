//! `quantacolor display`: renders a linear reconstruction (OUT/linear.npy) to an 8/16-bit sRGB
//! PNG or a 16-bit TIFF: colour correction -> noise-aware low-light blend -> exposure -> tone
//! map -> sRGB (paper §7, Fig. 14, Fig. 20; supplement §4 Eq. 9–10).

use anyhow::{bail, Context, Result};
use clap::{Args, ValueEnum};
use quantacolor::capture::io;
use quantacolor::display::{
    write_rendered, BitDepth, ColorMatrix, GlobalConfig, Mantiuk06Config, RenderOptions, ToneMap,
};
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
    /// Linear reconstruction, float32 (H, W, 3) .npy (e.g. OUT/linear.npy).
    pub linear: PathBuf,
    /// Output image: .png (8 or 16 bit) or .tif/.tiff (16 bit); written atomically.
    #[arg(long)]
    pub out: PathBuf,
    /// Tone-mapping operator.
    #[arg(long, value_enum, default_value_t = ToneMapArg::Global)]
    pub tonemap: ToneMapArg,
    /// Noise-aware low-light view with offset L0 (supplement Eq. 9): colour fades to grey below
    /// 10^-L0 detections per frame and is gone at 10^(-2-L0).
    #[arg(long, value_name = "L0", allow_hyphen_values = true)]
    pub mesopic: Option<f32>,
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

/// `w_weights` from a report.toml beside `linear`, when it has them.
fn w_weights_beside(linear: &Path) -> Option<[f64; 3]> {
    let report = linear.with_file_name("report.toml");
    let text = std::fs::read_to_string(report).ok()?;
    let table: toml::Table = toml::from_str(&text).ok()?;
    let v = table.get("w_weights")?.as_array()?;
    let w: Vec<f64> = v
        .iter()
        .filter_map(|x| x.as_float().or(x.as_integer().map(|i| i as f64)))
        .collect();
    (w.len() == 3).then(|| [w[0], w[1], w[2]])
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
    let linear = io::read_npy_3d::<f32>(&args.linear)?;
    let (h, w, c) = linear.dim();
    if c != 3 || h == 0 || w == 0 {
        bail!(
            "{}: expected a linear RGB image of shape (H, W, 3), found {:?}",
            args.linear.display(),
            linear.dim()
        );
    }
    let color_matrix = match &args.ccm {
        Some(p) => Some(ColorMatrix::read(p)?),
        None => None,
    };
    let options = RenderOptions {
        exposure: args.exposure,
        color_matrix,
        tonemap: args.tonemap.to_tone_map(),
        mesopic: args.mesopic,
        w_weights: w_weights_beside(&args.linear).unwrap_or([1.0, 1.0, 1.0]),
    };
    write_rendered(&args.out, linear.view(), &options, bits)
        .with_context(|| format!("rendering {}", args.linear.display()))?;
    println!("wrote {}", args.out.display());
    Ok(())
}
