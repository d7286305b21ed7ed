//! Python bindings of quantacolor (module `quantacolor._native`, wrapped by the pure-Python
//! package `quantacolor`). This crate only converts types: numpy arrays and Python values in,
//! library calls, numpy arrays out. Every algorithm lives in the `quantacolor` crate.
//!
//! Conventions kept here:
//! - The GIL is released around every library call (`allow_threads`), so Python threads run
//!   reconstructions concurrently; progress reaches an optional Python callback, which
//!   re-acquires the GIL for the call.
//! - Bad input raises `TypeError` (wrong type or dtype) or `ValueError` (rank, shape, range),
//!   naming the argument; library errors map to `ValueError` (invalid values, bad files) or
//!   `OSError` (I/O). A Rust panic is caught and raised as `RuntimeError`, never unwinds into
//!   Python.

use ndarray::{Array2, Array3};
use numpy::{
    dtype, IntoPyArray, PyArray2, PyArray3, PyArrayDescrMethods, PyArrayMethods, PyUntypedArray,
    PyUntypedArrayMethods,
};
use pyo3::exceptions::{PyOSError, PyRuntimeError, PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyBool, PyDict, PyFloat, PyInt, PyList, PyString, PyTuple};
use quantacolor::capture::{BinaryFrames, CaptureMeta};
use quantacolor::denoise::chroma::{denoise_linear, DenoiseConfig, DenoiseInput, DenoiseMethod};
use quantacolor::display::{
    render_srgb8, ColorMatrix, MesopicConfig, MesopicOffset, RenderOptions, ToneMap,
};
use quantacolor::metrics::{evaluate, evaluate_lpips, EvalOptions};
use quantacolor::pipeline::{Method, ReconstructConfig, ReconstructOverrides};
use quantacolor::progress::Progress;
use quantacolor::simulate::{FluxSpec, MotionConfig, Scene, SensorKind, SimulationConfig};
use quantacolor::Cfa;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::PathBuf;
use std::sync::{Arc, Mutex};

// ---------------------------------------------------------------------------------------------
// Errors

/// A library error as a Python exception, prefixed with `context` (the argument or call).
fn lib_err(context: &str, e: quantacolor::Error) -> PyErr {
    let prefix = if context.is_empty() {
        String::new()
    } else {
        format!("{context}: ")
    };
    match e {
        quantacolor::Error::Invalid(m) => PyValueError::new_err(format!("{prefix}{m}")),
        quantacolor::Error::Format { .. } => PyValueError::new_err(format!("{prefix}{e}")),
        quantacolor::Error::Io { .. } => PyOSError::new_err(format!("{prefix}{e}")),
    }
}

/// Runs `f` without the GIL; a panic becomes a `RuntimeError`.
fn compute<T: Send>(py: Python<'_>, f: impl FnOnce() -> PyResult<T> + Send) -> PyResult<T> {
    py.allow_threads(|| match catch_unwind(AssertUnwindSafe(f)) {
        Ok(r) => r,
        Err(panic) => {
            let msg = panic
                .downcast_ref::<String>()
                .cloned()
                .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
                .unwrap_or_else(|| "unknown panic".into());
            Err(PyRuntimeError::new_err(format!(
                "internal error in quantacolor (please report): {msg}"
            )))
        }
    })
}

// ---------------------------------------------------------------------------------------------
// Progress

/// Forwards progress to a Python callable `callback(stage: str, done: int, total: int)`. The
/// first exception it raises stops further calls and is re-raised when the computation ends.
struct PyProgress {
    callback: Option<Py<PyAny>>,
    state: Mutex<(String, u64, u64)>,
    error: Mutex<Option<PyErr>>,
}

impl PyProgress {
    fn new(callback: Option<Bound<'_, PyAny>>) -> PyResult<Self> {
        if let Some(cb) = &callback {
            if !cb.is_callable() {
                return Err(PyTypeError::new_err(format!(
                    "progress must be a callable (stage, done, total) or None, got {}",
                    type_name(cb)
                )));
            }
        }
        Ok(PyProgress {
            callback: callback.map(|c| c.unbind()),
            state: Mutex::new((String::new(), 0, 0)),
            error: Mutex::new(None),
        })
    }

    fn report(&self, label: &str, done: u64, total: u64) {
        let Some(cb) = &self.callback else { return };
        if self.error.lock().map(|e| e.is_some()).unwrap_or(true) {
            return;
        }
        Python::with_gil(|py| {
            if let Err(e) = cb.call1(py, (label, done, total)) {
                if let Ok(mut slot) = self.error.lock() {
                    slot.get_or_insert(e);
                }
            }
        });
    }

    /// The callback's exception, if it raised one.
    fn check(self, py: Python<'_>) -> PyResult<()> {
        let _ = py;
        match self.error.into_inner() {
            Ok(Some(e)) => Err(e),
            _ => Ok(()),
        }
    }
}

impl Progress for PyProgress {
    fn start(&self, label: &str, total: u64) {
        if self.callback.is_none() {
            return;
        }
        if let Ok(mut s) = self.state.lock() {
            *s = (label.to_string(), 0, total);
        }
        self.report(label, 0, total);
    }

    fn advance(&self, n: u64) {
        if self.callback.is_none() {
            return;
        }
        let snapshot = self.state.lock().ok().map(|mut s| {
            s.1 += n;
            s.clone()
        });
        if let Some((label, done, total)) = snapshot {
            self.report(&label, done, total);
        }
    }

    fn finish(&self) {}
}

// ---------------------------------------------------------------------------------------------
// Argument conversion

fn type_name(obj: &Bound<'_, PyAny>) -> String {
    obj.get_type()
        .name()
        .map(|n| n.to_string())
        .unwrap_or_else(|_| "?".into())
}

/// The `cfa` argument: uint8 (H, W), codes 0=R 1=G 2=B 3=W.
fn cfa_arg(py: Python<'_>, cfa: &Bound<'_, PyAny>) -> PyResult<Cfa> {
    let cfa_arr = as_ndarray("cfa", cfa)?;
    if !cfa_arr.dtype().is_equiv_to(&dtype::<u8>(py)) {
        return Err(PyTypeError::new_err(format!(
            "cfa must be uint8 codes 0=R 1=G 2=B 3=W, got dtype {}",
            dtype_str(&cfa_arr)
        )));
    }
    check_ndim("cfa", &cfa_arr, 2, "(H, W)")?;
    let codes: Array2<u8> = cfa_arr
        .downcast::<PyArray2<u8>>()?
        .readonly()
        .as_array()
        .to_owned();
    Cfa::new(codes).map_err(|e| lib_err("cfa", e))
}

/// The `frames` argument as packed frames: uint8 (T, H, ceil(W/8)) packed MSB first as it is,
/// or bool / uint8 0/1 (T, H, W) unpacked, packed here; `(h, w)` is the CFA's size.
fn packed_frames_arg(
    py: Python<'_>,
    frames: &Bound<'_, PyAny>,
    h: usize,
    w: usize,
) -> PyResult<Array3<u8>> {
    let fr = as_ndarray("frames", frames)?;
    check_ndim("frames", &fr, 3, "(T, H, ceil(W/8)) packed or (T, H, W)")?;
    let shape = fr.shape().to_vec();
    if shape[0] == 0 {
        return Err(PyValueError::new_err(
            "frames holds no frames (T = 0); a capture needs at least one",
        ));
    }
    if shape[1] != h {
        return Err(PyValueError::new_err(format!(
            "frames has height {} (shape {shape:?}), cfa has height {h} (shape ({h}, {w}))",
            shape[1]
        )));
    }
    if fr.dtype().is_equiv_to(&dtype::<bool>(py)) {
        if shape[2] != w {
            return Err(PyValueError::new_err(format!(
                "frames (bool, unpacked) has width {}, cfa has width {w}",
                shape[2]
            )));
        }
        let bits = fr
            .downcast::<PyArray3<bool>>()?
            .readonly()
            .as_array()
            .mapv(u8::from);
        Ok(quantacolor::capture::frames::pack_bits(&bits))
    } else if fr.dtype().is_equiv_to(&dtype::<u8>(py)) {
        let arr = fr.downcast::<PyArray3<u8>>()?.readonly();
        let view = arr.as_array();
        if shape[2] == w && (w != 1 || view.iter().all(|&b| b <= 1)) {
            if let Some(&bad) = view.iter().find(|&&b| b > 1) {
                return Err(PyValueError::new_err(format!(
                    "frames (uint8, unpacked (T, H, W)) must hold 0 or 1, found {bad}; \
                     packed frames have ceil(W/8) = {} bytes per row",
                    w.div_ceil(8)
                )));
            }
            Ok(quantacolor::capture::frames::pack_bits(&view.to_owned()))
        } else if shape[2] == w.div_ceil(8) {
            Ok(view.to_owned())
        } else {
            Err(PyValueError::new_err(format!(
                "frames has shape {shape:?}: for cfa width {w} its last axis must be {} \
                 (packed) or {w} (unpacked)",
                w.div_ceil(8)
            )))
        }
    } else {
        Err(PyTypeError::new_err(format!(
            "frames must be uint8 (packed or 0/1) or bool, got dtype {}",
            dtype_str(&fr)
        )))
    }
}

/// The `hot_pixels` argument: a bool (H, W) mask.
fn hot_pixels_arg(py: Python<'_>, obj: &Bound<'_, PyAny>) -> PyResult<Array2<bool>> {
    let a = as_ndarray("hot_pixels", obj)?;
    if !a.dtype().is_equiv_to(&dtype::<bool>(py)) {
        return Err(PyTypeError::new_err(format!(
            "hot_pixels must be a bool (H, W) mask, got dtype {}",
            dtype_str(&a)
        )));
    }
    check_ndim("hot_pixels", &a, 2, "(H, W)")?;
    Ok(a.downcast::<PyArray2<bool>>()?
        .readonly()
        .as_array()
        .to_owned())
}

/// The `ground_truth` argument: a float32 (h, w, 3) linear image.
fn ground_truth_arg(obj: &Bound<'_, PyAny>, h: usize, w: usize) -> PyResult<Array3<f32>> {
    let t = linear_image("ground_truth", obj)?;
    if t.dim() != (h, w, 3) {
        return Err(PyValueError::new_err(format!(
            "ground_truth has shape {:?}, expected ({h}, {w}, 3)",
            t.dim()
        )));
    }
    Ok(t)
}

/// `obj` as a numpy array, or a `TypeError` naming `arg`.
fn as_ndarray<'py>(arg: &str, obj: &Bound<'py, PyAny>) -> PyResult<Bound<'py, PyUntypedArray>> {
    obj.downcast::<PyUntypedArray>().cloned().map_err(|_| {
        PyTypeError::new_err(format!(
            "{arg} must be a numpy array, got {}",
            type_name(obj)
        ))
    })
}

fn dtype_str(a: &Bound<'_, PyUntypedArray>) -> String {
    a.dtype().to_string()
}

fn check_ndim(arg: &str, a: &Bound<'_, PyUntypedArray>, ndim: usize, what: &str) -> PyResult<()> {
    if a.ndim() != ndim {
        return Err(PyValueError::new_err(format!(
            "{arg} must have {ndim} dimensions {what}, got shape {:?}",
            a.shape()
        )));
    }
    Ok(())
}

/// A float32 (H, W, 3) linear image (float64 is accepted and converted).
fn linear_image(arg: &str, obj: &Bound<'_, PyAny>) -> PyResult<Array3<f32>> {
    let a = as_ndarray(arg, obj)?;
    check_ndim(arg, &a, 3, "(H, W, 3)")?;
    let shape = a.shape().to_vec();
    if shape[2] != 3 || shape[0] == 0 || shape[1] == 0 {
        return Err(PyValueError::new_err(format!(
            "{arg} must have shape (H, W, 3) with H, W > 0, got {shape:?}"
        )));
    }
    let py = obj.py();
    if a.dtype().is_equiv_to(&dtype::<f32>(py)) {
        let arr = a.downcast::<PyArray3<f32>>()?;
        Ok(arr.readonly().as_array().to_owned())
    } else if a.dtype().is_equiv_to(&dtype::<f64>(py)) {
        let arr = a.downcast::<PyArray3<f64>>()?;
        Ok(arr.readonly().as_array().mapv(|v| v as f32))
    } else {
        Err(PyTypeError::new_err(format!(
            "{arg} must be float32 or float64, got dtype {}",
            dtype_str(&a)
        )))
    }
}

/// `(wR, wG, wB)`: three finite numbers.
fn w_weights_arg(obj: &Bound<'_, PyAny>) -> PyResult<[f64; 3]> {
    let v: Vec<f64> = obj.extract().map_err(|_| {
        PyTypeError::new_err(format!(
            "w_weights must be a sequence of three numbers (wR, wG, wB), got {}",
            type_name(obj)
        ))
    })?;
    <[f64; 3]>::try_from(v).map_err(|v| {
        PyValueError::new_err(format!(
            "w_weights must hold three numbers (wR, wG, wB), got {}",
            v.len()
        ))
    })
}

/// A non-negative integer (or None), as `usize`.
fn index_arg(arg: &str, value: Option<i64>) -> PyResult<Option<usize>> {
    value
        .map(|v| {
            usize::try_from(v)
                .map_err(|_| PyValueError::new_err(format!("{arg} must be >= 0, got {v}")))
        })
        .transpose()
}

fn parse_arg<T: std::str::FromStr<Err = quantacolor::Error>>(arg: &str, s: &str) -> PyResult<T> {
    s.parse::<T>().map_err(|e| lib_err(arg, e))
}

/// A Python value (dict, list, str, int, float, bool) as TOML, for `config=` dicts.
fn to_toml(path: &str, obj: &Bound<'_, PyAny>) -> PyResult<toml::Value> {
    if obj.is_instance_of::<PyBool>() {
        return Ok(toml::Value::Boolean(obj.extract()?));
    }
    if obj.is_instance_of::<PyInt>() {
        return Ok(toml::Value::Integer(obj.extract()?));
    }
    if obj.is_instance_of::<PyFloat>() {
        return Ok(toml::Value::Float(obj.extract()?));
    }
    if obj.is_instance_of::<PyString>() {
        return Ok(toml::Value::String(obj.extract()?));
    }
    if let Ok(d) = obj.downcast::<PyDict>() {
        let mut table = toml::Table::new();
        for (k, v) in d.iter() {
            let key: String = k.extract().map_err(|_| {
                PyTypeError::new_err(format!(
                    "{path}: keys must be strings, got {}",
                    type_name(&k)
                ))
            })?;
            let value = to_toml(&format!("{path}.{key}"), &v)?;
            table.insert(key, value);
        }
        return Ok(toml::Value::Table(table));
    }
    if obj.is_instance_of::<PyList>() || obj.is_instance_of::<PyTuple>() {
        let items: Vec<Bound<'_, PyAny>> = obj.extract()?;
        return items
            .iter()
            .enumerate()
            .map(|(i, v)| to_toml(&format!("{path}[{i}]"), v))
            .collect::<PyResult<Vec<_>>>()
            .map(toml::Value::Array);
    }
    if obj.is_none() {
        return Err(PyTypeError::new_err(format!(
            "{path}: None has no TOML equivalent; leave the key out for its default"
        )));
    }
    Err(PyTypeError::new_err(format!(
        "{path} must be a dict, list, str, int, float or bool, got {}",
        type_name(obj)
    )))
}

/// A `config=` dict (the keys of `report.toml`'s `[config]`) as a `T`.
fn config_arg<T: serde::de::DeserializeOwned + Default>(
    obj: Option<&Bound<'_, PyAny>>,
) -> PyResult<T> {
    let Some(obj) = obj.filter(|o| !o.is_none()) else {
        return Ok(T::default());
    };
    if !obj.is_instance_of::<PyDict>() {
        return Err(PyTypeError::new_err(format!(
            "config must be a dict (the keys of report.toml's [config]) or None, got {}",
            type_name(obj)
        )));
    }
    // Through TOML text, so that an error shows the key at fault.
    let text = toml::to_string(&to_toml("config", obj)?)
        .map_err(|e| PyValueError::new_err(format!("config: {e}")))?;
    quantacolor::config_toml::parse::<T>(&text)
        .map_err(|e| PyValueError::new_err(format!("config: {}", e.to_string().trim_end())))
}

/// Reconstruction options as the library's overrides (Python spellings in errors).
#[allow(clippy::too_many_arguments)]
fn overrides(
    method: Option<&str>,
    denoise: Option<&str>,
    scale: Option<i64>,
    reference_frame: Option<i64>,
    sigma_y: Option<f32>,
    sigma_c: Option<f32>,
    block_size: Option<i64>,
    max_sub_block_motion: Option<f64>,
    window: Option<i64>,
) -> PyResult<ReconstructOverrides> {
    Ok(ReconstructOverrides {
        method: method
            .map(|m| parse_arg::<Method>("method", m))
            .transpose()?,
        denoise: denoise
            .map(|d| parse_arg::<DenoiseMethod>("denoise", d))
            .transpose()?,
        scale: match scale {
            Some(s) if s < 1 => {
                return Err(PyValueError::new_err(format!(
                    "scale must be 1, 2, 3 or 4, got {s}"
                )))
            }
            s => index_arg("scale", s)?,
        },
        reference_frame: index_arg("reference_frame", reference_frame)?,
        sigma_y,
        sigma_c,
        block_size: match block_size {
            Some(b) if b < 1 => {
                return Err(PyValueError::new_err(format!(
                    "block_size must be >= 1, got {b}"
                )))
            }
            b => index_arg("block_size", b)?,
        },
        max_sub_block_motion,
        window: match window {
            Some(w) if w < 1 => {
                return Err(PyValueError::new_err(format!(
                    "window must be >= 1, got {w}"
                )))
            }
            w => index_arg("window", w)?,
        },
    })
}

fn reconstruct_config(
    config: Option<&Bound<'_, PyAny>>,
    overrides: &ReconstructOverrides,
) -> PyResult<ReconstructConfig> {
    let mut cfg: ReconstructConfig = config_arg(config)?;
    overrides
        .apply(&mut cfg, &|key| key.to_string())
        .map_err(|e| lib_err("", e))?;
    Ok(cfg)
}

/// Render options of `display` / `preview.png`.
fn render_options(
    tonemap: &str,
    mesopic: Option<MesopicOffset>,
    frames: Option<f64>,
    exposure: Option<f32>,
    w_weights: [f64; 3],
    ccm: Option<&Bound<'_, PyAny>>,
) -> PyResult<RenderOptions> {
    let tonemap = parse_arg::<ToneMap>("tonemap", tonemap)?;
    if let Some(e) = exposure {
        if !(e.is_finite() && e > 0.0) {
            return Err(PyValueError::new_err(format!(
                "exposure must be a positive number, got {e}"
            )));
        }
    }
    if let Some(f) = frames {
        if !(f.is_finite() && f > 0.0) {
            return Err(PyValueError::new_err(format!(
                "frames must be a positive number, got {f}"
            )));
        }
    }
    let color_matrix = match ccm.filter(|c| !c.is_none()) {
        None => None,
        Some(c) => Some(ccm_arg(c)?),
    };
    Ok(RenderOptions {
        exposure,
        color_matrix,
        tonemap,
        mesopic: mesopic.map(|l0| MesopicConfig { l0, frames }),
        w_weights,
    })
}

/// `mesopic=`: a finite number (L0 of supplement Eq. 9) or the string "auto".
fn mesopic_arg(obj: Option<&Bound<'_, PyAny>>) -> PyResult<Option<MesopicOffset>> {
    let Some(obj) = obj.filter(|o| !o.is_none()) else {
        return Ok(None);
    };
    if obj.is_instance_of::<PyString>() {
        let text: String = obj.extract()?;
        return parse_arg::<MesopicOffset>("mesopic", &text).map(Some);
    }
    let l0: f32 = obj
        .extract()
        .map_err(|_| PyTypeError::new_err("mesopic must be a number (L0) or \"auto\""))?;
    if !l0.is_finite() {
        return Err(PyValueError::new_err(format!(
            "mesopic must be a finite number, got {l0}"
        )));
    }
    Ok(Some(MesopicOffset::Fixed(l0)))
}

/// `ccm=`: a path to a `calibrate-color` TOML file or a (3, 3) / (3, 4) matrix.
fn ccm_arg(obj: &Bound<'_, PyAny>) -> PyResult<ColorMatrix> {
    if let Ok(path) = obj.extract::<PathBuf>() {
        return ColorMatrix::read(&path).map_err(|e| lib_err("ccm", e));
    }
    let rows: Vec<Vec<f64>> = obj.extract().map_err(|_| {
        PyTypeError::new_err(format!(
            "ccm must be a path or a (3, 3) / (3, 4) matrix, got {}",
            type_name(obj)
        ))
    })?;
    let affine = rows.first().map(|r| r.len() == 4).unwrap_or(false);
    let m = ColorMatrix {
        rows,
        affine,
        gain: None,
    };
    m.validate().map_err(|e| lib_err("ccm", e))?;
    Ok(m)
}

// ---------------------------------------------------------------------------------------------
// Capture

/// A colour single-photon capture: T binary frames, the colour filter array and the metadata
/// that turns counts into flux (paper §3, Eq. 2–3). Open a capture directory with
/// `Capture.open(path)`, wrap arrays with `Capture.from_arrays(...)`, or simulate one with
/// `quantacolor.simulate(...)`.
#[pyclass(module = "quantacolor", name = "Capture", frozen)]
struct PyCapture {
    inner: Arc<quantacolor::Capture>,
    ground_truth: Option<Array3<f32>>,
}

#[pymethods]
impl PyCapture {
    /// Opens and validates the capture directory `path` (frames.npy memory-mapped, cfa.npy or
    /// cfa.png, capture.toml; docs/capture-format.md). A `ground_truth.npy` beside them is read
    /// too. Without a hot-pixel mask in the capture, one is detected from its frames (as
    /// `quantacolor reconstruct` does) unless `detect_hot_pixels=False`.
    #[staticmethod]
    #[pyo3(signature = (path, *, detect_hot_pixels=true))]
    fn open(py: Python<'_>, path: PathBuf, detect_hot_pixels: bool) -> PyResult<Self> {
        compute(py, || {
            let capture = quantacolor::convert::open_capture(&path, None, detect_hot_pixels)
                .map_err(|e| lib_err("", e))?;
            let ground_truth = capture.ground_truth().map_err(|e| lib_err("", e))?;
            Ok(PyCapture {
                inner: Arc::new(capture),
                ground_truth,
            })
        })
    }

    /// A capture from arrays: `frames` uint8 (T, H, ceil(W/8)) packed MSB first
    /// (`np.packbits(bits, axis=-1)`), or bool/uint8 0/1 (T, H, W) unpacked; `cfa` uint8 (H, W)
    /// with 0=R 1=G 2=B 3=W; `exposure_s` of one binary frame in seconds. Optional
    /// `hot_pixels` bool (H, W) and `ground_truth` float32 (H, W, 3).
    #[staticmethod]
    #[pyo3(signature = (frames, cfa, exposure_s, dark_count_rate_hz=0.0, w_weights=None,
                        hot_pixels=None, reference_frame=None, ground_truth=None))]
    #[allow(clippy::too_many_arguments)]
    fn from_arrays(
        py: Python<'_>,
        frames: &Bound<'_, PyAny>,
        cfa: &Bound<'_, PyAny>,
        exposure_s: f64,
        dark_count_rate_hz: f64,
        w_weights: Option<&Bound<'_, PyAny>>,
        hot_pixels: Option<&Bound<'_, PyAny>>,
        reference_frame: Option<i64>,
        ground_truth: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<Self> {
        let cfa = cfa_arg(py, cfa)?;
        let (h, w) = (cfa.height(), cfa.width());
        let packed = packed_frames_arg(py, frames, h, w)?;
        let hot = hot_pixels
            .filter(|o| !o.is_none())
            .map(|obj| hot_pixels_arg(py, obj))
            .transpose()?;
        let truth = ground_truth
            .filter(|o| !o.is_none())
            .map(|obj| ground_truth_arg(obj, h, w))
            .transpose()?;
        let mut meta = CaptureMeta::new(exposure_s);
        meta.dark_count_rate_hz = dark_count_rate_hz;
        if let Some(wobj) = w_weights.filter(|o| !o.is_none()) {
            meta.w_weights = w_weights_arg(wobj)?;
        }
        meta.reference_frame = index_arg("reference_frame", reference_frame)?;
        let binary = BinaryFrames::from_packed(packed, w).map_err(|e| lib_err("frames", e))?;
        let capture = quantacolor::Capture::from_memory(binary, cfa, meta, hot)
            .map_err(|e| lib_err("", e))?;
        Ok(PyCapture {
            inner: Arc::new(capture),
            ground_truth: truth,
        })
    }

    /// Bit-packed frames, uint8 (T, H, ceil(W/8)), MSB first (a copy). Multi-bit captures
    /// (a conventional sensor's uint16 frames) raise ValueError.
    #[getter]
    fn frames<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray3<u8>>> {
        if self.inner.frames.is_multibit() {
            return Err(PyValueError::new_err(
                "this capture holds multi-bit (uint16) frames; read frames.npy with numpy",
            ));
        }
        Ok(self.inner.frames.to_packed().into_pyarray(py))
    }

    /// Number of binary frames T.
    #[getter]
    fn frame_count(&self) -> usize {
        self.inner.frames.frame_count()
    }

    /// Height H in pixels.
    #[getter]
    fn height(&self) -> usize {
        self.inner.frames.height()
    }

    /// Width W in pixels.
    #[getter]
    fn width(&self) -> usize {
        self.inner.frames.width()
    }

    /// Colour filter array, uint8 (H, W): 0=R 1=G 2=B 3=W.
    #[getter]
    fn cfa<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<u8>> {
        self.inner.cfa.codes().clone().into_pyarray(py)
    }

    /// Linear ground truth, float32 (H, W, 3), of simulated captures; None otherwise.
    #[getter]
    fn ground_truth<'py>(&self, py: Python<'py>) -> Option<Bound<'py, PyArray3<f32>>> {
        self.ground_truth.clone().map(|g| g.into_pyarray(py))
    }

    /// Hot-pixel mask, bool (H, W), or None.
    #[getter]
    fn hot_pixels<'py>(&self, py: Python<'py>) -> Option<Bound<'py, PyArray2<bool>>> {
        self.inner.hot_pixels.clone().map(|m| m.into_pyarray(py))
    }

    /// Exposure of one binary frame, seconds.
    #[getter]
    fn exposure_s(&self) -> f64 {
        self.inner.meta.exposure_s
    }

    /// Mean dark count rate, counts per second.
    #[getter]
    fn dark_count_rate_hz(&self) -> f64 {
        self.inner.meta.dark_count_rate_hz
    }

    /// W = wR·R + wG·G + wB·B.
    #[getter]
    fn w_weights(&self) -> (f64, f64, f64) {
        let w = self.inner.meta.w_weights;
        (w[0], w[1], w[2])
    }

    /// The reference frame: the capture's, else T/2 rounded down.
    #[getter]
    fn reference_frame(&self) -> usize {
        self.inner.reference_frame()
    }

    fn __repr__(&self) -> String {
        format!(
            "Capture(T={}, H={}, W={}, exposure_s={}, ground_truth={})",
            self.inner.frames.frame_count(),
            self.inner.frames.height(),
            self.inner.frames.width(),
            self.inner.meta.exposure_s,
            if self.ground_truth.is_some() {
                "yes"
            } else {
                "no"
            }
        )
    }
}

fn capture_arg(
    arg: &str,
    obj: &Bound<'_, PyAny>,
) -> PyResult<(Arc<quantacolor::Capture>, Option<Array3<f32>>)> {
    let c = obj.downcast::<PyCapture>().map_err(|_| {
        PyTypeError::new_err(format!(
            "{arg} must be a quantacolor.Capture (Capture.open, Capture.from_arrays or \
             simulate), got {}",
            type_name(obj)
        ))
    })?;
    let c = c.get();
    Ok((c.inner.clone(), c.ground_truth.clone()))
}

// ---------------------------------------------------------------------------------------------
// Functions

/// Reconstructs `capture` into linear RGB, float32 (H·scale, W·scale, 3), in mean detections
/// per binary frame of an R, G or B pixel with dark counts removed. Same result as the CLI's
/// `linear.npy` for the same inputs and options.
#[pyfunction]
#[pyo3(signature = (capture, method=None, denoise=None, scale=None, reference_frame=None,
                    config=None, *, sigma_y=None, sigma_c=None, block_size=None,
                    max_sub_block_motion=None, window=None, progress=None))]
#[allow(clippy::too_many_arguments)]
fn reconstruct<'py>(
    py: Python<'py>,
    capture: &Bound<'py, PyAny>,
    method: Option<&str>,
    denoise: Option<&str>,
    scale: Option<i64>,
    reference_frame: Option<i64>,
    config: Option<&Bound<'py, PyAny>>,
    sigma_y: Option<f32>,
    sigma_c: Option<f32>,
    block_size: Option<i64>,
    max_sub_block_motion: Option<f64>,
    window: Option<i64>,
    progress: Option<Bound<'py, PyAny>>,
) -> PyResult<Bound<'py, PyArray3<f32>>> {
    let (capture, _) = capture_arg("capture", capture)?;
    let ov = overrides(
        method,
        denoise,
        scale,
        reference_frame,
        sigma_y,
        sigma_c,
        block_size,
        max_sub_block_motion,
        window,
    )?;
    let cfg = reconstruct_config(config, &ov)?;
    let sink = PyProgress::new(progress)?;
    let result = compute(py, || {
        quantacolor::pipeline::reconstruct(&capture, &cfg, &sink).map_err(|e| lib_err("", e))
    });
    sink.check(py)?;
    Ok(result?.linear.into_pyarray(py))
}

/// Reconstructs the capture directory `capture_dir` into `out_dir` exactly as `quantacolor
/// reconstruct CAPTURE_DIR --out OUT_DIR` does (linear.npy, linear.exr, preview.png,
/// report.toml; written atomically). Returns a summary dict.
#[pyfunction]
#[pyo3(signature = (capture_dir, out_dir, method=None, denoise=None, scale=None,
                    reference_frame=None, config=None, *, sigma_y=None, sigma_c=None,
                    block_size=None, max_sub_block_motion=None, window=None,
                    tonemap="global", mesopic=None, ccm=None, progress=None))]
#[allow(clippy::too_many_arguments)]
fn reconstruct_dir<'py>(
    py: Python<'py>,
    capture_dir: PathBuf,
    out_dir: PathBuf,
    method: Option<&str>,
    denoise: Option<&str>,
    scale: Option<i64>,
    reference_frame: Option<i64>,
    config: Option<&Bound<'py, PyAny>>,
    sigma_y: Option<f32>,
    sigma_c: Option<f32>,
    block_size: Option<i64>,
    max_sub_block_motion: Option<f64>,
    window: Option<i64>,
    tonemap: &str,
    mesopic: Option<&Bound<'py, PyAny>>,
    ccm: Option<&Bound<'py, PyAny>>,
    progress: Option<Bound<'py, PyAny>>,
) -> PyResult<Bound<'py, PyDict>> {
    let ov = overrides(
        method,
        denoise,
        scale,
        reference_frame,
        sigma_y,
        sigma_c,
        block_size,
        max_sub_block_motion,
        window,
    )?;
    let cfg = reconstruct_config(config, &ov)?;
    let ccm = ccm.filter(|c| !c.is_none()).map(ccm_arg).transpose()?;
    let tonemap = parse_arg::<ToneMap>("tonemap", tonemap)?;
    let mesopic = mesopic_arg(mesopic)?;
    let sink = PyProgress::new(progress)?;
    let result = compute(py, || {
        let capture = quantacolor::convert::open_capture(&capture_dir, None, true)
            .map_err(|e| lib_err("", e))?;
        let rec = quantacolor::pipeline::reconstruct(&capture, &cfg, &sink)
            .map_err(|e| lib_err("", e))?;
        let preview = RenderOptions {
            exposure: None,
            color_matrix: ccm,
            tonemap,
            mesopic: mesopic.map(|l0| MesopicConfig {
                l0,
                frames: Some(rec.frames_used as f64),
            }),
            w_weights: capture.meta.w_weights,
        };
        quantacolor::output::write_reconstruction(
            &out_dir,
            &capture_dir.display().to_string(),
            &capture,
            &cfg,
            &rec,
            &preview,
        )
        .map_err(|e| lib_err("", e))?;
        let seconds: f64 = rec.timings.iter().map(|t| t.seconds).sum();
        let (h, w, _) = rec.linear.dim();
        Ok((rec.reference_frame, rec.frames_used, h, w, seconds))
    });
    sink.check(py)?;
    let (reference_frame, frames_used, h, w, seconds) = result?;
    let d = PyDict::new(py);
    d.set_item("capture", capture_dir)?;
    d.set_item("out", out_dir)?;
    d.set_item("reference_frame", reference_frame)?;
    d.set_item("frames_used", frames_used)?;
    d.set_item("height", h)?;
    d.set_item("width", w)?;
    d.set_item("seconds", seconds)?;
    Ok(d)
}

/// Block-level alignment of `capture` (paper §4.1; `quantacolor align`). Returns a dict with
/// `flow` float32 (n_blocks, tiles_y, tiles_x, 2) as (dy, dx) to the reference frame, and the
/// keys of `flow.toml`: `block_size`, `block_start_frames`, `block_center_frames`,
/// `tile_size`, `tile_stride`, `tile_centers_y`, `tile_centers_x`.
#[pyfunction]
#[pyo3(signature = (capture, reference_frame=None, block_size=None, *, progress=None))]
fn align<'py>(
    py: Python<'py>,
    capture: &Bound<'py, PyAny>,
    reference_frame: Option<i64>,
    block_size: Option<i64>,
    progress: Option<Bound<'py, PyAny>>,
) -> PyResult<Bound<'py, PyDict>> {
    let (capture, _) = capture_arg("capture", capture)?;
    let reference =
        index_arg("reference_frame", reference_frame)?.unwrap_or_else(|| capture.reference_frame());
    if reference >= capture.frames.frame_count() {
        return Err(PyValueError::new_err(format!(
            "reference_frame {reference} is outside the capture's {} frames",
            capture.frames.frame_count()
        )));
    }
    let mut config = quantacolor::align::AlignConfig::default();
    config.blocks.block_size = match block_size {
        Some(b) if b < 1 => {
            return Err(PyValueError::new_err(format!(
                "block_size must be >= 1, got {b}"
            )))
        }
        b => index_arg("block_size", b)?,
    };
    let sink = PyProgress::new(progress)?;
    let result = compute(py, || {
        quantacolor::align::align(
            &capture.frames,
            &capture.cfa,
            capture.hot_pixels.as_ref(),
            reference,
            &config,
            &sink,
        )
        .map_err(|e| lib_err("", e))
    });
    sink.check(py)?;
    let alignment = result?;
    let meta = alignment.flow_meta();
    let d = PyDict::new(py);
    d.set_item(
        "flow",
        numpy::PyArray4::from_owned_array(py, alignment.flow),
    )?;
    d.set_item("block_size", meta.block_size)?;
    d.set_item("block_start_frames", meta.block_start_frames)?;
    d.set_item("block_center_frames", meta.block_center_frames)?;
    d.set_item("tile_size", meta.tile_size)?;
    d.set_item("tile_stride", meta.tile_stride)?;
    d.set_item("tile_centers_y", meta.tile_centers_y)?;
    d.set_item("tile_centers_x", meta.tile_centers_x)?;
    Ok(d)
}

/// Denoises a linear image (paper §4.3): binomial Anscombe, BM3D in the W-weighted YCbCr with
/// chroma filtered harder (`chroma-bm3d`), or plain colour BM3D (`bm3d`). `frames` is the
/// number of binary frames behind each pixel (it sets the Anscombe transform); without the
/// merge's noise model, σ is estimated from the image unless `sigma_y` / `sigma_c` are given.
#[pyfunction]
#[pyo3(signature = (linear, frames, method="chroma-bm3d", *, sigma_y=None, sigma_c=None,
                    w_weights=None, dark_counts_per_frame=0.0, config=None))]
#[allow(clippy::too_many_arguments)]
fn denoise<'py>(
    py: Python<'py>,
    linear: &Bound<'py, PyAny>,
    frames: f64,
    method: &str,
    sigma_y: Option<f32>,
    sigma_c: Option<f32>,
    w_weights: Option<&Bound<'py, PyAny>>,
    dark_counts_per_frame: f64,
    config: Option<&Bound<'py, PyAny>>,
) -> PyResult<Bound<'py, PyArray3<f32>>> {
    let image = linear_image("linear", linear)?;
    if !(frames.is_finite() && frames >= 1.0) {
        return Err(PyValueError::new_err(format!(
            "frames must be the number of binary frames behind each pixel (>= 1), got {frames}"
        )));
    }
    if !(dark_counts_per_frame.is_finite() && dark_counts_per_frame >= 0.0) {
        return Err(PyValueError::new_err(format!(
            "dark_counts_per_frame must be >= 0, got {dark_counts_per_frame}"
        )));
    }
    let w = match w_weights.filter(|o| !o.is_none()) {
        Some(o) => w_weights_arg(o)?,
        None => [1.0, 1.0, 1.0],
    };
    let mut cfg: DenoiseConfig = config_arg(config)?;
    cfg.method = parse_arg::<DenoiseMethod>("method", method)?;
    if sigma_y.is_some() {
        cfg.sigma_y = sigma_y;
    }
    if sigma_c.is_some() {
        cfg.sigma_c = sigma_c;
    }
    let out = compute(py, || {
        let input = DenoiseInput {
            noise: None,
            frames,
            model: dark_counts_per_frame.into(),
            w_weights: w,
        };
        denoise_linear(image.view(), &input, &cfg)
            .map(|(d, _)| d)
            .map_err(|e| lib_err("", e))
    })?;
    Ok(out.into_pyarray(py))
}

/// Renders a linear image to 8-bit sRGB, uint8 (H, W, 3) (paper §7; `quantacolor display`):
/// colour matrix -> noise-aware low-light view (`mesopic` = L0 or "auto", supplement Eq. 9–10;
/// a fixed L0 needs `frames`, the number of frames merged) -> exposure (`None` = automatic) ->
/// tone map (`global`, `mantiuk06` or `none`) -> sRGB.
#[pyfunction]
#[pyo3(signature = (linear, tonemap="global", mesopic=None, exposure=None, *, w_weights=None,
                    ccm=None, frames=None))]
#[allow(clippy::too_many_arguments)]
fn display<'py>(
    py: Python<'py>,
    linear: &Bound<'py, PyAny>,
    tonemap: &str,
    mesopic: Option<&Bound<'py, PyAny>>,
    exposure: Option<f32>,
    w_weights: Option<&Bound<'py, PyAny>>,
    ccm: Option<&Bound<'py, PyAny>>,
    frames: Option<f64>,
) -> PyResult<Bound<'py, PyArray3<u8>>> {
    let image = linear_image("linear", linear)?;
    let w = match w_weights.filter(|o| !o.is_none()) {
        Some(o) => w_weights_arg(o)?,
        None => [1.0, 1.0, 1.0],
    };
    let options = render_options(tonemap, mesopic_arg(mesopic)?, frames, exposure, w, ccm)?;
    let out = compute(py, || {
        render_srgb8(image.view(), &options).map_err(|e| lib_err("", e))
    })?;
    Ok(out.into_pyarray(py))
}

fn eval_options(border: i64, normalize_percentile: f64) -> PyResult<EvalOptions> {
    Ok(EvalOptions {
        border: index_arg("border", Some(border))?.unwrap_or(0),
        normalize_percentile: (normalize_percentile > 0.0).then_some(normalize_percentile),
    })
}

fn eval_pair(a: &Bound<'_, PyAny>, b: &Bound<'_, PyAny>) -> PyResult<(Array3<f32>, Array3<f32>)> {
    let est = linear_image("estimate", a)?;
    let truth = linear_image("truth", b)?;
    if est.dim() != truth.dim() {
        return Err(PyValueError::new_err(format!(
            "estimate has shape {:?} but truth has shape {:?}",
            est.dim(),
            truth.dim()
        )));
    }
    Ok((est, truth))
}

/// Scores `estimate` against `truth` as `quantacolor eval` does (paper §6): crop `border`,
/// scale both so the truth's `normalize_percentile` is 1 (0 = no scaling), clip to [0, 1].
/// Returns psnr_linear, ssim_linear, psnr_srgb, ssim_srgb (and lpips_srgb with `lpips=True`).
#[pyfunction]
#[pyo3(signature = (estimate, truth, border=0, normalize_percentile=99.5, lpips=false))]
fn evaluate_images<'py>(
    py: Python<'py>,
    estimate: &Bound<'py, PyAny>,
    truth: &Bound<'py, PyAny>,
    border: i64,
    normalize_percentile: f64,
    lpips: bool,
) -> PyResult<Bound<'py, PyDict>> {
    let (est, tru) = eval_pair(estimate, truth)?;
    let opts = eval_options(border, normalize_percentile)?;
    let (scores, l) = compute(py, || {
        let s = evaluate(est.view(), tru.view(), &opts).map_err(|e| lib_err("", e))?;
        let l = if lpips {
            Some(evaluate_lpips(est.view(), tru.view(), &opts).map_err(|e| lib_err("", e))?)
        } else {
            None
        };
        Ok((s, l))
    })?;
    let d = PyDict::new(py);
    d.set_item("psnr_linear", scores.psnr_linear)?;
    d.set_item("ssim_linear", scores.ssim_linear)?;
    d.set_item("psnr_srgb", scores.psnr_srgb)?;
    d.set_item("ssim_srgb", scores.ssim_srgb)?;
    if let Some(l) = l {
        d.set_item("lpips_srgb", l)?;
    }
    Ok(d)
}

/// Simulates a capture (`quantacolor simulate`, same names and defaults): `size` is
/// (width, height). Writes the capture directory to `out` when given. Returns a Capture with
/// ground truth.
#[pyfunction]
#[pyo3(signature = (scene="builtin:chart", motion="handheld", frames=512, flux=0.1,
                    cfa="rgbw-75-regular", sensor="spad", seed=1, size=(496, 254), *,
                    cfa_seed=0, hot_fraction=0.02, reference_frame=None, out=None,
                    progress=None))]
#[allow(clippy::too_many_arguments)]
fn simulate<'py>(
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

/// Native part of the `quantacolor` Python package.
#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyCapture>()?;
    m.add_function(wrap_pyfunction!(reconstruct, m)?)?;
    m.add_function(wrap_pyfunction!(reconstruct_dir, m)?)?;
    m.add_function(wrap_pyfunction!(align, m)?)?;
    m.add_function(wrap_pyfunction!(denoise, m)?)?;
    m.add_function(wrap_pyfunction!(display, m)?)?;
    m.add_function(wrap_pyfunction!(evaluate_images, m)?)?;
    m.add_function(wrap_pyfunction!(simulate, m)?)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add(
        "RECONSTRUCTION_FILES",
        quantacolor::output::RECONSTRUCTION_FILES.to_vec(),
    )?;
    Ok(())
}
