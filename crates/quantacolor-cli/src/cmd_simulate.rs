//! `quantacolor simulate`: renders a simulated capture (scene, motion, sensor of paper Table 1)
//! and writes it as a capture directory with ground truth, hot-pixel mask and `motion.toml`,
//! streaming the frames to disk (memory independent of the number of frames).

#![forbid(unsafe_code)]

use anyhow::{bail, Context};
use clap::Args;
use quantacolor::progress::Progress;
use quantacolor::simulate::{self, FluxSpec, MotionConfig, Scene, SensorKind, SimulationConfig};
use std::path::PathBuf;

/// Options of `quantacolor simulate`.
#[derive(Debug, Clone, Args)]
pub struct SimulateArgs {
    /// Scene: an image file (PNG/JPEG sRGB, EXR linear), builtin:chart, builtin:chart-hdr or
    /// builtin:flat.
    #[arg(long, default_value = "builtin:chart")]
    pub scene: String,
    /// Motion: static, pan, handheld, fast-handheld, circular or object.
    #[arg(long, default_value = "handheld")]
    pub motion: String,
    /// Pan velocity "DY,DX" in pixels per frame (pan motion; default 0,0.02).
    #[arg(long, value_name = "DY,DX")]
    pub velocity: Option<String>,
    /// Peak translation in pixels (handheld motions) or circle radius (circular).
    #[arg(long)]
    pub amplitude: Option<f64>,
    /// Peak rotation in degrees (handheld motions; default 0.5).
    #[arg(long)]
    pub rotation_deg: Option<f64>,
    /// Number of frames T.
    #[arg(long, default_value_t = 512)]
    pub frames: usize,
    /// Light level: mean detections per frame of a W pixel over the image (default 0.1).
    #[arg(long, conflicts_with_all = ["peak_percentile", "peak"])]
    pub flux: Option<f64>,
    /// HDR light level: this percentile (0-100) of the W detections per frame ...
    #[arg(long, requires = "peak")]
    pub peak_percentile: Option<f64>,
    /// ... equals this value.
    #[arg(long, requires = "peak_percentile")]
    pub peak: Option<f64>,
    /// Sensor size WIDTHxHEIGHT.
    #[arg(long, default_value = "496x254")]
    pub size: String,
    /// CFA pattern (bayer, rgbw-75-regular, ...).
    #[arg(long, default_value = "rgbw-75-regular")]
    pub cfa: String,
    /// Seed of pseudorandom CFA patterns.
    #[arg(long, default_value_t = 0)]
    pub cfa_seed: u64,
    /// Sensor: spad, jot or cmos.
    #[arg(long, default_value = "spad")]
    pub sensor: String,
    /// Seed of motion, dark counts and photon noise.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Fraction of hot pixels.
    #[arg(long, default_value_t = 0.02)]
    pub hot_fraction: f64,
    /// Reference frame (default T/2).
    #[arg(long)]
    pub reference_frame: Option<usize>,
    /// Output capture directory.
    #[arg(long)]
    pub out: PathBuf,
    /// Replace the files of an existing, non-empty output directory (refused otherwise).
    #[arg(long)]
    pub overwrite: bool,
}

/// Parses `--size WIDTHxHEIGHT`.
pub(crate) fn parse_size(s: &str) -> anyhow::Result<(usize, usize)> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .with_context(|| format!("--size '{s}' is not WIDTHxHEIGHT"))?;
    let parse = |v: &str| {
        v.trim()
            .parse::<usize>()
            .with_context(|| format!("--size '{s}' is not WIDTHxHEIGHT"))
    };
    Ok((parse(w)?, parse(h)?))
}

fn parse_velocity(s: &str) -> anyhow::Result<[f64; 2]> {
    let (dy, dx) = s
        .split_once(',')
        .with_context(|| format!("--velocity '{s}' is not DY,DX"))?;
    Ok([
        dy.trim()
            .parse()
            .with_context(|| format!("--velocity '{s}'"))?,
        dx.trim()
            .parse()
            .with_context(|| format!("--velocity '{s}'"))?,
    ])
}

/// The motion named by `--motion`, with the overrides given.
fn motion_config(args: &SimulateArgs) -> anyhow::Result<MotionConfig> {
    let mut motion: MotionConfig = args.motion.parse()?;
    match &mut motion {
        MotionConfig::Pan { velocity } | MotionConfig::Object { velocity, .. } => {
            if let Some(v) = &args.velocity {
                *velocity = parse_velocity(v)?;
            }
        }
        MotionConfig::Handheld {
            amplitude_px,
            rotation_deg,
            ..
        }
        | MotionConfig::FastHandheld {
            amplitude_px,
            rotation_deg,
            ..
        } => {
            *amplitude_px = args.amplitude.unwrap_or(*amplitude_px);
            *rotation_deg = args.rotation_deg.unwrap_or(*rotation_deg);
        }
        MotionConfig::Circular { radius_px, .. } => {
            *radius_px = args.amplitude.unwrap_or(*radius_px);
        }
        MotionConfig::Static => {}
    }
    Ok(motion)
}

/// The library configuration these arguments describe.
pub fn config_from_args(args: &SimulateArgs) -> anyhow::Result<SimulationConfig> {
    let (width, height) = parse_size(&args.size)?;
    let flux = match (args.flux, args.peak_percentile, args.peak) {
        (Some(flux), None, None) => FluxSpec::Mean { flux },
        (None, Some(percentile), Some(peak)) => FluxSpec::Percentile { percentile, peak },
        (None, None, None) => FluxSpec::Mean { flux: 0.1 },
        _ => bail!("give either --flux or both --peak-percentile and --peak"),
    };
    Ok(SimulationConfig {
        height,
        width,
        frames: args.frames,
        cfa: args.cfa.clone(),
        cfa_seed: args.cfa_seed,
        sensor: args.sensor.parse::<SensorKind>()?,
        flux,
        motion: motion_config(args)?,
        reference_frame: args.reference_frame,
        hot_fraction: args.hot_fraction,
        seed: args.seed,
        ..SimulationConfig::default()
    })
}

/// Runs `quantacolor simulate`.
pub fn run(args: &SimulateArgs, progress: &dyn Progress) -> anyhow::Result<()> {
    crate::output::check_out_dir(&args.out, "--out", args.overwrite)?;
    let config = config_from_args(args)?;
    let scene = Scene::from_spec(&args.scene)?;
    // Streams the frames to disk a chunk at a time: memory does not grow with --frames.
    simulate::simulate_to_dir(&config, &scene, &args.out, progress)?;
    Ok(())
}
