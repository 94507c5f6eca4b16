//! Binding of stage 3's KNN consistency term (gear_core::consistency): its value and gradient
//! in one call, float32 or float64 by the dtype of `logits`.

use gear_core::consistency::knn_consistency as consistency;
use gear_core::motion::Real;
use numpy::{PyArray1, PyArrayMethods, PyUntypedArrayMethods};
use pyo3::prelude::*;

use crate::args::{array, has_dtype, Dim, Dtype};
use crate::errors::guarded;

type Array<'py> = Bound<'py, PyAny>;

fn run<'py, T: Dtype + Real>(
    py: Python<'py>,
    logits: &Array<'py>,
    neighbours: &Array<'py>,
) -> PyResult<(f64, Array<'py>)> {
    let logits = array::<T>(logits, "logits", &[Dim::Any("N"), Dim::Any("K")])?;
    let (n, k) = (logits.shape()[0], logits.shape()[1]);
    let neighbours = array::<i64>(neighbours, "neighbours", &[Dim::Fixed(n), Dim::Any("n")])?;
    let (values, lists) = (logits.as_slice()?, neighbours.as_slice()?);
    let out = guarded(py, || consistency(values, k, lists))?;
    let grad = PyArray1::from_vec(py, out.grad).reshape([n, k])?.into_any();
    Ok((out.loss.into(), grad))
}

/// (loss, grad [N, K]): the mean distance between each row of `logits` [N, K] and the rows
/// its `neighbours` [N, n] (int64; negative = padding) list, and its gradient.
#[pyfunction]
fn knn_consistency<'py>(
    py: Python<'py>,
    logits: &Array<'py>,
    neighbours: &Array<'py>,
) -> PyResult<(f64, Array<'py>)> {
    if has_dtype::<f64>(logits) {
        run::<f64>(py, logits, neighbours)
    } else {
        run::<f32>(py, logits, neighbours)
    }
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(knn_consistency, m)?)?;
    Ok(())
}
