//! `display`: a linear image rendered to 8-bit sRGB (paper §7), and the render options shared
//! with `reconstruct_dir`'s preview (`mesopic=`, `ccm=`, tone map).

#![forbid(unsafe_code)]

use crate::args::{linear_image, parse_arg, type_name, w_weights_arg};
use crate::errors::{compute, lib_err};
use numpy::{IntoPyArray, PyArray3};
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyString;
use quantacolor::display::{
    render_srgb8, ColorMatrix, MesopicConfig, MesopicOffset, RenderOptions, ToneMap,
};
use std::path::PathBuf;

/// Renders a linear image for display (paper §7; ``quantacolor display``).
///
/// Colour matrix, then the noise-aware low-light view, exposure, tone map and sRGB encoding.
///
/// Parameters
/// ----------
/// linear : numpy.ndarray
///     Linear RGB (H, W, 3), e.g. from ``reconstruct``.
/// tonemap : {"global", "mantiuk06", "none"}
///     Tone map (default "global").
/// mesopic : float or "auto", optional
///     Noise-aware low-light view (supplement Eq. 9–10): the offset L0 in decades of
///     detections, or "auto"; a number needs ``frames``. Default: off.
/// exposure : float, optional
///     Exposure scale (default: automatic).
/// w_weights : (float, float, float), optional
///     W = wR·R + wG·G + wB·B of the capture (default (1, 1, 1)).
/// ccm : path or array, optional
///     Colour matrix: a ``calibrate-color`` TOML file or a (3, 3) / (3, 4) matrix (paper
///     Fig. 14). Default: none.
/// frames : float, optional
///     Binary frames merged into ``linear``, > 0 (for ``mesopic``; default: none).
///
/// Returns
/// -------
/// numpy.ndarray
///     uint8 (H, W, 3) sRGB; ``quantacolor.show`` wraps it for Jupyter.
///
/// Raises
/// ------
/// TypeError, ValueError
///     A bad argument (the message names it).
#[pyfunction]
#[pyo3(signature = (linear, tonemap="global", mesopic=None, exposure=None, *, w_weights=None,
                    ccm=None, frames=None))]
#[expect(
    clippy::too_many_arguments,
    reason = "pyo3: the parameters are the Python keyword arguments"
)]
pub(crate) fn display<'py>(
    py: Python<'py>,
    linear: &Bound<'py, PyAny>,
    tonemap: &str,
    mesopic: Option<&Bound<'py, PyAny>>,
    exposure: Option<f32>,
    w_weights: Option<&Bound<'py, PyAny>>,
    ccm: Option<&Bound<'py, PyAny>>,
    frames: Option<f64>,
) -> PyResult<Bound<'py, PyArray3<u8>>> {
    let args = DisplayArgs {
        tonemap,
        mesopic,
        exposure,
        w_weights,
        ccm,
        frames,
    };
    display_image(py, linear, args)
}

/// The arguments of `display` but the image, as Python passed them.
struct DisplayArgs<'a, 'py> {
    tonemap: &'a str,
    mesopic: Option<&'a Bound<'py, PyAny>>,
    exposure: Option<f32>,
    w_weights: Option<&'a Bound<'py, PyAny>>,
    ccm: Option<&'a Bound<'py, PyAny>>,
    frames: Option<f64>,
}

/// `display`: the image, then the options checked; the rendering without the GIL.
fn display_image<'py>(
    py: Python<'py>,
    linear: &Bound<'py, PyAny>,
    args: DisplayArgs<'_, 'py>,
) -> PyResult<Bound<'py, PyArray3<u8>>> {
    let DisplayArgs {
        tonemap,
        mesopic,
        exposure,
        w_weights,
        ccm,
        frames,
    } = args;
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

/// Render options of `display` / `preview.png`.
pub(crate) fn render_options(
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
pub(crate) fn mesopic_arg(obj: Option<&Bound<'_, PyAny>>) -> PyResult<Option<MesopicOffset>> {
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
pub(crate) fn ccm_arg(obj: &Bound<'_, PyAny>) -> PyResult<ColorMatrix> {
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
