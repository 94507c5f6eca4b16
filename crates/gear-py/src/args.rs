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

/// The numpy element types the bindings take, with their dtype names (for messages).
pub trait Dtype: numpy::Element {
    const NAME: &'static str;
}

impl Dtype for f32 {
    const NAME: &'static str = "float32";
}

impl Dtype for f64 {
    const NAME: &'static str = "float64";
}

impl Dtype for i64 {
    const NAME: &'static str = "int64";
}

impl Dtype for bool {
    const NAME: &'static str = "bool";
}

/// Whether `obj` is an array of the element type `T` (by its dtype's name).
pub fn has_dtype<T: Dtype>(obj: &Bound<'_, PyAny>) -> bool {
    obj.getattr("dtype").is_ok_and(|d| d.to_string() == T::NAME)
}

/// A read-only view of `obj` as a C-contiguous numpy array of `T` with the expected `shape`,
/// or an error naming the argument `name`.
pub fn array<'py, T: Dtype>(
    obj: &Bound<'py, PyAny>,
    name: &str,
    shape: &[Dim],
) -> PyResult<PyReadonlyArrayDyn<'py, T>> {
    let dtype = T::NAME;
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
