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

/// A colour single-photon capture (paper §3, Eq. 1–4): T binary frames, the colour filter
/// array in front of them and the metadata that turns detection counts into flux.
///
/// Not constructed directly: open a capture directory with ``Capture.open(path)``, wrap
/// numpy arrays with ``Capture.from_arrays(...)``, or simulate one with
/// ``quantacolor.simulate(...)``. Immutable; the frames of an opened directory stay
/// memory-mapped. Linear images made from it are λ, mean photon detections per binary frame
/// of an R, G or B pixel, dark counts removed (docs/capture-format.md).
///
/// Attributes
/// ----------
/// frames : numpy.ndarray
///     Bit-packed frames, uint8 (T, H, ceil(W/8)), MSB first (a copy).
/// frame_count : int
///     Number of binary frames T.
/// height : int
///     Height H, pixels.
/// width : int
///     Width W, pixels.
/// cfa : numpy.ndarray
///     Colour filter array, uint8 (H, W): 0=R 1=G 2=B 3=W.
/// ground_truth : numpy.ndarray or None
///     float32 (H, W, 3) true λ of simulated captures, detections per frame.
/// hot_pixels : numpy.ndarray or None
///     bool (H, W) mask, True = hot or dead.
/// exposure_s : float
///     Exposure of one binary frame, seconds.
/// dark_count_rate_hz : float
///     Mean dark count rate of a pixel, counts per second.
/// w_weights : (float, float, float)
///     (wR, wG, wB) of W = wR·R + wG·G + wB·B.
/// reference_frame : int
///     Frame the reconstruction is registered to.
#[pyclass(module = "quantacolor", name = "Capture", frozen)]
pub(crate) struct PyCapture {
    pub(crate) inner: Arc<quantacolor::Capture>,
    pub(crate) ground_truth: Option<Array3<f32>>,
}

#[pymethods]
impl PyCapture {
    /// Opens and validates a capture directory (paper §3; docs/capture-format.md).
    ///
    /// ``frames.npy`` is memory-mapped, not read into memory; ``ground_truth.npy`` beside it
    /// is read too.
    ///
    /// Parameters
    /// ----------
    /// path : path
    ///     Directory holding ``frames.npy``, ``cfa.npy`` or ``cfa.png`` and ``capture.toml``
    ///     (as ``quantacolor simulate`` or ``quantacolor convert`` write it).
    /// detect_hot_pixels : bool
    ///     Without a hot-pixel mask in the capture, detect one from its frames, as
    ///     ``quantacolor reconstruct`` does (supplement §1.4). Default True.
    ///
    /// Returns
    /// -------
    /// Capture
    ///     With ``ground_truth`` when the directory holds ``ground_truth.npy``.
    ///
    /// Raises
    /// ------
    /// ValueError
    ///     A malformed file or key (the message names the file and the key).
    /// OSError
    ///     A missing directory or file, or one that cannot be read (the message names it).
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

    /// Wraps numpy arrays as a capture (paper §3, Eq. 1–4).
    ///
    /// The arrays are copied (frames packed if given unpacked); nothing is written to disk.
    ///
    /// Parameters
    /// ----------
    /// frames : numpy.ndarray
    ///     uint8 (T, H, ceil(W/8)) bit-packed along the width, MSB first
    ///     (``np.packbits(bits, axis=-1)``), or bool / uint8 0 or 1 (T, H, W) unpacked.
    /// cfa : numpy.ndarray
    ///     uint8 (H, W) colour filter codes: 0=R 1=G 2=B 3=W.
    /// exposure_s : float
    ///     Exposure of one binary frame, seconds, > 0.
    /// dark_count_rate_hz : float
    ///     Mean dark count rate of a pixel, counts per second, >= 0 (default 0).
    /// w_weights : (float, float, float), optional
    ///     (wR, wG, wB) of W = wR·R + wG·G + wB·B, each >= 0, not all 0 (default
    ///     (1, 1, 1)).
    /// hot_pixels : numpy.ndarray, optional
    ///     bool (H, W) mask, True = hot or dead (default: none, and none is detected).
    /// reference_frame : int, optional
    ///     Frame the reconstruction is registered to, 0 <= r < T (default: T // 2).
    /// ground_truth : numpy.ndarray, optional
    ///     float32 (H, W, 3) true λ, detections per frame, for scoring (default: none).
    ///
    /// Returns
    /// -------
    /// Capture
    ///
    /// Raises
    /// ------
    /// TypeError
    ///     An array of the wrong dtype (the message names it).
    /// ValueError
    ///     Shapes that disagree with ``cfa``, values out of range (the message names the
    ///     argument).
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

    /// Bit-packed frames, uint8 (T, H, ceil(W/8)), MSB first: pixel x of a row is bit
    /// 7 - x % 8 of byte x // 8 (a copy). Multi-bit captures (a conventional sensor's uint16
    /// frames) raise ValueError.
    #[getter]
    fn frames<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray3<u8>>> {
        if self.inner.frames.is_multibit() {
            return Err(PyValueError::new_err(
                "this capture holds multi-bit (uint16) frames; read frames.npy with numpy",
            ));
        }
        Ok(self.inner.frames.to_packed().into_pyarray(py))
    }

    /// Number of binary frames T (frames).
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

    /// Linear ground truth of simulated captures, float32 (H, W, 3): the true λ of an R, G
    /// and B filter at every pixel, mean photon detections per binary frame, in the reference
    /// frame's coordinates; None otherwise.
    #[getter]
    fn ground_truth<'py>(&self, py: Python<'py>) -> Option<Bound<'py, PyArray3<f32>>> {
        self.ground_truth.clone().map(|g| g.into_pyarray(py))
    }

    /// Hot-pixel mask, bool (H, W), True = hot or dead; None without one.
    #[getter]
    fn hot_pixels<'py>(&self, py: Python<'py>) -> Option<Bound<'py, PyArray2<bool>>> {
        self.inner.hot_pixels.clone().map(|m| m.into_pyarray(py))
    }

    /// Exposure of one binary frame, seconds.
    #[getter]
    fn exposure_s(&self) -> f64 {
        self.inner.meta.exposure_s
    }

    /// Mean dark count rate of a pixel, counts per second (Hz).
    #[getter]
    fn dark_count_rate_hz(&self) -> f64 {
        self.inner.meta.dark_count_rate_hz
    }

    /// (wR, wG, wB) of W = wR·R + wG·G + wB·B: how a W pixel's λ sums the R, G and B λ.
    #[getter]
    fn w_weights(&self) -> (f64, f64, f64) {
        let w = self.inner.meta.w_weights;
        (w[0], w[1], w[2])
    }

    /// The reference frame (a frame index): the capture's, else T // 2.
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
