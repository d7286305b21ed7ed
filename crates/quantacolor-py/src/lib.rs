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
//!
//! One file per topic: [`args`] (argument conversion), [`errors`], [`progress`], [`capture`]
//! (the `Capture` class), and one per function family: [`reconstruct`] (`reconstruct`,
//! `reconstruct_dir`, `align`), [`denoise`], [`display`], [`evaluate`] (`evaluate_images`),
//! [`simulate`], [`video`] (the steps of `batch.reconstruct_video`).

#![forbid(unsafe_code)]

mod args;
mod capture;
mod denoise;
mod display;
mod errors;
mod evaluate;
mod progress;
mod reconstruct;
mod simulate;
mod video;

use pyo3::prelude::*;

/// Native part of the `quantacolor` Python package.
#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<capture::PyCapture>()?;
    m.add_function(wrap_pyfunction!(reconstruct::reconstruct, m)?)?;
    m.add_function(wrap_pyfunction!(reconstruct::reconstruct_dir, m)?)?;
    m.add_function(wrap_pyfunction!(reconstruct::align, m)?)?;
    m.add_function(wrap_pyfunction!(denoise::denoise, m)?)?;
    m.add_function(wrap_pyfunction!(display::display, m)?)?;
    m.add_function(wrap_pyfunction!(evaluate::evaluate_images, m)?)?;
    m.add_function(wrap_pyfunction!(simulate::simulate, m)?)?;
    m.add_function(wrap_pyfunction!(video::video_prepare, m)?)?;
    m.add_function(wrap_pyfunction!(video::video_parts, m)?)?;
    m.add_function(wrap_pyfunction!(video::video_assemble, m)?)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add(
        "RECONSTRUCTION_FILES",
        quantacolor::output::RECONSTRUCTION_FILES.to_vec(),
    )?;
    Ok(())
}
