//! The op in f64, one Gaussian after another: what the executors are tested against.

use super::basis::{backward_one, forward_one};
use super::{coefficient_count, ShGradients, ShInput, CHANNELS};
use crate::error::Result;

/// `rgb` [N, 3] of `input`.
pub fn forward(input: &ShInput<'_, f64>) -> Result<Vec<f64>> {
    input.validate()?;
    let k = coefficient_count(input.degree);
    let mut rgb = vec![0.0; input.dirs.len()];
    for (i, out) in rgb.chunks_exact_mut(CHANNELS).enumerate() {
        let coeffs = &input.coeffs[i * k * CHANNELS..(i + 1) * k * CHANNELS];
        forward_one(&input.dirs[3 * i..3 * i + 3], coeffs, k, out);
    }
    Ok(rgb)
}

/// Gradients of a loss with respect to `input`, given its gradient `grad_rgb` [N, 3].
pub fn backward(input: &ShInput<'_, f64>, grad_rgb: &[f64]) -> Result<ShGradients<f64>> {
    input.validate()?;
    input.validate_grad(grad_rgb)?;
    let k = coefficient_count(input.degree);
    let mut grads = ShGradients {
        coeffs: vec![0.0; input.coeffs.len()],
        dirs: vec![0.0; input.dirs.len()],
    };
    let rows = grads
        .coeffs
        .chunks_exact_mut(k * CHANNELS)
        .zip(grads.dirs.chunks_exact_mut(3));
    for (i, (grad_coeffs, grad_dir)) in rows.enumerate() {
        backward_one(
            &input.dirs[3 * i..3 * i + 3],
            &input.coeffs[i * k * CHANNELS..(i + 1) * k * CHANNELS],
            k,
            &grad_rgb[3 * i..3 * i + 3],
            grad_coeffs,
            grad_dir,
        );
    }
    Ok(grads)
}
