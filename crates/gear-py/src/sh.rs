//! Bindings of the spherical-harmonic colour op (gear_core::sh): forward and backward on the
//! GPU or the native CPU executor (float32), and the f64 reference pair (float64). The degree
//! follows from the coefficients' shape [N, K, 3], K = (degree + 1)^2.

use gear_core::sh::{self, ShGradients, ShInput, MAX_DEGREE};
use numpy::{Element, PyArray1, PyArrayMethods, PyUntypedArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use crate::args::{array, Dim, Dtype};
use crate::errors::guarded;

type Array<'py> = Bound<'py, PyAny>;

/// The checked arrays of one call, borrowed from numpy.
struct Args<'py, T: Element> {
    dirs: numpy::PyReadonlyArrayDyn<'py, T>,
    coeffs: numpy::PyReadonlyArrayDyn<'py, T>,
    degree: u32,
}

impl<T: Element> Args<'_, T> {
    fn input(&self) -> PyResult<ShInput<'_, T>> {
        Ok(ShInput {
            dirs: self.dirs.as_slice()?,
            coeffs: self.coeffs.as_slice()?,
            degree: self.degree,
        })
    }

    fn n(&self) -> usize {
        self.dirs.shape()[0]
    }
}

fn args<'py, T: Dtype>(dirs: &Array<'py>, coeffs: &Array<'py>) -> PyResult<Args<'py, T>> {
    let dirs = array::<T>(dirs, "dirs", &[Dim::Any("N"), Dim::Fixed(3)])?;
    let n = dirs.shape()[0];
    let coeffs = array::<T>(
        coeffs,
        "coeffs",
        &[Dim::Fixed(n), Dim::Any("K"), Dim::Fixed(3)],
    )?;
    let k = coeffs.shape()[1];
    let degree = (0..=MAX_DEGREE)
        .find(|&d| sh::coefficient_count(d) == k)
        .ok_or_else(|| {
            PyValueError::new_err(format!(
                "argument 'coeffs': K must be (degree + 1)^2 = 1, 4, 9 or 16, got {k}"
            ))
        })?;
    Ok(Args {
        dirs,
        coeffs,
        degree,
    })
}

type Forward = fn(&ShInput<'_, f32>) -> gear_core::Result<Vec<f32>>;

fn executor_forward(backend: &str) -> PyResult<Forward> {
    match backend {
        "cpu" => Ok(sh::cpu::forward),
        "wgpu" => Ok(sh::gpu::forward),
        other => Err(bad_backend(other)),
    }
}

type Backward = fn(&ShInput<'_, f32>, &[f32]) -> gear_core::Result<ShGradients<f32>>;

fn executor_backward(backend: &str) -> PyResult<Backward> {
    match backend {
        "cpu" => Ok(sh::cpu::backward),
        "wgpu" => Ok(sh::gpu::backward),
        other => Err(bad_backend(other)),
    }
}

fn bad_backend(got: &str) -> PyErr {
    PyValueError::new_err(format!(
        "argument 'backend': expected 'cpu' or 'wgpu', got {got:?}"
    ))
}

fn rows<'py, T: Element>(py: Python<'py>, v: Vec<T>, shape: &[usize]) -> PyResult<Array<'py>> {
    Ok(PyArray1::from_vec(py, v).reshape(shape)?.into_any())
}

fn grad_arrays<'py, T: Element>(
    py: Python<'py>,
    g: ShGradients<T>,
    n: usize,
    k: usize,
) -> PyResult<(Array<'py>, Array<'py>)> {
    Ok((rows(py, g.coeffs, &[n, k, 3])?, rows(py, g.dirs, &[n, 3])?))
}

/// rgb [N, 3] = max(sum_k coeffs[:, k] Y_k(dirs / |dirs|) + 0.5, 0) (float32), with the
/// executor `backend` ("cpu" or "wgpu").
#[pyfunction]
fn sh_to_rgb<'py>(
    py: Python<'py>,
    dirs: &Array<'py>,
    coeffs: &Array<'py>,
    backend: &str,
) -> PyResult<Array<'py>> {
    let run = executor_forward(backend)?;
    let a = args::<f32>(dirs, coeffs)?;
    let input = a.input()?;
    let rgb = guarded(py, || run(&input))?;
    rows(py, rgb, &[a.n(), 3])
}

/// Gradients (coeffs [N, K, 3], dirs [N, 3]) of a loss whose gradient with respect to the
/// output of `sh_to_rgb` is `grad_rgb` [N, 3] (float32).
#[pyfunction]
fn sh_to_rgb_backward<'py>(
    py: Python<'py>,
    dirs: &Array<'py>,
    coeffs: &Array<'py>,
    grad_rgb: &Array<'py>,
    backend: &str,
) -> PyResult<(Array<'py>, Array<'py>)> {
    let run = executor_backward(backend)?;
    let a = args::<f32>(dirs, coeffs)?;
    let upstream = array::<f32>(grad_rgb, "grad_rgb", &[Dim::Fixed(a.n()), Dim::Fixed(3)])?;
    let input = a.input()?;
    let upstream = upstream.as_slice()?;
    let g = guarded(py, || run(&input, upstream))?;
    grad_arrays(py, g, a.n(), sh::coefficient_count(a.degree))
}

/// `sh_to_rgb` by the f64 reference (float64 in and out).
#[pyfunction]
fn sh_reference_forward<'py>(
    py: Python<'py>,
    dirs: &Array<'py>,
    coeffs: &Array<'py>,
) -> PyResult<Array<'py>> {
    let a = args::<f64>(dirs, coeffs)?;
    let input = a.input()?;
    let rgb = guarded(py, || sh::reference::forward(&input))?;
    rows(py, rgb, &[a.n(), 3])
}

/// `sh_to_rgb_backward` by the f64 reference (float64 in and out).
#[pyfunction]
fn sh_reference_backward<'py>(
    py: Python<'py>,
    dirs: &Array<'py>,
    coeffs: &Array<'py>,
    grad_rgb: &Array<'py>,
) -> PyResult<(Array<'py>, Array<'py>)> {
    let a = args::<f64>(dirs, coeffs)?;
    let upstream = array::<f64>(grad_rgb, "grad_rgb", &[Dim::Fixed(a.n()), Dim::Fixed(3)])?;
    let input = a.input()?;
    let upstream = upstream.as_slice()?;
    let g = guarded(py, || sh::reference::backward(&input, upstream))?;
    grad_arrays(py, g, a.n(), sh::coefficient_count(a.degree))
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(sh_to_rgb, m)?)?;
    m.add_function(wrap_pyfunction!(sh_to_rgb_backward, m)?)?;
    m.add_function(wrap_pyfunction!(sh_reference_forward, m)?)?;
    m.add_function(wrap_pyfunction!(sh_reference_backward, m)?)?;
    Ok(())
}
