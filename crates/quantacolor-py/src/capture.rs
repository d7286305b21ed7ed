//! `quantacolor.Capture`: a capture opened from a directory, wrapped from numpy arrays or
//! simulated, and the `capture` argument of the functions.

#![forbid(unsafe_code)]

use crate::args::{
    cfa_arg, ground_truth_arg, hot_pixels_arg, index_arg, packed_frames_arg, type_name,
    w_weights_arg,
};
use crate::errors::{compute, lib_err};
use ndarray::Array3;
use numpy::{IntoPyArray, PyArray2, PyArray3};
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;
use quantacolor::capture::{BinaryFrames, CaptureMeta};
use std::path::PathBuf;
use std::sync::Arc;

/// A colour single-photon capture: T binary frames, the colour filter array and the metadata
/// that turns counts into flux (paper §3, Eq. 2–3). Open a capture directory with
/// `Capture.open(path)`, wrap arrays with `Capture.from_arrays(...)`, or simulate one with
/// `quantacolor.simulate(...)`.
#[pyclass(module = "quantacolor", name = "Capture", frozen)]
pub(crate) struct PyCapture {
    pub(crate) inner: Arc<quantacolor::Capture>,
    pub(crate) ground_truth: Option<Array3<f32>>,
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
    #[expect(
        clippy::too_many_arguments,
        reason = "pyo3: the parameters are the Python keyword arguments"
    )]
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
        let arrays = CaptureArrays {
            frames,
            cfa,
            exposure_s,
            dark_count_rate_hz,
            w_weights,
            hot_pixels,
            reference_frame,
            ground_truth,
        };
        arrays.capture(py)
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

pub(crate) fn capture_arg(
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

/// The arguments of `Capture.from_arrays`, as Python passed them.
struct CaptureArrays<'a, 'py> {
    frames: &'a Bound<'py, PyAny>,
    cfa: &'a Bound<'py, PyAny>,
    exposure_s: f64,
    dark_count_rate_hz: f64,
    w_weights: Option<&'a Bound<'py, PyAny>>,
    hot_pixels: Option<&'a Bound<'py, PyAny>>,
    reference_frame: Option<i64>,
    ground_truth: Option<&'a Bound<'py, PyAny>>,
}

impl CaptureArrays<'_, '_> {
    /// The capture of `Capture.from_arrays`, its arguments checked in order.
    fn capture(self, py: Python<'_>) -> PyResult<PyCapture> {
        let CaptureArrays {
            frames,
            cfa,
            exposure_s,
            dark_count_rate_hz,
            w_weights,
            hot_pixels,
            reference_frame,
            ground_truth,
        } = self;
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
}
