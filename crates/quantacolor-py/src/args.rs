//! Python arguments converted to library types: numpy arrays (CFA, frames, masks, linear
//! images), weights, indices, parsed names and `config=` dicts. Bad input raises `TypeError`
//! or `ValueError` naming the argument.

#![forbid(unsafe_code)]

use crate::errors::lib_err;
use ndarray::{Array2, Array3};
use numpy::{
    dtype, PyArray2, PyArray3, PyArrayDescrMethods, PyArrayMethods, PyUntypedArray,
    PyUntypedArrayMethods,
};
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyBool, PyDict, PyFloat, PyInt, PyList, PyString, PyTuple};
use quantacolor::Cfa;

pub(crate) fn type_name(obj: &Bound<'_, PyAny>) -> String {
    obj.get_type()
        .name()
        .map(|n| n.to_string())
        .unwrap_or_else(|_| "?".into())
}

/// The `cfa` argument: uint8 (H, W), codes 0=R 1=G 2=B 3=W.
pub(crate) fn cfa_arg(py: Python<'_>, cfa: &Bound<'_, PyAny>) -> PyResult<Cfa> {
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
pub(crate) fn packed_frames_arg(
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
pub(crate) fn hot_pixels_arg(py: Python<'_>, obj: &Bound<'_, PyAny>) -> PyResult<Array2<bool>> {
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
pub(crate) fn ground_truth_arg(
    obj: &Bound<'_, PyAny>,
    h: usize,
    w: usize,
) -> PyResult<Array3<f32>> {
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
pub(crate) fn linear_image(arg: &str, obj: &Bound<'_, PyAny>) -> PyResult<Array3<f32>> {
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
pub(crate) fn w_weights_arg(obj: &Bound<'_, PyAny>) -> PyResult<[f64; 3]> {
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
pub(crate) fn index_arg(arg: &str, value: Option<i64>) -> PyResult<Option<usize>> {
    value
        .map(|v| {
            usize::try_from(v)
                .map_err(|_| PyValueError::new_err(format!("{arg} must be >= 0, got {v}")))
        })
        .transpose()
}

pub(crate) fn parse_arg<T: std::str::FromStr<Err = quantacolor::Error>>(
    arg: &str,
    s: &str,
) -> PyResult<T> {
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
pub(crate) fn config_arg<T: serde::de::DeserializeOwned + Default>(
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
