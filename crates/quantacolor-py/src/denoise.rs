//! `denoise`: chroma-BM3D or colour BM3D of a linear image (paper §4.3).

#![forbid(unsafe_code)]

use crate::args::{config_arg, linear_image, parse_arg, w_weights_arg};
use crate::errors::{compute, lib_err};
use numpy::{IntoPyArray, PyArray3};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use quantacolor::denoise::chroma::{denoise_linear, DenoiseConfig, DenoiseInput, DenoiseMethod};

/// Denoises a linear image (paper §4.3, Fig. 6; supplement §1.5).
///
/// The binomial Anscombe transform (supplement Eq. 7–8) per channel, then BM3D, then the
/// exact unbiased inverse. Without the merge's noise model (which ``reconstruct`` has), σ is
/// estimated from the image unless ``sigma_y`` / ``sigma_c`` are given.
///
/// Parameters
/// ----------
/// linear : numpy.ndarray
///     Linear RGB (H, W, 3) in mean photon detections per binary frame, as ``reconstruct``
///     returns (e.g. with ``denoise="none"``).
/// frames : float
///     Binary frames behind each pixel, >= 1 (it sets the Anscombe transform).
/// method : {"chroma-bm3d", "bm3d", "none"}
///     "chroma-bm3d" (default): BM3D in the W-weighted YCbCr, grouping on luma, chroma
///     filtered harder (§4.3). "bm3d": plain colour BM3D with one σ. "none": no filtering.
/// sigma_y, sigma_c : float, optional
///     σ of luma and chroma in the variance-stabilised domain (``sigma_y`` is the one σ of
///     "bm3d"). Default: estimated from the image.
/// w_weights : (float, float, float), optional
///     W = wR·R + wG·G + wB·B of the capture, the luma weights (default (1, 1, 1)).
/// dark_counts_per_frame : float
///     Mean dark counts of a pixel per binary frame, >= 0 (``dark_count_rate_hz`` ×
///     ``exposure_s``; default 0).
/// config : dict, optional
///     Keys of ``report.toml``'s ``[config.denoise]`` (docs/pipeline.md §13); ``method``,
///     ``sigma_y`` and ``sigma_c`` override it. Default: the CLI's defaults.
///
/// Returns
/// -------
/// numpy.ndarray
///     float32 (H, W, 3), in the units of ``linear``.
///
/// Raises
/// ------
/// TypeError
///     An argument of the wrong type.
/// ValueError
///     A bad shape, ``frames`` < 1, ``dark_counts_per_frame`` < 0, an unknown ``method`` or a
///     bad ``config`` key (the message names it).
#[pyfunction]
#[pyo3(signature = (linear, frames, method="chroma-bm3d", *, sigma_y=None, sigma_c=None,
                    w_weights=None, dark_counts_per_frame=0.0, config=None))]
#[expect(
    clippy::too_many_arguments,
    reason = "pyo3: the parameters are the Python keyword arguments"
)]
pub(crate) fn denoise<'py>(
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
    let args = DenoiseArgs {
        frames,
        method,
        sigma_y,
        sigma_c,
        w_weights,
        dark_counts_per_frame,
        config,
    };
    denoise_image(py, linear, args)
}

/// The arguments of `denoise` but the image, as Python passed them.
struct DenoiseArgs<'a, 'py> {
    frames: f64,
    method: &'a str,
    sigma_y: Option<f32>,
    sigma_c: Option<f32>,
    w_weights: Option<&'a Bound<'py, PyAny>>,
    dark_counts_per_frame: f64,
    config: Option<&'a Bound<'py, PyAny>>,
}

/// `denoise`: the image, then the options checked; the denoising without the GIL.
fn denoise_image<'py>(
    py: Python<'py>,
    linear: &Bound<'py, PyAny>,
    args: DenoiseArgs<'_, 'py>,
) -> PyResult<Bound<'py, PyArray3<f32>>> {
    let DenoiseArgs {
        frames,
        method,
        sigma_y,
        sigma_c,
        w_weights,
        dark_counts_per_frame,
        config,
    } = args;
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
