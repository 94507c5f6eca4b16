//! Strict argument checks for numpy inputs: right dtype, shape and C-contiguous layout, or a
//! `TypeError`/`ValueError` that names the argument and what was expected.

use numpy::{PyArrayDyn, PyArrayMethods, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;

/// One expected dimension: a fixed size, or any size (named for the message).
#[derive(Clone, Copy)]
pub enum Dim {
    Fixed(usize),
    Any(&'static str),
}

fn describe(shape: &[Dim]) -> String {
    let parts: Vec<String> = shape
        .iter()
        .map(|d| match d {
            Dim::Fixed(n) => n.to_string(),
            Dim::Any(name) => (*name).to_string(),
        })
        .collect();
    format!("[{}]", parts.join(", "))
}

/// A read-only view of `obj` as a C-contiguous array of `T` with the expected `shape`.
fn typed_array<'py, T: numpy::Element>(
    obj: &Bound<'py, PyAny>,
    name: &str,
    dtype: &str,
    shape: &[Dim],
) -> PyResult<PyReadonlyArrayDyn<'py, T>> {
    let expected = describe(shape);
    let Ok(arr) = obj.cast::<PyArrayDyn<T>>() else {
        let got = obj
            .getattr("dtype")
            .map(|d| d.to_string())
            .unwrap_or_else(|_| obj.get_type().to_string());
        return Err(PyTypeError::new_err(format!(
            "argument '{name}': expected a numpy {dtype} array of shape {expected}, got {got}"
        )));
    };
    let got_shape = arr.shape().to_vec();
    let matches = got_shape.len() == shape.len()
        && shape.iter().zip(&got_shape).all(|(d, &g)| match d {
            Dim::Fixed(n) => *n == g,
            Dim::Any(_) => true,
        });
    if !matches {
        return Err(PyValueError::new_err(format!(
            "argument '{name}': expected shape {expected}, got {got_shape:?}"
        )));
    }
    if !arr.is_c_contiguous() {
        return Err(PyValueError::new_err(format!(
            "argument '{name}': array must be C-contiguous (use numpy.ascontiguousarray)"
        )));
    }
    Ok(arr.readonly())
}

pub fn f32_array<'py>(
    obj: &Bound<'py, PyAny>,
    name: &str,
    shape: &[Dim],
) -> PyResult<PyReadonlyArrayDyn<'py, f32>> {
    typed_array::<f32>(obj, name, "float32", shape)
}

pub fn i64_array<'py>(
    obj: &Bound<'py, PyAny>,
    name: &str,
    shape: &[Dim],
) -> PyResult<PyReadonlyArrayDyn<'py, i64>> {
    typed_array::<i64>(obj, name, "int64", shape)
}

pub fn bool_array<'py>(
    obj: &Bound<'py, PyAny>,
    name: &str,
    shape: &[Dim],
) -> PyResult<PyReadonlyArrayDyn<'py, bool>> {
    typed_array::<bool>(obj, name, "bool", shape)
}

pub fn f64_array<'py>(
    obj: &Bound<'py, PyAny>,
    name: &str,
    shape: &[Dim],
) -> PyResult<PyReadonlyArrayDyn<'py, f64>> {
    typed_array::<f64>(obj, name, "float64", shape)
}
