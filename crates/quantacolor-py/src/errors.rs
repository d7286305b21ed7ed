//! Library errors and Rust panics as Python exceptions, and the GIL released around every
//! library call.

#![forbid(unsafe_code)]

use pyo3::exceptions::{PyOSError, PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use std::panic::{catch_unwind, AssertUnwindSafe};

/// A library error as a Python exception, prefixed with `context` (the argument or call).
pub(crate) fn lib_err(context: &str, e: quantacolor::Error) -> PyErr {
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
pub(crate) fn compute<T: Send>(
    py: Python<'_>,
    f: impl FnOnce() -> PyResult<T> + Send,
) -> PyResult<T> {
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
