//! Progress of a library call forwarded to an optional Python callback.

#![forbid(unsafe_code)]

use crate::args::type_name;
use pyo3::exceptions::PyTypeError;
use pyo3::prelude::*;
use quantacolor::progress::Progress;
use std::sync::Mutex;

/// Forwards progress to a Python callable `callback(stage: str, done: int, total: int)`. The
/// first exception it raises stops further calls and is re-raised when the computation ends.
pub(crate) struct PyProgress {
    callback: Option<Py<PyAny>>,
    state: Mutex<(String, u64, u64)>,
    error: Mutex<Option<PyErr>>,
}

impl PyProgress {
    pub(crate) fn new(callback: Option<Bound<'_, PyAny>>) -> PyResult<Self> {
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
    pub(crate) fn check(self, py: Python<'_>) -> PyResult<()> {
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
