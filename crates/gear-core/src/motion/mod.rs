//! Deformation of Gaussians by a soft blend of rigid part motions: each Gaussian's K part
//! motions (unit dual quaternions) are sign-aligned with its heaviest part, mixed by its
//! weights and normalised (linear dual-quaternion blending); the result moves its mean and
//! turns its rotation. Forward and backward, to the means, rotations, weights and (when the
//! motions train) the motions themselves, in f32 for training and f64 for gradient checks.
//!
//! One pass per Gaussian replaces the chain of [N, K] tensor operations of the reference
//! (`gear.kinematics.deform`), which costs an E-step tens of milliseconds at 90k Gaussians.
//! Gaussians run in fixed chunks on the rasterizer's thread pool; the motions' gradients are
//! summed per chunk, then over the chunks in order, so every result is bit-identical for any
//! thread count.

mod blend;
mod quat;

#[cfg(test)]
mod tests;

use num_traits::Float;
use rayon::prelude::*;

use self::blend::{backward_one, forward_one, GradientsOne, Motions};
use crate::error::{check_finite, invalid, Result};
use crate::splat::cpu::global_pool;

/// The element types the op runs in.
pub trait Real: Float + Send + Sync + Into<f64> {}
impl Real for f32 {}
impl Real for f64 {}

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

impl<T: Real> DeformInput<'_, T> {
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

    /// Gaussian `i`'s weights: its row of `weights`, or their softmax (written to `buffer`).
    fn weights_of<'s>(&'s self, i: usize, buffer: &'s mut [T]) -> &'s [T] {
        let k = buffer.len();
        let row = &self.weights[k * i..k * (i + 1)];
        if !self.softmax {
            return row;
        }
        if let Some(given) = self.softmax_weights {
            return &given[k * i..k * (i + 1)];
        }
        // The largest logit subtracted first: every exponential is at most 1, none overflows.
        let top = row.iter().fold(T::neg_infinity(), |m, &v| m.max(v));
        let mut total = T::zero();
        for (w, &v) in buffer.iter_mut().zip(row) {
            *w = (v - top).exp();
            total = total + *w;
        }
        for w in buffer.iter_mut() {
            *w = *w / total;
        }
        buffer
    }

    fn motions(&self) -> Motions<T> {
        let quats = |flat: &[T]| {
            flat.chunks_exact(4)
                .map(|q| [q[0], q[1], q[2], q[3]])
                .collect()
        };
        Motions::new(quats(self.qr), quats(self.qd))
    }
}

/// Turns the gradient with respect to softmax weights `w` into the one with respect to their
/// logits, in place: dL/dl_p = w_p (dL/dw_p - sum_q w_q dL/dw_q).
fn softmax_backward<T: Real>(w: &[T], grad: &mut [T]) {
    let along = w
        .iter()
        .zip(grad.iter())
        .fold(T::zero(), |s, (&w, &g)| s + w * g);
    for (g, &w) in grad.iter_mut().zip(w) {
        *g = w * (*g - along);
    }
}

fn vec3<T: Copy>(v: &[T]) -> [T; 3] {
    [v[0], v[1], v[2]]
}

fn quat4<T: Copy>(v: &[T]) -> [T; 4] {
    [v[0], v[1], v[2], v[3]]
}

/// Runs `work` over the chunks (in the pool when there is more than one) and returns its
/// results in chunk order.
fn in_chunks<R: Send>(
    n: usize,
    work: impl Fn(std::ops::Range<usize>) -> R + Sync,
) -> Result<Vec<R>> {
    let ranges: Vec<_> = (0..n.div_ceil(CHUNK))
        .map(|c| c * CHUNK..((c + 1) * CHUNK).min(n))
        .collect();
    if ranges.len() <= 1 {
        return Ok(ranges.into_iter().map(work).collect());
    }
    Ok(global_pool()?.install(|| ranges.into_par_iter().map(&work).collect()))
}

/// The deformed means and rotations of `input`.
pub fn forward<T: Real>(input: &DeformInput<'_, T>) -> Result<Deformed<T>> {
    input.validate()?;
    let k = input.parts();
    let motions = input.motions();
    let chunks = in_chunks(input.len(), |range| {
        let mut means = Vec::with_capacity(3 * range.len());
        let mut quats = Vec::with_capacity(4 * range.len());
        let mut softmax = Vec::with_capacity(if input.softmax { k * range.len() } else { 0 });
        let mut weights = vec![T::zero(); k];
        for i in range {
            let w = input.weights_of(i, &mut weights);
            let (m, q) = forward_one(
                &vec3(&input.means[3 * i..]),
                &quat4(&input.quats[4 * i..]),
                w,
                &motions,
            );
            means.extend_from_slice(&m);
            quats.extend_from_slice(&q);
            if input.softmax {
                softmax.extend_from_slice(w);
            }
        }
        (means, quats, softmax)
    })?;
    let mut out = Deformed {
        means: Vec::with_capacity(input.means.len()),
        quats: Vec::with_capacity(input.quats.len()),
        weights: Vec::with_capacity(if input.softmax {
            input.weights.len()
        } else {
            0
        }),
    };
    for (means, quats, weights) in chunks {
        out.means.extend_from_slice(&means);
        out.quats.extend_from_slice(&quats);
        out.weights.extend_from_slice(&weights);
    }
    Ok(out)
}

/// Gradients of a loss with respect to `input`, given its gradients `grad_means` [N, 3] and
/// `grad_quats` [N, 4] with respect to the outputs; the motions' only if `motion_grads`.
pub fn backward<T: Real>(
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
    let motions = input.motions();
    let chunks = in_chunks(input.len(), |range| {
        let n = range.len();
        let mut g = DeformGradients {
            means: vec![T::zero(); 3 * n],
            quats: vec![T::zero(); 4 * n],
            weights: vec![T::zero(); k * n],
            qr: vec![],
            qd: vec![],
        };
        let mut sums = vec![[T::zero(); 4]; if motion_grads { 2 * k } else { 0 }];
        let mut weights = vec![T::zero(); k];
        for (r, i) in range.enumerate() {
            let w = input.weights_of(i, &mut weights);
            backward_one(
                &vec3(&input.means[3 * i..]),
                &quat4(&input.quats[4 * i..]),
                w,
                &motions,
                &vec3(&grad_means[3 * i..]),
                &quat4(&grad_quats[4 * i..]),
                GradientsOne {
                    mean: &mut g.means[3 * r..3 * r + 3],
                    quat: &mut g.quats[4 * r..4 * r + 4],
                    weights: &mut g.weights[k * r..k * (r + 1)],
                    motions: motion_grads.then_some(&mut sums[..]),
                },
            );
            if input.softmax {
                softmax_backward(w, &mut g.weights[k * r..k * (r + 1)]);
            }
        }
        (g, sums)
    })?;
    let mut out = DeformGradients {
        means: Vec::with_capacity(input.means.len()),
        quats: Vec::with_capacity(input.quats.len()),
        weights: Vec::with_capacity(input.weights.len()),
        qr: vec![T::zero(); if motion_grads { 4 * k } else { 0 }],
        qd: vec![T::zero(); if motion_grads { 4 * k } else { 0 }],
    };
    // Chunk order: the motions' sums do not depend on how the chunks were scheduled.
    for (g, sums) in chunks {
        out.means.extend_from_slice(&g.means);
        out.quats.extend_from_slice(&g.quats);
        out.weights.extend_from_slice(&g.weights);
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
