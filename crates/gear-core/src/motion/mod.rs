//! Deformation of Gaussians by a soft blend of rigid part motions: each Gaussian's K part
//! motions (unit dual quaternions) are sign-aligned with its heaviest part, mixed by its
//! weights and normalised (linear dual-quaternion blending); the result moves its mean and
//! turns its rotation. Forward and backward, to the means, rotations, weights and (when the
//! motions train) the motions themselves, in f32 for training and f64 for gradient checks.
//!
//! One pass per Gaussian replaces the chain of [N, K] tensor operations of the reference
//! (`gear.kinematics.deform`), which costs an E-step tens of milliseconds at 90k Gaussians.
//! In f32 eight Gaussians run at once, one per SIMD lane (`chunk.rs`; the maths is written once
//! over the lane type, `lane.rs`). Gaussians run in fixed chunks on the rasterizer's thread
//! pool; the motions' gradients are summed per chunk, then over the chunks in order, so every
//! result is bit-identical for any thread count.

mod blend;
mod chunk;
mod lane;
mod quat;

#[cfg(test)]
mod tests;

use num_traits::Float;
use rayon::prelude::*;

use self::chunk::{Chunks, Rows};
use crate::error::{check_finite, invalid, Result};
use crate::splat::cpu::global_pool;

/// The element types the native ops run in.
pub trait Real: Float + Send + Sync + Into<f64> {}
impl Real for f32 {}
impl Real for f64 {}

/// The element types the deformation runs in: f32 eight Gaussians at a time (SIMD lanes), f64
/// one at a time.
pub trait Blendable: Real + Chunks {}
impl Blendable for f32 {}
impl Blendable for f64 {}

/// Gaussians per task: a chunk is ~0.1 ms of work, and inputs of one chunk stay on the calling
/// thread (handing them to the pool costs more than they do).
const CHUNK: usize = 4096;

/// The op's inputs, flat and row-major: `means` [N, 3], `quats` [N, 4], `weights` [N, K],
/// and the K part motions `qr`, `qd` [K, 4] (rotation and dual halves).
#[derive(Debug, Clone, Copy)]
pub struct DeformInput<'a, T> {
    pub means: &'a [T],
    pub quats: &'a [T],
    pub weights: &'a [T],
    pub qr: &'a [T],
    pub qd: &'a [T],
    /// `weights` holds part logits: each Gaussian's weights are their softmax, and the
    /// backward's `weights` gradient is the logits'. (A softmax over K = 2 columns costs
    /// torch more than this whole op: its kernel is slow along a short last dimension.)
    pub softmax: bool,
    /// With `softmax`, optionally the weights the forward returned for these logits
    /// ([`Deformed::weights`]): the backward reads them instead of computing them again.
    pub softmax_weights: Option<&'a [T]>,
}

/// Deformed means [N, 3] and rotations [N, 4].
#[derive(Debug, Clone, PartialEq)]
pub struct Deformed<T> {
    pub means: Vec<T>,
    pub quats: Vec<T>,
    /// With `softmax`, each Gaussian's weights [N, K] (the softmax of its logits), for the
    /// backward's [`DeformInput::softmax_weights`]; empty otherwise.
    pub weights: Vec<T>,
}

/// Gradients shaped like the inputs; `qr`, `qd` are empty when the motions are held.
#[derive(Debug, Clone, PartialEq)]
pub struct DeformGradients<T> {
    pub means: Vec<T>,
    pub quats: Vec<T>,
    pub weights: Vec<T>,
    pub qr: Vec<T>,
    pub qd: Vec<T>,
}

impl<T> DeformInput<'_, T> {
    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.means.len() / 3
    }

    pub fn is_empty(&self) -> bool {
        self.means.is_empty()
    }

    /// Number of parts.
    pub fn parts(&self) -> usize {
        self.qr.len() / 4
    }
}

impl<T: Real> DeformInput<'_, T> {
    /// Checks the array lengths against each other and that every value is finite.
    pub fn validate(&self) -> Result<()> {
        let k = self.parts();
        if k == 0 || self.qr.len() != 4 * k || self.qd.len() != 4 * k {
            return Err(invalid(format!(
                "deform: qr and qd must both hold K x 4 values with K >= 1, got {} and {}",
                self.qr.len(),
                self.qd.len()
            )));
        }
        let n = self.len();
        let expected = [
            ("means", self.means.len(), 3 * n),
            ("quats", self.quats.len(), 4 * n),
            ("weights", self.weights.len(), k * n),
        ];
        let given = self.softmax_weights.map(|w| w.len());
        if given.is_some_and(|len| !self.softmax || len != k * n) {
            return Err(invalid(format!(
                "deform: softmax_weights must come with softmax and hold {} values, got {}",
                k * n,
                given.unwrap_or(0)
            )));
        }
        if let Some((name, got, want)) = expected.iter().find(|(_, got, want)| got != want) {
            return Err(invalid(format!(
                "deform: {name} must hold {want} values for {n} Gaussians and {k} parts, got {got}"
            )));
        }
        for (name, values) in [
            ("means", self.means),
            ("quats", self.quats),
            ("weights", self.weights),
            ("qr", self.qr),
            ("qd", self.qd),
        ] {
            check_finite(&format!("deform {name}"), values)?;
        }
        Ok(())
    }
}

/// Runs `work` over the chunks of `out`'s rows (in the pool when there is more than one) and
/// returns its results in chunk order.
fn in_chunks<T: Send, R: Send>(
    n: usize,
    out: Rows<'_, T>,
    work: impl Fn(std::ops::Range<usize>, Rows<'_, T>) -> R + Sync,
) -> Result<Vec<R>> {
    let runs = out.split(n, CHUNK);
    if runs.len() <= 1 {
        return Ok(runs.into_iter().map(|(r, rows)| work(r, rows)).collect());
    }
    let pool = global_pool()?;
    Ok(pool.install(|| {
        runs.into_par_iter()
            .map(|(r, rows)| work(r, rows))
            .collect()
    }))
}

/// The deformed means and rotations of `input`.
pub fn forward<T: Blendable>(input: &DeformInput<'_, T>) -> Result<Deformed<T>> {
    input.validate()?;
    let weights = if input.softmax {
        input.weights.len()
    } else {
        0
    };
    let mut out = Deformed {
        means: vec![T::zero(); input.means.len()],
        quats: vec![T::zero(); input.quats.len()],
        weights: vec![T::zero(); weights],
    };
    let rows = Rows {
        means: &mut out.means,
        quats: &mut out.quats,
        weights: &mut out.weights,
    };
    in_chunks(input.len(), rows, |range, rows| {
        T::forward_chunk(input, range, rows)
    })?;
    Ok(out)
}

/// Gradients of a loss with respect to `input`, given its gradients `grad_means` [N, 3] and
/// `grad_quats` [N, 4] with respect to the outputs; the motions' only if `motion_grads`.
pub fn backward<T: Blendable>(
    input: &DeformInput<'_, T>,
    grad_means: &[T],
    grad_quats: &[T],
    motion_grads: bool,
) -> Result<DeformGradients<T>> {
    input.validate()?;
    if grad_means.len() != input.means.len() || grad_quats.len() != input.quats.len() {
        return Err(invalid(format!(
            "deform: the output gradients must hold N x 3 = {} and N x 4 = {} values, got {} and {}",
            input.means.len(),
            input.quats.len(),
            grad_means.len(),
            grad_quats.len()
        )));
    }
    check_finite("deform grad_means", grad_means)?;
    check_finite("deform grad_quats", grad_quats)?;
    let k = input.parts();
    let mut out = DeformGradients {
        means: vec![T::zero(); input.means.len()],
        quats: vec![T::zero(); input.quats.len()],
        weights: vec![T::zero(); input.weights.len()],
        qr: vec![T::zero(); if motion_grads { 4 * k } else { 0 }],
        qd: vec![T::zero(); if motion_grads { 4 * k } else { 0 }],
    };
    let rows = Rows {
        means: &mut out.means,
        quats: &mut out.quats,
        weights: &mut out.weights,
    };
    let chunks = in_chunks(input.len(), rows, |range, rows| {
        T::backward_chunk(input, (grad_means, grad_quats), motion_grads, range, rows)
    })?;
    // Chunk order: the motions' sums do not depend on how the chunks were scheduled.
    for sums in chunks {
        for (p, s) in sums.iter().enumerate() {
            let target = if p < k {
                &mut out.qr[4 * p..4 * p + 4]
            } else {
                &mut out.qd[4 * (p - k)..4 * (p - k) + 4]
            };
            for (t, &v) in target.iter_mut().zip(s) {
                *t = *t + v;
            }
        }
    }
    Ok(out)
}
