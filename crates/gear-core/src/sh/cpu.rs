//! The op on the CPU in f32, Gaussians in chunks over the rasterizer's thread pool
//! (`GEAR_THREADS`); each Gaussian is independent, so results do not depend on the threads.

use rayon::prelude::*;

use super::basis::{backward_one, forward_one};
use super::{coefficient_count, ShGradients, ShInput, CHANNELS};
use crate::error::Result;
use crate::splat::cpu::global_pool;

/// Gaussians per parallel task: enough work to outweigh rayon's scheduling.
const CHUNK: usize = 1024;

/// `rgb` [N, 3] of `input`.
pub fn forward(input: &ShInput<'_, f32>) -> Result<Vec<f32>> {
    input.validate()?;
    let k = coefficient_count(input.degree);
    let stride = k * CHANNELS;
    let mut rgb = vec![0.0f32; input.dirs.len()];
    global_pool()?.install(|| {
        rgb.par_chunks_mut(CHUNK * CHANNELS)
            .enumerate()
            .for_each(|(c, block)| {
                for (r, out) in block.chunks_exact_mut(CHANNELS).enumerate() {
                    let i = c * CHUNK + r;
                    let coeffs = &input.coeffs[i * stride..(i + 1) * stride];
                    forward_one(&input.dirs[3 * i..3 * i + 3], coeffs, k, out);
                }
            });
    });
    Ok(rgb)
}

/// Gradients of a loss with respect to `input`, given its gradient `grad_rgb` [N, 3].
pub fn backward(input: &ShInput<'_, f32>, grad_rgb: &[f32]) -> Result<ShGradients<f32>> {
    input.validate()?;
    input.validate_grad(grad_rgb)?;
    let k = coefficient_count(input.degree);
    let stride = k * CHANNELS;
    let mut grads = ShGradients {
        coeffs: vec![0.0f32; input.coeffs.len()],
        dirs: vec![0.0f32; input.dirs.len()],
    };
    global_pool()?.install(|| {
        grads
            .coeffs
            .par_chunks_mut(CHUNK * stride)
            .zip(grads.dirs.par_chunks_mut(CHUNK * 3))
            .enumerate()
            .for_each(|(c, (coeff_block, dir_block))| {
                let rows = coeff_block
                    .chunks_exact_mut(stride)
                    .zip(dir_block.chunks_exact_mut(3));
                for (r, (grad_coeffs, grad_dir)) in rows.enumerate() {
                    let i = c * CHUNK + r;
                    backward_one(
                        &input.dirs[3 * i..3 * i + 3],
                        &input.coeffs[i * stride..(i + 1) * stride],
                        k,
                        &grad_rgb[3 * i..3 * i + 3],
                        grad_coeffs,
                        grad_dir,
                    );
                }
            });
    });
    Ok(grads)
}
