//! Simulated captures: scenes, motion, sensors of paper Table 1, and frame rendering.
//!
//! The imaging model is paper Eq. 2–3: a pixel behind filter c sees λ_c = φ_c·η_c·τ photon
//! detections per frame plus d dark counts; a SPAD frame is 1 with probability
//! 1 − exp(−(λ + d)). A W (clear) pixel sees the sum of the three bands, W = R + G + B, so the
//! captures carry `w_weights = [1, 1, 1]`.
//!
//! Light level ([`FluxSpec`]): `flux` is the mean, over the reference frame's pixels, of the
//! detections per frame a W pixel would collect (dark counts excluded). A flat grey scene at
//! flux F therefore gives W bits at density 1 − exp(−F) (plus dark counts) and R, G, B bits at
//! the share of F set by the sensor's quantum efficiencies. For jot and CMOS sensors
//! "detections" are photoelectrons per frame.
//!
//! The ground truth is λ of R, G, B (dark counts excluded) at the reference frame, float32
//! (H, W, 3), rendered through the same scene sampler as the frames.
//!
//! Pixel supersampling ([`SimulationConfig::pixel_supersampling`] = s > 1) models a scene with
//! detail finer than a pixel: the scene raster is pre-filtered by a 1/s-pixel box instead of a
//! whole pixel, and each pixel's λ (in every frame and in the ground truth) is the mean over s x s
//! sample points at offsets ((i + ½)/s − ½, (j + ½)/s − ½) px, i.e. the pixel-area integral. The
//! capture then also carries a high-resolution ground truth (s·H, s·W, 3) whose pixel (Y, X) is
//! the scene at reference position ((Y + ½)/s − ½, (X + ½)/s − ½) (the merge's scale-s output
//! grid) averaged over its own 1/s-pixel area; its s x s box mean is the ordinary ground truth.
//!
//! Everything is seeded: the same configuration, scene and seed give identical bytes, whatever
//! the number of threads (each frame has its own random stream).
//!
//! [`simulate`] and [`simulate_cmos`] return the capture in memory (tests, Python, the
//! benchmarks); [`simulate_to_dir`] writes the same files as their `write` while holding only a
//! chunk of frames in memory (`quantacolor simulate`, 10^5–10^6-frame captures).
#![deny(unsafe_code)]

pub mod chart;
pub mod motion;
pub mod render;
pub mod scene;
pub mod sensor;
mod stream;

pub use motion::{Motion, MotionConfig, ObjectTrack};
pub use scene::{Scene, SceneRaster};
pub use sensor::{DarkCountMap, FluxSpec, JotReadout, SensorKind, SensorModel};
pub use stream::simulate_to_dir;

use crate::capture::{CaptureMeta, CaptureParts, FrameData, MultiBitReadout};
use crate::cfa::{self, Cfa, Pattern};
use crate::error::{Error, Result};
use crate::progress::Progress;
use ndarray::{s, Array2, Array3};
use render::{mix, BinaryReadout, FluxField};
use serde::{Deserialize, Serialize};
use std::path::Path;
use std::str::FromStr;

/// Everything that defines a simulated capture except the scene. Every field has a default.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct SimulationConfig {
    /// Sensor height H, pixels.
    pub height: usize,
    /// Sensor width W, pixels.
    pub width: usize,
    /// Number of frames T.
    pub frames: usize,
    /// CFA pattern name (`bayer`, `rgbw-75-regular`, ...), see [`cfa::Pattern`].
    pub cfa: String,
    /// Seed of pseudorandom CFA patterns.
    pub cfa_seed: u64,
    pub sensor: SensorKind,
    pub flux: FluxSpec,
    pub motion: MotionConfig,
    /// Reference frame (default T/2 rounded down); the motion is the identity there.
    pub reference_frame: Option<usize>,
    /// Fraction of hot pixels.
    pub hot_fraction: f64,
    /// Range of hot-pixel dark count rates, counts per second.
    pub hot_rate_hz: [f64; 2],
    /// Log-standard deviation of the normal pixels' dark count rates around the sensor mean.
    pub dark_variation: f64,
    /// Seed of the motion, dark counts and frames.
    pub seed: u64,
    /// Seed of the dark counts and hot pixels alone (default `seed`): captures of one sensor
    /// under different motion and photon noise share it.
    pub dark_seed: Option<u64>,
    /// Sub-pixel samples per axis s (1 = none): each pixel integrates the scene over s x s
    /// sample points, the scene keeps detail down to 1/s pixel, and the capture carries a
    /// ground truth at s times the resolution (see the module documentation).
    pub pixel_supersampling: usize,
}

impl Default for SimulationConfig {
    fn default() -> Self {
        SimulationConfig {
            height: 254,
            width: 496,
            frames: 512,
            cfa: "rgbw-75-regular".into(),
            cfa_seed: 0,
            sensor: SensorKind::Spad,
            flux: FluxSpec::default(),
            motion: MotionConfig::Static,
            reference_frame: None,
            hot_fraction: 0.02,
            hot_rate_hz: [200.0, 2000.0],
            dark_variation: 0.3,
            seed: 1,
            dark_seed: None,
            pixel_supersampling: 1,
        }
    }
}

/// A simulated binary capture (SPAD or jot), in memory.
#[derive(Debug, Clone)]
pub struct SimulatedCapture {
    /// Bit-packed frames, uint8 (T, H, ceil(W/8)), MSB first.
    pub packed_frames: Array3<u8>,
    pub width: usize,
    pub cfa: Cfa,
    pub meta: CaptureMeta,
    /// Hot pixels, (H, W).
    pub hot_pixels: Array2<bool>,
    /// λ of R, G, B at the reference frame, (H, W, 3).
    pub ground_truth: Array3<f32>,
    /// With pixel supersampling s > 1: λ of R, G, B at the reference frame on the merge's
    /// scale-s grid, (s·H, s·W, 3); `None` for s = 1.
    pub ground_truth_hr: Option<Array3<f32>>,
    pub motion: Motion,
    /// Dark count rate of every pixel, counts per second, (H, W).
    pub dark_count_rates_hz: Array2<f64>,
    pub sensor: SensorModel,
}

/// A simulated conventional (CMOS) capture, in memory.
#[derive(Debug, Clone)]
pub struct SimulatedCmosCapture {
    /// Digital numbers (1 DN = 1 e-), uint16 (T, H, W) in `0..2^bit_depth`.
    pub frames: Array3<u16>,
    pub cfa: Cfa,
    pub meta: CaptureMeta,
    pub hot_pixels: Array2<bool>,
    /// Mean photoelectrons of R, G, B per frame at the reference frame, (H, W, 3).
    pub ground_truth: Array3<f32>,
    /// As [`SimulatedCapture::ground_truth_hr`].
    pub ground_truth_hr: Option<Array3<f32>>,
    pub motion: Motion,
    pub dark_count_rates_hz: Array2<f64>,
    pub sensor: SensorModel,
}

/// Name of the motion description inside a capture directory.
pub const MOTION_FILE: &str = "motion.toml";

impl SimulatedCapture {
    /// The simulated capture as an opened [`Capture`] held in memory (no files written).
    pub fn to_capture(&self) -> Result<crate::capture::Capture> {
        Ok(crate::capture::Capture {
            dir: "simulated".into(),
            frames: crate::capture::BinaryFrames::from_packed(
                self.packed_frames.clone(),
                self.width,
            )?,
            cfa: self.cfa.clone(),
            meta: self.meta.clone(),
            hot_pixels: Some(self.hot_pixels.clone()),
        })
    }

    /// The parts `capture::write_capture` writes, including `motion.toml`.
    pub fn capture_parts(&self) -> Result<CaptureParts<'_>> {
        Ok(CaptureParts {
            frames: FrameData::Packed(&self.packed_frames),
            width: self.width,
            cfa: &self.cfa,
            meta: &self.meta,
            hot_pixels: Some(&self.hot_pixels),
            ground_truth: Some(&self.ground_truth),
            extra_files: vec![self.motion_file()?],
            extra_toml: None,
        })
    }

    /// Writes the capture directory atomically (frames, CFA, metadata, hot pixels, ground
    /// truth and motion).
    pub fn write(&self, dir: impl AsRef<Path>) -> Result<()> {
        crate::capture::write_capture(dir, &self.capture_parts()?)
    }

    /// `(file name, contents)` of the motion description, `motion.toml`.
    pub fn motion_file(&self) -> Result<(String, Vec<u8>)> {
        Ok((MOTION_FILE.into(), self.motion.to_toml()?.into_bytes()))
    }
}

impl SimulatedCmosCapture {
    /// The simulated capture as an opened multi-bit [`Capture`](crate::capture::Capture) held
    /// in memory (no files written).
    pub fn to_capture(&self) -> Result<crate::capture::Capture> {
        crate::capture::Capture::from_memory(
            crate::capture::BinaryFrames::from_multibit(&self.frames)?,
            self.cfa.clone(),
            self.meta.clone(),
            Some(self.hot_pixels.clone()),
        )
    }

    /// The parts `capture::write_capture` writes, including `motion.toml`.
    pub fn capture_parts(&self) -> Result<CaptureParts<'_>> {
        Ok(CaptureParts {
            frames: FrameData::MultiBit(&self.frames),
            width: self.cfa.width(),
            cfa: &self.cfa,
            meta: &self.meta,
            hot_pixels: Some(&self.hot_pixels),
            ground_truth: Some(&self.ground_truth),
            extra_files: vec![(MOTION_FILE.into(), self.motion.to_toml()?.into_bytes())],
            extra_toml: None,
        })
    }

    /// Writes the capture directory atomically: `frames.npy` (uint16 (T, H, W)), `cfa.npy`,
    /// `hot_pixels.npy`, `ground_truth.npy`, `motion.toml` and `capture.toml` (with
    /// `bit_depth`, `read_noise_e`, `gain_e_per_dn`, `black_level_dn` and
    /// `dark_current_e_per_s`), readable by `reconstruct` like any capture.
    pub fn write(&self, dir: impl AsRef<Path>) -> Result<()> {
        crate::capture::write_capture(dir, &self.capture_parts()?)
    }
}

/// Everything shared by the binary and CMOS renderers.
struct Prepared {
    sensor: SensorModel,
    motion: Motion,
    background: SceneRaster,
    object: Option<SceneRaster>,
    supersampling: usize,
    ground_truth: Array3<f32>,
    ground_truth_hr: Option<Array3<f32>>,
    dark: DarkCountMap,
    dark_per_frame: Array2<f32>,
    meta: CaptureMeta,
}

impl Prepared {
    fn field(&self) -> FluxField<'_> {
        FluxField {
            background: &self.background,
            object: self.object.as_ref(),
            motion: &self.motion,
            supersampling: self.supersampling,
        }
    }
}

const MOTION_STREAM: u64 = 0x6d6f_7469_6f6e;
const DARK_STREAM: u64 = 0x6461_726b;

/// Turns R, G, B planes into R, G, B, W planes in detections per frame (before the flux gain):
/// channel k scaled by its quantum efficiency, W = R + G + B. Extra planes (coverage) pass through.
fn to_detection_planes(raster: SceneRaster, qe: [f64; 3]) -> SceneRaster {
    let (c, h, w) = raster.planes.dim();
    let planes = Array3::from_shape_fn((c + 1, h, w), |(k, i, j)| match k {
        0..=2 => raster.planes[[k, i, j]] * qe[k] as f32,
        3 => (0..3)
            .map(|m| raster.planes[[m, i, j]] * qe[m] as f32)
            .sum(),
        _ => raster.planes[[k - 1, i, j]],
    });
    SceneRaster { planes, ..raster }
}

fn prepare(config: &SimulationConfig, scene: &Scene, cfa: &Cfa) -> Result<Prepared> {
    check_size(config, cfa)?;
    let (h, w, t) = (config.height, config.width, config.frames);
    let ss = config.pixel_supersampling;
    let footprint = 1.0 / ss as f64; // sensor px: the box the rasters are pre-filtered by
    let sensor = SensorModel::table1(config.sensor);
    let reference = config.reference_frame.unwrap_or(t / 2);
    let motion = Motion::generate(
        &config.motion,
        t,
        reference,
        h,
        w,
        mix(config.seed ^ MOTION_STREAM),
    )?;
    let margin = motion.max_excursion(h, w).ceil() + 3.0;
    let qe = sensor.quantum_efficiency;
    let mut background =
        to_detection_planes(scene.rasterise_with_footprint(h, w, margin, footprint), qe);
    let mut object = motion
        .object
        .as_ref()
        .map(|track| object_raster(track.radius, footprint, qe));

    // Flux gain from the unscaled ground truth, then the ground truth from the scaled rasters.
    let field = FluxField {
        background: &background,
        object: object.as_ref(),
        motion: &motion,
        supersampling: ss,
    };
    let gain = config.flux.gain(&w_values(&field.rgb(reference, h, w)))? as f32;
    background.planes.mapv_inplace(|v| v * gain);
    if let Some(obj) = object.as_mut() {
        obj.planes
            .slice_mut(s![0..4, .., ..])
            .mapv_inplace(|v| v * gain);
    }
    let field = FluxField {
        background: &background,
        object: object.as_ref(),
        motion: &motion,
        supersampling: ss,
    };
    let ground_truth = field.rgb(reference, h, w);
    let ground_truth_hr = (ss > 1).then(|| field.rgb_hr(reference, h, w, ss));

    let dark = DarkCountMap::generate(
        h,
        w,
        sensor.dark_count_rate_hz,
        config.dark_variation,
        config.hot_fraction,
        config.hot_rate_hz,
        mix(config.dark_seed.unwrap_or(config.seed) ^ DARK_STREAM),
    )?;
    let exposure_s = sensor.exposure_s();
    let dark_per_frame = dark.rates_hz.mapv(|r| (r * exposure_s) as f32);
    let meta = capture_meta(&sensor, &dark, reference);
    Ok(Prepared {
        sensor,
        motion,
        background,
        object,
        supersampling: ss,
        ground_truth,
        ground_truth_hr,
        dark,
        dark_per_frame,
        meta,
    })
}

/// Checks the simulation's size, the CFA's agreement with it and the pixel supersampling.
fn check_size(config: &SimulationConfig, cfa: &Cfa) -> Result<()> {
    let (h, w, t) = (config.height, config.width, config.frames);
    if h == 0 || w == 0 || t == 0 {
        return Err(Error::invalid(format!(
            "simulation size must be non-zero, got {w}x{h} pixels and {t} frames"
        )));
    }
    if (cfa.height(), cfa.width()) != (h, w) {
        return Err(Error::invalid(format!(
            "CFA is {}x{}, the sensor is {w}x{h}",
            cfa.width(),
            cfa.height()
        )));
    }
    let ss = config.pixel_supersampling;
    if ss == 0 || ss > 16 {
        return Err(Error::invalid(format!(
            "pixel supersampling must be 1..=16, got {ss}"
        )));
    }
    Ok(())
}

/// The moving object's raster: a disc of `radius` px with the chart's object texture, in
/// detection planes of quantum efficiency `qe`, pre-filtered by the pixel `footprint`.
fn object_raster(radius: f64, footprint: f64, qe: [f64; 3]) -> SceneRaster {
    let r = radius;
    let step = 0.5 * footprint;
    let n = ((2.0 * r + 4.0) / step).ceil() as usize + 1;
    let origin = [-(n as f64 - 1.0) * step / 2.0; 2];
    let planes = scene::supersample(n, n, origin, step, |y, x| {
        let a = if y * y + x * x < r * r { 1.0 } else { 0.0 };
        let c = chart::object_texture(y, x);
        [c[0] * a, c[1] * a, c[2] * a, a]
    });
    to_detection_planes(
        SceneRaster::new_filtered_footprint(planes, origin, step, footprint),
        qe,
    )
}

/// The W value (R + G + B) of every pixel of an `(H, W, 3)` image, row-major.
fn w_values(rgb: &Array3<f32>) -> Vec<f32> {
    rgb.outer_iter()
        .flat_map(|row| row.outer_iter().map(|v| v.sum()).collect::<Vec<_>>())
        .collect()
}

/// The `capture.toml` metadata of a simulated capture of `sensor` with dark counts `dark`.
fn capture_meta(sensor: &SensorModel, dark: &DarkCountMap, reference: usize) -> CaptureMeta {
    CaptureMeta {
        exposure_s: sensor.exposure_s(),
        dark_count_rate_hz: dark.mean_normal_rate(),
        w_weights: [1.0, 1.0, 1.0],
        hot_pixels: Some("hot_pixels.npy".into()),
        reference_frame: Some(reference),
        read_noise_e: sensor.read_noise_e,
        multibit: (sensor.bit_depth > 1).then_some(MultiBitReadout {
            bit_depth: sensor.bit_depth,
            gain_e_per_dn: sensor.gain_e_per_dn,
            black_level_dn: sensor.black_level_dn,
        }),
    }
}

/// The CFA named by `config.cfa` at the configured size.
pub fn config_cfa(config: &SimulationConfig) -> Result<Cfa> {
    let pattern = Pattern::from_str(&config.cfa)?;
    cfa::generate(&pattern, config.height, config.width, config.cfa_seed)
}

/// Labels of the progress of frame rendering.
const PROGRESS_BINARY: &str = "simulating binary frames";
const PROGRESS_CMOS: &str = "simulating CMOS frames";

/// How `sensor` reads a frame out: a binary readout, or `None` for the multi-bit CMOS sensor.
fn binary_readout(sensor: SensorKind) -> Option<BinaryReadout> {
    match sensor {
        SensorKind::Spad => Some(BinaryReadout::Spad),
        SensorKind::Jot => Some(BinaryReadout::Jot(JotReadout::new(
            SensorModel::table1(SensorKind::Jot).read_noise_e,
        ))),
        SensorKind::Cmos => None,
    }
}

/// Simulates a binary capture (SPAD or jot sensor) of `scene` with the CFA named in `config`.
pub fn simulate(
    config: &SimulationConfig,
    scene: &Scene,
    progress: &dyn Progress,
) -> Result<SimulatedCapture> {
    simulate_with_cfa(config, scene, &config_cfa(config)?, progress)
}

/// Simulates a binary capture (SPAD or jot sensor) of `scene` behind `cfa` (which must be
/// `config.height` x `config.width`; `config.cfa` is ignored).
pub fn simulate_with_cfa(
    config: &SimulationConfig,
    scene: &Scene,
    cfa: &Cfa,
    progress: &dyn Progress,
) -> Result<SimulatedCapture> {
    let readout = binary_readout(config.sensor)
        .ok_or_else(|| Error::invalid("the CMOS sensor has multi-bit frames; use simulate_cmos"))?;
    let prep = prepare(config, scene, cfa)?;
    let job = render::FrameJob {
        field: &prep.field(),
        cfa,
        dark_per_frame: &prep.dark_per_frame,
        frames: config.frames,
        seed: config.seed,
    };
    let packed_frames = render::render_binary(&job, readout, progress);
    Ok(SimulatedCapture {
        packed_frames,
        width: config.width,
        cfa: cfa.clone(),
        meta: prep.meta,
        hot_pixels: prep.dark.hot_pixels,
        ground_truth: prep.ground_truth,
        ground_truth_hr: prep.ground_truth_hr,
        motion: prep.motion,
        dark_count_rates_hz: prep.dark.rates_hz,
        sensor: prep.sensor,
    })
}

/// The ground truth of the capture `config` simulates of `scene` behind `cfa`, at each of
/// `frames` instead of the reference frame: λ of R, G, B (H, W, 3) of the scene as frame t sees
/// it (camera and object motion of frame t, the same flux gain as
/// [`SimulatedCapture::ground_truth`]), the truth of a reconstruction registered to frame t
/// (a video frame, [`crate::video`]). Renders no frames.
pub fn ground_truth_at(
    config: &SimulationConfig,
    scene: &Scene,
    cfa: &Cfa,
    frames: &[usize],
) -> Result<Vec<Array3<f32>>> {
    let prep = prepare(config, scene, cfa)?;
    frames
        .iter()
        .map(|&t| {
            if t >= config.frames {
                return Err(Error::invalid(format!(
                    "ground truth: frame {t} is outside the {} simulated frames",
                    config.frames
                )));
            }
            Ok(prep.field().rgb(t, config.height, config.width))
        })
        .collect()
}

/// Simulates a conventional CMOS capture (`config.sensor` is taken as CMOS whatever it says).
pub fn simulate_cmos(
    config: &SimulationConfig,
    scene: &Scene,
    progress: &dyn Progress,
) -> Result<SimulatedCmosCapture> {
    simulate_cmos_with_cfa(config, scene, &config_cfa(config)?, progress)
}

/// As [`simulate_cmos`] with an explicit CFA.
pub fn simulate_cmos_with_cfa(
    config: &SimulationConfig,
    scene: &Scene,
    cfa: &Cfa,
    progress: &dyn Progress,
) -> Result<SimulatedCmosCapture> {
    let config = SimulationConfig {
        sensor: SensorKind::Cmos,
        ..config.clone()
    };
    let prep = prepare(&config, scene, cfa)?;
    let job = render::FrameJob {
        field: &prep.field(),
        cfa,
        dark_per_frame: &prep.dark_per_frame,
        frames: config.frames,
        seed: config.seed,
    };
    let frames = render::render_cmos(&job, &prep.sensor, progress);
    Ok(SimulatedCmosCapture {
        frames,
        cfa: cfa.clone(),
        meta: prep.meta,
        hot_pixels: prep.dark.hot_pixels,
        ground_truth: prep.ground_truth,
        ground_truth_hr: prep.ground_truth_hr,
        motion: prep.motion,
        dark_count_rates_hz: prep.dark.rates_hz,
        sensor: prep.sensor,
    })
}
