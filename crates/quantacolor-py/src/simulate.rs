//! `simulate`: a simulated colour single-photon capture (paper Table 1 sensors), as
//! `quantacolor simulate`.

#![forbid(unsafe_code)]

use crate::args::{index_arg, parse_arg};
use crate::capture::PyCapture;
use crate::errors::{compute, lib_err};
use crate::progress::PyProgress;
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use quantacolor::simulate::{FluxSpec, MotionConfig, Scene, SensorKind, SimulationConfig};
use std::path::PathBuf;
use std::sync::Arc;

/// Simulates a colour single-photon capture (paper Table 1; ``quantacolor simulate``, same
/// names and defaults).
///
/// Parameters
/// ----------
/// scene : str
///     An image file (PNG/JPEG sRGB, EXR linear) or "builtin:chart" (default),
///     "builtin:chart-hdr" or "builtin:flat".
/// motion : {"handheld", "static", "pan", "fast-handheld", "circular", "object"}
///     Camera (or object) motion; default "handheld".
/// frames : int
///     Number of binary frames T (default 512).
/// flux : float
///     Mean detections per frame of a W pixel over the image (default 0.1).
/// cfa : str
///     Colour filter array: "rgbw-75-regular" (default), "bayer", "rgbw-75-bluenoise", ...
/// sensor : {"spad", "jot", "cmos"}
///     Sensor model (default "spad").
/// seed : int
///     Seed of motion, dark counts and photon noise (default 1): same seed, same bytes.
/// size : (int, int)
///     (width, height) in pixels (default (496, 254)).
/// cfa_seed : int
///     Seed of pseudorandom CFA patterns (default 0).
/// hot_fraction : float
///     Fraction of hot pixels (default 0.02).
/// reference_frame : int, optional
///     Reference frame (default T // 2).
/// out : path, optional
///     Also write the capture directory there (refused if it holds something other than a
///     capture). Default: none, the capture stays in memory.
/// progress : callable, optional
///     Called as ``progress(stage, done, total)`` (default: none).
///
/// Returns
/// -------
/// Capture
///     The capture, with ``ground_truth`` (float32 (H, W, 3), λ of R, G, B at the reference
///     frame).
///
/// Raises
/// ------
/// TypeError, ValueError
///     A bad argument (the message names it); OSError when ``out`` cannot be written.
#[pyfunction]
#[pyo3(signature = (scene="builtin:chart", motion="handheld", frames=512, flux=0.1,
                    cfa="rgbw-75-regular", sensor="spad", seed=1, size=(496, 254), *,
                    cfa_seed=0, hot_fraction=0.02, reference_frame=None, out=None,
                    progress=None))]
#[expect(
    clippy::too_many_arguments,
    reason = "pyo3: the parameters are the Python keyword arguments"
)]
pub(crate) fn simulate<'py>(
    py: Python<'py>,
    scene: &str,
    motion: &str,
    frames: i64,
    flux: f64,
    cfa: &str,
    sensor: &str,
    seed: u64,
    size: (i64, i64),
    cfa_seed: u64,
    hot_fraction: f64,
    reference_frame: Option<i64>,
    out: Option<PathBuf>,
    progress: Option<Bound<'py, PyAny>>,
) -> PyResult<PyCapture> {
    let args = SimulateArgs {
        scene,
        motion,
        frames,
        flux,
        cfa,
        sensor,
        seed,
        size,
        cfa_seed,
        hot_fraction,
        reference_frame,
        out,
    };
    simulate_capture(py, args, progress)
}

/// The arguments of `simulate` but the progress callback, as Python passed them.
struct SimulateArgs<'a> {
    scene: &'a str,
    motion: &'a str,
    frames: i64,
    flux: f64,
    cfa: &'a str,
    sensor: &'a str,
    seed: u64,
    size: (i64, i64),
    cfa_seed: u64,
    hot_fraction: f64,
    reference_frame: Option<i64>,
    out: Option<PathBuf>,
}

/// `simulate`: the options checked, then the simulation (and the capture directory) without the GIL.
fn simulate_capture<'py>(
    py: Python<'py>,
    args: SimulateArgs<'_>,
    progress: Option<Bound<'py, PyAny>>,
) -> PyResult<PyCapture> {
    let SimulateArgs {
        scene,
        motion,
        frames,
        flux,
        cfa,
        sensor,
        seed,
        size,
        cfa_seed,
        hot_fraction,
        reference_frame,
        out,
    } = args;
    if frames < 1 {
        return Err(PyValueError::new_err(format!(
            "frames must be >= 1, got {frames}"
        )));
    }
    let (width, height) = size;
    if width < 1 || height < 1 {
        return Err(PyValueError::new_err(format!(
            "size must be (width, height) with both >= 1, got {size:?}"
        )));
    }
    let sensor_kind = parse_arg::<SensorKind>("sensor", sensor)?;
    if sensor_kind == SensorKind::Cmos {
        return Err(PyValueError::new_err(
            "sensor 'cmos' simulates multi-bit frames, which a binary Capture cannot hold; \
             use 'spad' or 'jot' (or the CLI for CMOS baselines)",
        ));
    }
    let config = SimulationConfig {
        height: height as usize,
        width: width as usize,
        frames: frames as usize,
        cfa: cfa.to_string(),
        cfa_seed,
        sensor: sensor_kind,
        flux: FluxSpec::Mean { flux },
        motion: parse_arg::<MotionConfig>("motion", motion)?,
        reference_frame: index_arg("reference_frame", reference_frame)?,
        hot_fraction,
        seed,
        ..SimulationConfig::default()
    };
    let scene = scene.to_string();
    let sink = PyProgress::new(progress)?;
    let result = compute(py, || {
        let scene = Scene::from_spec(&scene).map_err(|e| lib_err("scene", e))?;
        let sim =
            quantacolor::simulate::simulate(&config, &scene, &sink).map_err(|e| lib_err("", e))?;
        if let Some(dir) = &out {
            sim.write(dir).map_err(|e| lib_err("out", e))?;
        }
        let capture = sim.to_capture().map_err(|e| lib_err("", e))?;
        Ok(PyCapture {
            inner: Arc::new(capture),
            ground_truth: Some(sim.ground_truth),
        })
    });
    sink.check(py)?;
    result
}
