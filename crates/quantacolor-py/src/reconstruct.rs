//! `reconstruct`, `reconstruct_dir` and `align`: the pipeline and its alignment stage on a
//! capture (paper §4), with the options of `quantacolor reconstruct`.

#![forbid(unsafe_code)]

use crate::args::{config_arg, index_arg, parse_arg};
use crate::capture::capture_arg;
use crate::display::{ccm_arg, mesopic_arg};
use crate::errors::{compute, lib_err};
use crate::progress::PyProgress;
use numpy::{IntoPyArray, PyArray3};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;
use quantacolor::denoise::chroma::DenoiseMethod;
use quantacolor::display::{MesopicConfig, RenderOptions, ToneMap};
use quantacolor::pipeline::{Method, ReconstructConfig, ReconstructOverrides};
use std::path::PathBuf;

/// Reconstructs a capture into one linear RGB image (Ma et al. 2023, §4).
///
/// The same result as the CLI's ``quantacolor reconstruct`` ``linear.npy`` for the same inputs
/// and options.
///
/// Parameters
/// ----------
/// capture : Capture
///     From ``Capture.open``, ``Capture.from_arrays`` or ``simulate``.
/// method : {"burst", "naive"}, optional
///     "burst" (default): align, jointly demosaic and merge. "naive": the plain sum of the
///     frames (the paper's Table 2 baseline), not denoised unless ``denoise`` is given.
/// denoise : {"chroma-bm3d", "bm3d", "none"}, optional
///     Default "chroma-bm3d" (BM3D in the W-weighted YCbCr, chroma filtered harder, §4.3).
/// scale : int, optional
///     Output grid scale, 1 (default) to 4 (2 = super-resolution); burst only.
/// reference_frame : int, optional
///     Frame the image is registered to (default: the capture's, else T // 2).
/// config : dict, optional
///     Any keys of ``report.toml``'s ``[config]`` (every stage's settings,
///     docs/pipeline.md); the keyword options override it. Default: the CLI's defaults.
/// sigma_y, sigma_c : float, optional
///     Denoising σ of luma and chroma in the variance-stabilised domain (default: from the
///     merge's noise model).
/// block_size : int, optional
///     Frames per temporal block for alignment (default: from T and the light level).
/// max_sub_block_motion : float, optional
///     Largest camera motion inside one sub-block, px (default 0.35).
/// window : int, optional
///     Naive method: frames centred on the reference frame (default: all).
/// progress : callable, optional
///     Called as ``progress(stage, done, total)`` while stages run (default: none).
///
/// Returns
/// -------
/// numpy.ndarray
///     float32 (H·scale, W·scale, 3): mean photon detections per binary frame of an R, G or B
///     pixel, dark counts removed; never negative.
///
/// Raises
/// ------
/// TypeError
///     An argument of the wrong type.
/// ValueError
///     An option out of range or unknown (the message names it).
#[pyfunction]
#[pyo3(signature = (capture, method=None, denoise=None, scale=None, reference_frame=None,
                    config=None, *, sigma_y=None, sigma_c=None, block_size=None,
                    max_sub_block_motion=None, window=None, progress=None))]
#[expect(
    clippy::too_many_arguments,
    reason = "pyo3: the parameters are the Python keyword arguments"
)]
pub(crate) fn reconstruct<'py>(
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
    let args = ReconstructArgs {
        overrides: OverrideArgs {
            method,
            denoise,
            scale,
            reference_frame,
            sigma_y,
            sigma_c,
            block_size,
            max_sub_block_motion,
            window,
        },
        config,
    };
    reconstruct_capture(py, capture, &args, progress)
}

/// Reconstructs a capture directory into an output directory (paper §4, §7;
/// ``quantacolor reconstruct CAPTURE_DIR --out OUT_DIR``).
///
/// Writes exactly the CLI's files with the same options: ``linear.npy``, ``linear.exr`` and
/// ``preview.png`` byte-identical, ``report.toml`` differing only in timings. The files are
/// staged beside ``out_dir`` and moved into place when complete (``report.toml`` last), so a
/// failed or killed run leaves no partial result.
///
/// Parameters
/// ----------
/// capture_dir : path
///     Capture directory (``frames.npy``, ``cfa.npy`` or ``cfa.png``, ``capture.toml``;
///     docs/capture-format.md). Without a hot-pixel mask in it, one is detected from the
///     frames, as the CLI does.
/// out_dir : path
///     Output directory, created if missing. One that already holds files is refused before
///     any work unless ``overwrite=True`` (the CLI's ``--overwrite``).
/// method : {"burst", "naive"}, optional
///     "burst" (default): align, jointly demosaic and merge. "naive": the plain sum of the
///     frames (the paper's Table 2 baseline), not denoised unless ``denoise`` is given.
/// denoise : {"chroma-bm3d", "bm3d", "none"}, optional
///     Default "chroma-bm3d" (BM3D in the W-weighted YCbCr, chroma filtered harder, §4.3).
/// scale : int, optional
///     Output grid scale, 1 (default) to 4 (2 = super-resolution); burst only.
/// reference_frame : int, optional
///     Frame the image is registered to (default: the capture's, else T // 2).
/// config : dict, optional
///     Any keys of ``report.toml``'s ``[config]`` (every stage's settings,
///     docs/pipeline.md); the keyword options override it. Default: the CLI's defaults.
/// sigma_y, sigma_c : float, optional
///     Denoising σ of luma and chroma in the variance-stabilised domain (default: from the
///     merge's noise model).
/// block_size : int, optional
///     Frames per temporal block for alignment (default: from T and the light level).
/// max_sub_block_motion : float, optional
///     Largest camera motion inside one sub-block, px (default 0.35).
/// window : int, optional
///     Naive method: frames centred on the reference frame (default: all).
/// tonemap : {"global", "mantiuk06", "none"}
///     Tone map of ``preview.png`` (default "global"); ``linear.npy`` is not tone mapped.
/// mesopic : float or "auto", optional
///     Noise-aware low-light view of ``preview.png`` (supplement Eq. 9–10): the offset L0 in
///     decades of detections, or "auto". Default: off.
/// ccm : path or array, optional
///     Colour matrix of ``preview.png``: a ``calibrate-color`` TOML file or a (3, 3) / (3, 4)
///     matrix (paper Fig. 14). Default: none.
/// overwrite : bool
///     Replace the files of a non-empty ``out_dir`` (default False: refuse it). Other files
///     in it are kept.
/// progress : callable, optional
///     Called as ``progress(stage, done, total)`` while stages run (default: none).
///
/// Returns
/// -------
/// dict
///     ``capture`` and ``out`` (the paths given), ``reference_frame``, ``frames_used``,
///     ``height`` and ``width`` (pixels of ``linear.npy``) and ``seconds`` (the stages' time,
///     s).
///
/// Raises
/// ------
/// TypeError
///     An argument of the wrong type.
/// ValueError
///     An option out of range or unknown (the message names it), a malformed capture file
///     (the message names it), or ``out_dir`` already holding files without
///     ``overwrite=True``.
/// OSError
///     A missing capture file, or a file that cannot be read or written (the message names
///     it).
#[pyfunction]
#[pyo3(signature = (capture_dir, out_dir, method=None, denoise=None, scale=None,
                    reference_frame=None, config=None, *, sigma_y=None, sigma_c=None,
                    block_size=None, max_sub_block_motion=None, window=None,
                    tonemap="global", mesopic=None, ccm=None, overwrite=false, progress=None))]
#[expect(
    clippy::too_many_arguments,
    reason = "pyo3: the parameters are the Python keyword arguments"
)]
pub(crate) fn reconstruct_dir<'py>(
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
    overwrite: bool,
    progress: Option<Bound<'py, PyAny>>,
) -> PyResult<Bound<'py, PyDict>> {
    let args = ReconstructDirArgs {
        capture_dir,
        out_dir,
        overrides: OverrideArgs {
            method,
            denoise,
            scale,
            reference_frame,
            sigma_y,
            sigma_c,
            block_size,
            max_sub_block_motion,
            window,
        },
        config,
        tonemap,
        mesopic,
        ccm,
        overwrite,
    };
    reconstruct_capture_dir(py, args, progress)
}

/// The reconstruction options of `reconstruct` and `reconstruct_dir` (Python spellings in
/// errors), as Python passed them.
pub(crate) struct OverrideArgs<'a> {
    pub(crate) method: Option<&'a str>,
    pub(crate) denoise: Option<&'a str>,
    pub(crate) scale: Option<i64>,
    pub(crate) reference_frame: Option<i64>,
    pub(crate) sigma_y: Option<f32>,
    pub(crate) sigma_c: Option<f32>,
    pub(crate) block_size: Option<i64>,
    pub(crate) max_sub_block_motion: Option<f64>,
    pub(crate) window: Option<i64>,
}

impl OverrideArgs<'_> {
    /// The options as the library's overrides, checked in parameter order.
    pub(crate) fn overrides(&self) -> PyResult<ReconstructOverrides> {
        Ok(ReconstructOverrides {
            method: self
                .method
                .map(|m| parse_arg::<Method>("method", m))
                .transpose()?,
            denoise: self
                .denoise
                .map(|d| parse_arg::<DenoiseMethod>("denoise", d))
                .transpose()?,
            scale: match self.scale {
                Some(s) if s < 1 => {
                    return Err(PyValueError::new_err(format!(
                        "scale must be 1, 2, 3 or 4, got {s}"
                    )))
                }
                s => index_arg("scale", s)?,
            },
            reference_frame: index_arg("reference_frame", self.reference_frame)?,
            sigma_y: self.sigma_y,
            sigma_c: self.sigma_c,
            block_size: match self.block_size {
                Some(b) if b < 1 => {
                    return Err(PyValueError::new_err(format!(
                        "block_size must be >= 1, got {b}"
                    )))
                }
                b => index_arg("block_size", b)?,
            },
            max_sub_block_motion: self.max_sub_block_motion,
            window: match self.window {
                Some(w) if w < 1 => {
                    return Err(PyValueError::new_err(format!(
                        "window must be >= 1, got {w}"
                    )))
                }
                w => index_arg("window", w)?,
            },
        })
    }
}

/// The reconstruction config: the `config=` dict (or the defaults) with the overrides applied.
pub(crate) fn reconstruct_config(
    config: Option<&Bound<'_, PyAny>>,
    overrides: &ReconstructOverrides,
) -> PyResult<ReconstructConfig> {
    let mut cfg: ReconstructConfig = config_arg(config)?;
    overrides
        .apply(&mut cfg, &|key| key.to_string())
        .map_err(|e| lib_err("", e))?;
    Ok(cfg)
}

/// The arguments of `reconstruct` but the capture and the progress callback.
struct ReconstructArgs<'a, 'py> {
    overrides: OverrideArgs<'a>,
    config: Option<&'a Bound<'py, PyAny>>,
}

/// `reconstruct`: the capture, then the options, then the callback checked; the library's
/// reconstruction without the GIL.
fn reconstruct_capture<'py>(
    py: Python<'py>,
    capture: &Bound<'py, PyAny>,
    args: &ReconstructArgs<'_, 'py>,
    progress: Option<Bound<'py, PyAny>>,
) -> PyResult<Bound<'py, PyArray3<f32>>> {
    let (capture, _) = capture_arg("capture", capture)?;
    let ov = args.overrides.overrides()?;
    let cfg = reconstruct_config(args.config, &ov)?;
    let sink = PyProgress::new(progress)?;
    let result = compute(py, || {
        quantacolor::pipeline::reconstruct(&capture, &cfg, &sink).map_err(|e| lib_err("", e))
    });
    sink.check(py)?;
    Ok(result?.linear.into_pyarray(py))
}

/// The arguments of `reconstruct_dir` but the progress callback.
struct ReconstructDirArgs<'a, 'py> {
    capture_dir: PathBuf,
    out_dir: PathBuf,
    overrides: OverrideArgs<'a>,
    config: Option<&'a Bound<'py, PyAny>>,
    tonemap: &'a str,
    mesopic: Option<&'a Bound<'py, PyAny>>,
    ccm: Option<&'a Bound<'py, PyAny>>,
    overwrite: bool,
}

/// `reconstruct_dir`: the options checked, then the output directory (refused when it holds
/// files, unless `overwrite`: the CLI's rule), then the capture directory opened,
/// reconstructed and written without the GIL; the summary dict.
fn reconstruct_capture_dir<'py>(
    py: Python<'py>,
    args: ReconstructDirArgs<'_, 'py>,
    progress: Option<Bound<'py, PyAny>>,
) -> PyResult<Bound<'py, PyDict>> {
    let ReconstructDirArgs {
        capture_dir,
        out_dir,
        overrides,
        config,
        tonemap,
        mesopic,
        ccm,
        overwrite,
    } = args;
    let ov = overrides.overrides()?;
    let cfg = reconstruct_config(config, &ov)?;
    let ccm = ccm.filter(|c| !c.is_none()).map(ccm_arg).transpose()?;
    let tonemap = parse_arg::<ToneMap>("tonemap", tonemap)?;
    let mesopic = mesopic_arg(mesopic)?;
    let sink = PyProgress::new(progress)?;
    quantacolor::output::check_out_dir(&out_dir, "out_dir", "pass overwrite=True", overwrite)
        .map_err(|e| lib_err("out_dir", e))?;
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

/// Estimates the motion of a capture as ``reconstruct`` does (paper §4.1; ``quantacolor
/// align``).
///
/// The block alignment of §4.1 (supplement §1.1), then this project's sub-block refinement,
/// fast-motion tracking and photon trajectory, with ``reconstruct``'s settings. Conventions
/// (pixel centres at integers, (dy, dx) order) and how to compare the result with a
/// simulator's ``motion.toml``: docs/motion.md.
///
/// Parameters
/// ----------
/// capture : Capture
///     From ``Capture.open``, ``Capture.from_arrays`` or ``simulate``.
/// reference_frame : int, optional
///     Frame the motion is measured from, 0 <= r < T (default: ``config``'s, else the
///     capture's, else T // 2).
/// block_size : int, optional
///     Frames per temporal block, >= 1 (default: from T and the light level, supplement
///     §1.1).
/// config : dict, optional
///     Keys of ``report.toml``'s ``[config]``; its ``burst`` settings and
///     ``reference_frame`` apply. Default: the CLI's defaults.
/// progress : callable, optional
///     Called as ``progress(stage, done, total)`` while stages run (default: none).
///
/// Returns
/// -------
/// dict
///     ``flow``: float32 (n_blocks, tiles_y, tiles_x, 2), the block alignment's tile flow as
///     (dy, dx) in pixels from the reference frame (``flow.npy``); the keys of ``flow.toml``:
///     ``block_size`` (frames), ``block_start_frames``, ``block_center_frames``,
///     ``tile_size`` and ``tile_stride`` (px), ``tile_centers_y``, ``tile_centers_x`` (px);
///     ``camera``: float64 (T, 2, 3) (``camera.npy``), for every frame t the affine map M_t
///     taking a reference-frame pixel position (y, x, 1) to the same scene point's position
///     in frame t (camera motion only, not moving objects).
///
/// Raises
/// ------
/// TypeError
///     An argument of the wrong type.
/// ValueError
///     ``reference_frame`` outside the capture, ``block_size`` < 1 or a bad ``config`` key
///     (the message names it).
#[pyfunction]
#[pyo3(signature = (capture, reference_frame=None, block_size=None, *, config=None, progress=None))]
pub(crate) fn align<'py>(
    py: Python<'py>,
    capture: &Bound<'py, PyAny>,
    reference_frame: Option<i64>,
    block_size: Option<i64>,
    config: Option<&Bound<'py, PyAny>>,
    progress: Option<Bound<'py, PyAny>>,
) -> PyResult<Bound<'py, PyDict>> {
    let mut config: ReconstructConfig = config_arg(config)?;
    let (capture, _) = capture_arg("capture", capture)?;
    let reference = index_arg("reference_frame", reference_frame)?
        .or(config.reference_frame)
        .unwrap_or_else(|| capture.reference_frame());
    let frames = capture.frames.frame_count();
    if reference >= frames {
        return Err(PyValueError::new_err(format!(
            "reference_frame {reference} is outside the capture's {frames} frames"
        )));
    }
    match block_size {
        Some(b) if b < 1 => {
            return Err(PyValueError::new_err(format!(
                "block_size must be >= 1, got {b}"
            )))
        }
        Some(b) => config.burst.align.blocks.block_size = index_arg("block_size", Some(b))?,
        None => {}
    }
    let sink = PyProgress::new(progress)?;
    let result = compute(py, || {
        quantacolor::burst::estimate_burst_motion(&capture, reference, &config.burst, &sink)
            .map_err(|e| lib_err("", e))
    });
    sink.check(py)?;
    let estimate = result?;
    let camera = estimate.motion.camera_matrices(frames);
    let alignment = estimate.alignment;
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
    d.set_item("camera", camera.into_pyarray(py))?;
    Ok(d)
}
