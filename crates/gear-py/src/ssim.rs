//! Binding of the SSIM op (gear_core::ssim): the mean SSIM of two [H, W, C] images and its
//! gradient with respect to the first, float32 or float64 by the dtype of `a`.

use gear_core::motion::Real;
use gear_core::ssim::{ssim as mean_ssim, Image};
use numpy::{PyArray1, PyArrayMethods, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::prelude::*;

use crate::args::{array, has_dtype, Dim, Dtype};
use crate::errors::guarded;

type Array<'py> = Bound<'py, PyAny>;

fn image<'a, T: Dtype>(arr: &'a PyReadonlyArrayDyn<'_, T>) -> PyResult<Image<'a, T>> {
    let shape = arr.shape();
    Ok(Image {
        values: arr.as_slice()?,
        height: shape[0],
        width: shape[1],
        channels: shape[2],
    })
}

fn run<'py, T: Dtype + Real>(
    py: Python<'py>,
    a: &Array<'py>,
    b: &Array<'py>,
    want_grad: bool,
) -> PyResult<(f64, Option<Array<'py>>)> {
    let a = array::<T>(a, "a", &[Dim::Any("H"), Dim::Any("W"), Dim::Any("C")])?;
    let shape = [a.shape()[0], a.shape()[1], a.shape()[2]];
    let b = array::<T>(b, "b", &shape.map(Dim::Fixed))?;
    let (ia, ib) = (image(&a)?, image(&b)?);
    let out = guarded(py, || mean_ssim(&ia, &ib, want_grad))?;
    let grad = out
        .grad
        .map(|g| -> PyResult<Array<'py>> {
            Ok(PyArray1::from_vec(py, g).reshape(shape)?.into_any())
        })
        .transpose()?;
    Ok((out.value.into(), grad))
}

/// (value, grad or None): the mean SSIM of the [H, W, C] images `a` and `b` (one dtype) and,
/// if `want_grad`, its gradient with respect to `a`.
#[pyfunction]
fn ssim<'py>(
    py: Python<'py>,
    a: &Array<'py>,
    b: &Array<'py>,
    want_grad: bool,
) -> PyResult<(f64, Option<Array<'py>>)> {
    if has_dtype::<f64>(a) {
        run::<f64>(py, a, b, want_grad)
    } else {
        run::<f32>(py, a, b, want_grad)
    }
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(ssim, m)?)?;
    Ok(())
}
