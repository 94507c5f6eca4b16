//! Bindings of the blended-motion deformation (gear_core::motion): forward and backward in
//! float32 (training) or float64 (gradient checks), chosen by the dtype of `means`.

use gear_core::motion::{self, Blendable, DeformInput};
use numpy::{PyArray1, PyArrayMethods, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::prelude::*;

use crate::args::{array, has_dtype, Dim, Dtype};
use crate::errors::guarded;

type Array<'py> = Bound<'py, PyAny>;

/// The checked arrays of one call, borrowed from numpy.
struct Args<'py, T: Dtype> {
    means: PyReadonlyArrayDyn<'py, T>,
    quats: PyReadonlyArrayDyn<'py, T>,
    weights: PyReadonlyArrayDyn<'py, T>,
    qr: PyReadonlyArrayDyn<'py, T>,
    qd: PyReadonlyArrayDyn<'py, T>,
}

impl<'py, T: Dtype + Blendable> Args<'py, T> {
    fn new(arrays: [&Array<'py>; 5]) -> PyResult<Self> {
        let [means, quats, weights, qr, qd] = arrays;
        let means = array::<T>(means, "means", &[Dim::Any("N"), Dim::Fixed(3)])?;
        let n = means.shape()[0];
        let qr = array::<T>(qr, "qr", &[Dim::Any("K"), Dim::Fixed(4)])?;
        let k = qr.shape()[0];
        Ok(Args {
            quats: array::<T>(quats, "quats", &[Dim::Fixed(n), Dim::Fixed(4)])?,
            weights: array::<T>(weights, "weights", &[Dim::Fixed(n), Dim::Fixed(k)])?,
            qd: array::<T>(qd, "qd", &[Dim::Fixed(k), Dim::Fixed(4)])?,
            means,
            qr,
        })
    }

    fn input<'a>(
        &'a self,
        softmax: bool,
        softmax_weights: Option<&'a PyReadonlyArrayDyn<'py, T>>,
    ) -> PyResult<DeformInput<'a, T>> {
        Ok(DeformInput {
            means: self.means.as_slice()?,
            quats: self.quats.as_slice()?,
            weights: self.weights.as_slice()?,
            qr: self.qr.as_slice()?,
            qd: self.qd.as_slice()?,
            softmax,
            softmax_weights: softmax_weights.map(|w| w.as_slice()).transpose()?,
        })
    }
}

fn rows<'py, T: Dtype>(py: Python<'py>, v: Vec<T>, width: usize) -> PyResult<Array<'py>> {
    let n = v.len() / width.max(1);
    Ok(PyArray1::from_vec(py, v).reshape([n, width])?.into_any())
}

type Deformed<'py> = (Array<'py>, Array<'py>, Option<Array<'py>>);

fn forward<'py, T: Dtype + Blendable>(
    py: Python<'py>,
    arrays: [&Array<'py>; 5],
    softmax: bool,
) -> PyResult<Deformed<'py>> {
    let args = Args::<T>::new(arrays)?;
    let k = args.qr.shape()[0];
    let input = args.input(softmax, None)?;
    let out = guarded(py, || motion::forward(&input))?;
    let weights = softmax.then(|| rows(py, out.weights, k)).transpose()?;
    Ok((rows(py, out.means, 3)?, rows(py, out.quats, 4)?, weights))
}

type Gradients<'py> = (
    Array<'py>,
    Array<'py>,
    Array<'py>,
    Option<Array<'py>>,
    Option<Array<'py>>,
);

fn backward<'py, T: Dtype + Blendable>(
    py: Python<'py>,
    arrays: [&Array<'py>; 5],
    grad_means: &Array<'py>,
    grad_quats: &Array<'py>,
    (motion_grads, softmax, softmax_weights): (bool, bool, Option<&Array<'py>>),
) -> PyResult<Gradients<'py>> {
    let args = Args::<T>::new(arrays)?;
    let n = args.means.shape()[0];
    let k = args.qr.shape()[0];
    let gm = array::<T>(grad_means, "grad_means", &[Dim::Fixed(n), Dim::Fixed(3)])?;
    let gq = array::<T>(grad_quats, "grad_quats", &[Dim::Fixed(n), Dim::Fixed(4)])?;
    let given = softmax_weights
        .map(|w| array::<T>(w, "softmax_weights", &[Dim::Fixed(n), Dim::Fixed(k)]))
        .transpose()?;
    let input = args.input(softmax, given.as_ref())?;
    let (gm, gq) = (gm.as_slice()?, gq.as_slice()?);
    let g = guarded(py, || motion::backward(&input, gm, gq, motion_grads))?;
    let motion = |v: Vec<T>| -> PyResult<Option<Array<'py>>> {
        motion_grads.then(|| rows(py, v, 4)).transpose()
    };
    Ok((
        rows(py, g.means, 3)?,
        rows(py, g.quats, 4)?,
        rows(py, g.weights, k)?,
        motion(g.qr)?,
        motion(g.qd)?,
    ))
}

/// (means' [N, 3], quats' [N, 4], softmax weights [N, K] or None): Gaussians moved by the
/// blend of the K part motions `qr`, `qd` [K, 4] with `weights` [N, K] (every array float32,
/// or every one float64); with `softmax`, `weights` are logits whose per-Gaussian softmax
/// gives the weights, and the third output holds them (for `deform_backward`).
#[pyfunction]
#[pyo3(signature = (means, quats, weights, qr, qd, softmax = false))]
fn deform<'py>(
    py: Python<'py>,
    means: &Array<'py>,
    quats: &Array<'py>,
    weights: &Array<'py>,
    qr: &Array<'py>,
    qd: &Array<'py>,
    softmax: bool,
) -> PyResult<Deformed<'py>> {
    let arrays = [means, quats, weights, qr, qd];
    if has_dtype::<f64>(means) {
        forward::<f64>(py, arrays, softmax)
    } else {
        forward::<f32>(py, arrays, softmax)
    }
}

/// Gradients (means, quats, weights, qr, qd) of a loss whose gradients with respect to the
/// outputs of `deform` are `grad_means` [N, 3] and `grad_quats` [N, 4]; qr and qd are None
/// unless `motion_grads`; with `softmax` (as in `deform`) the third is the logits' gradient,
/// and `softmax_weights` may give the weights `deform` returned (not computed again).
#[pyfunction]
#[pyo3(signature = (means, quats, weights, qr, qd, grad_means, grad_quats, motion_grads, softmax = false, softmax_weights = None))]
#[allow(clippy::too_many_arguments)] // the op's five inputs, two upstream gradients, two flags, the weights
fn deform_backward<'py>(
    py: Python<'py>,
    means: &Array<'py>,
    quats: &Array<'py>,
    weights: &Array<'py>,
    qr: &Array<'py>,
    qd: &Array<'py>,
    grad_means: &Array<'py>,
    grad_quats: &Array<'py>,
    motion_grads: bool,
    softmax: bool,
    softmax_weights: Option<&Array<'py>>,
) -> PyResult<Gradients<'py>> {
    let arrays = [means, quats, weights, qr, qd];
    let flags = (motion_grads, softmax, softmax_weights);
    if has_dtype::<f64>(means) {
        backward::<f64>(py, arrays, grad_means, grad_quats, flags)
    } else {
        backward::<f32>(py, arrays, grad_means, grad_quats, flags)
    }
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(deform, m)?)?;
    m.add_function(wrap_pyfunction!(deform_backward, m)?)?;
    Ok(())
}
