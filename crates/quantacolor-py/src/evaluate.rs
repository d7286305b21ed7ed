//! `evaluate_images`: PSNR / SSIM (and LPIPS) of an estimate against ground truth, as
//! `quantacolor eval` (paper §6).

#![forbid(unsafe_code)]

use crate::args::{index_arg, linear_image};
use crate::errors::{compute, lib_err};
use ndarray::Array3;
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;
use quantacolor::metrics::{evaluate, evaluate_lpips, EvalOptions};

/// The evaluation protocol of `evaluate_images` (`border`, `normalize_percentile`; 0 = none).
fn eval_options(border: i64, normalize_percentile: f64) -> PyResult<EvalOptions> {
    Ok(EvalOptions {
        border: index_arg("border", Some(border))?.unwrap_or(0),
        normalize_percentile: (normalize_percentile > 0.0).then_some(normalize_percentile),
    })
}

/// `estimate` and `truth` as linear images of the same shape.
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

/// Scores an estimate against ground truth (paper §6, Table 2; ``quantacolor eval``); the
/// native function behind ``quantacolor.evaluate``, which documents it in full.
///
/// Parameters
/// ----------
/// estimate, truth : numpy.ndarray
///     Linear RGB (H, W, 3) of the same shape.
/// border : int
///     Pixels cropped from every side, >= 0 (default 0).
/// normalize_percentile : float
///     Percentile of ``truth`` scaled to 1 before clipping to [0, 1], in percent; 0 = no
///     scaling (default 99.5).
/// lpips : bool
///     Also compute LPIPS (default False).
///
/// Returns
/// -------
/// dict
///     ``psnr_linear``, ``ssim_linear``, ``psnr_srgb``, ``ssim_srgb`` (PSNR in dB), and
///     ``lpips_srgb`` with ``lpips=True``.
///
/// Raises
/// ------
/// TypeError, ValueError
///     A bad argument or shapes that differ (the message names it).
#[pyfunction]
#[pyo3(signature = (estimate, truth, border=0, normalize_percentile=99.5, lpips=false))]
pub(crate) fn evaluate_images<'py>(
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
