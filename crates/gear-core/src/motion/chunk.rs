//! A chunk of Gaussians through the deformation: in f32 eight at a time (one [`F8`] lane per
//! Gaussian, AVX2 code where the CPU has it) and the chunk's last few one at a time; in f64
//! one at a time. A Gaussian's results are the same bits whichever way it runs (the lanes
//! compute the scalar expressions); the motions' gradients are summed per lane, then over the
//! lanes in order, then over the Gaussians run one at a time.

use std::ops::Range;

use super::blend::{backward_one, forward_one, GradientsOne, Motions};
use super::lane::Lane;
use super::quat::Quat;
use super::DeformInput;
use crate::splat::cpu::lanes::{array, with_avx2, LANES};
use crate::splat::cpu::wide::F8;

/// The rows of one chunk's Gaussians in three row-major outputs: deformed means [n, 3],
/// rotations [n, 4] and weights [n, K] (forward: empty without softmax), or their gradients.
pub struct Rows<'a, T> {
    pub means: &'a mut [T],
    pub quats: &'a mut [T],
    pub weights: &'a mut [T],
}

impl<'a, T> Rows<'a, T> {
    /// The rows of `n` Gaussians split into runs of `size`, each with its Gaussians' range.
    pub fn split(self, n: usize, size: usize) -> Vec<(Range<usize>, Rows<'a, T>)> {
        let k = self.weights.len() / n.max(1);
        let mut rest = self;
        let mut runs = Vec::with_capacity(n.div_ceil(size));
        for start in (0..n).step_by(size) {
            let len = size.min(n - start);
            let (means, more_means) = rest.means.split_at_mut(3 * len);
            let (quats, more_quats) = rest.quats.split_at_mut(4 * len);
            let (weights, more_weights) = rest.weights.split_at_mut(k * len);
            runs.push((
                start..start + len,
                Rows {
                    means,
                    quats,
                    weights,
                },
            ));
            rest = Rows {
                means: more_means,
                quats: more_quats,
                weights: more_weights,
            };
        }
        runs
    }
}

/// The motions' gradients summed over a chunk: rotation halves then dual halves, [2K].
pub type MotionSums<T> = Vec<Quat<T>>;

/// The chunk runners of an element type (f32: eight lanes at a time; f64: one).
pub trait Chunks: Sized {
    /// Deforms Gaussians `range` into `out`.
    fn forward_chunk(input: &DeformInput<'_, Self>, range: Range<usize>, out: Rows<Self>);

    /// The gradients of Gaussians `range` into `out`, given `grads`, the gradients to the
    /// outputs (means, rotations) of all N Gaussians; the motion sums are empty unless
    /// `motion_grads`.
    fn backward_chunk(
        input: &DeformInput<'_, Self>,
        grads: (&[Self], &[Self]),
        motion_grads: bool,
        range: Range<usize>,
        out: Rows<Self>,
    ) -> MotionSums<Self>;
}

/// Zeroed sums of the motions' gradients, one quaternion per part's qr and one per its qd
/// (none unless `wanted`).
fn motion_sums<L: Lane>(input: &DeformInput<'_, L::Scalar>, wanted: bool) -> Vec<Quat<L>> {
    vec![[L::zero(); 4]; if wanted { 2 * input.parts() } else { 0 }]
}

impl Chunks for f64 {
    fn forward_chunk(input: &DeformInput<'_, f64>, range: Range<usize>, mut out: Rows<f64>) {
        forward_lanes::<f64>(input, range.clone(), range.start, &mut out);
    }

    fn backward_chunk(
        input: &DeformInput<'_, f64>,
        grads: (&[f64], &[f64]),
        motion_grads: bool,
        range: Range<usize>,
        mut out: Rows<f64>,
    ) -> MotionSums<f64> {
        let mut sums = motion_sums::<f64>(input, motion_grads);
        let wanted = motion_grads.then_some(&mut sums[..]);
        backward_lanes::<f64>(input, grads, (range.clone(), range.start), &mut out, wanted);
        sums
    }
}

impl Chunks for f32 {
    fn forward_chunk(input: &DeformInput<'_, f32>, range: Range<usize>, mut out: Rows<f32>) {
        forward_f32(input, range, &mut out);
    }

    fn backward_chunk(
        input: &DeformInput<'_, f32>,
        grads: (&[f32], &[f32]),
        motion_grads: bool,
        range: Range<usize>,
        mut out: Rows<f32>,
    ) -> MotionSums<f32> {
        let mut sums = motion_sums::<f32>(input, motion_grads);
        backward_f32(input, grads, range, &mut out, &mut sums);
        sums
    }
}

/// The first Gaussian of `range` past its whole groups of eight.
fn tail(range: &Range<usize>) -> usize {
    range.start + range.len() / LANES * LANES
}

with_avx2!(
    /// [`forward_lanes`] over the whole groups of eight, then the rest one at a time.
    fn forward_f32(input: &DeformInput<'_, f32>, range: Range<usize>, out: &mut Rows<f32>) -> () =
        forward_f32_body
);

#[inline(always)]
fn forward_f32_body(input: &DeformInput<'_, f32>, range: Range<usize>, out: &mut Rows<f32>) {
    let rest = tail(&range);
    forward_lanes::<F8>(input, range.start..rest, range.start, out);
    forward_lanes::<f32>(input, rest..range.end, range.start, out);
}

with_avx2!(
    /// [`backward_lanes`] over the whole groups of eight (the motions' sums per lane, added
    /// to `sums` lane by lane), then the rest one at a time.
    fn backward_f32(
        input: &DeformInput<'_, f32>,
        grads: (&[f32], &[f32]),
        range: Range<usize>,
        out: &mut Rows<f32>,
        sums: &mut MotionSums<f32>
    ) -> () = backward_f32_body
);

#[inline(always)]
fn backward_f32_body(
    input: &DeformInput<'_, f32>,
    grads: (&[f32], &[f32]),
    range: Range<usize>,
    out: &mut Rows<f32>,
    sums: &mut MotionSums<f32>,
) {
    let wanted = !sums.is_empty();
    let rest = tail(&range);
    let mut lane_sums = motion_sums::<F8>(input, wanted);
    let lanes = wanted.then_some(&mut lane_sums[..]);
    backward_lanes::<F8>(input, grads, (range.start..rest, range.start), out, lanes);
    for (total, lanes) in sums.iter_mut().zip(&lane_sums) {
        for (t, l) in total.iter_mut().zip(lanes) {
            for v in l.0 {
                *t += v;
            }
        }
    }
    let sums = wanted.then_some(&mut sums[..]);
    backward_lanes::<f32>(input, grads, (rest..range.end, range.start), out, sums);
}

/// Gaussians `first..first + L::WIDTH`'s rows of a row-major [N, D] array, as D lanes.
#[inline(always)]
fn gather<L: Lane, const D: usize>(flat: &[L::Scalar], first: usize) -> [L; D] {
    let rows = &flat[D * first..D * (first + L::WIDTH)];
    array(|c| L::from_fn(|i| rows[D * i + c]))
}

/// Writes `values` (D lanes) as rows `at..at + L::WIDTH` of a row-major [n, D] array.
#[inline(always)]
fn scatter<L: Lane>(flat: &mut [L::Scalar], at: usize, values: &[L]) {
    let d = values.len();
    let rows = &mut flat[d * at..d * (at + L::WIDTH)];
    for i in 0..L::WIDTH {
        for (c, v) in values.iter().enumerate() {
            rows[d * i + c] = v.lane(i);
        }
    }
}

/// Gaussians `first..first + L::WIDTH`'s weights as K lanes in `out`: their rows of
/// `weights`, or with softmax the weights the forward returned, or else the softmax of
/// their logits.
#[inline(always)]
fn weights_of<L: Lane>(input: &DeformInput<'_, L::Scalar>, first: usize, out: &mut [L]) {
    let k = out.len();
    let source = match (input.softmax, input.softmax_weights) {
        (true, Some(given)) => given,
        _ => input.weights,
    };
    let rows = &source[k * first..k * (first + L::WIDTH)];
    for (p, w) in out.iter_mut().enumerate() {
        *w = L::from_fn(|i| rows[k * i + p]);
    }
    if !input.softmax || input.softmax_weights.is_some() {
        return;
    }
    // The largest logit subtracted first: every exponential is at most 1, none overflows.
    let top = out.iter().skip(1).fold(out[0], |m, &v| m.max(v));
    let mut total = L::zero();
    for w in out.iter_mut() {
        *w = (*w - top).exp();
        total = total + *w;
    }
    for w in out.iter_mut() {
        *w = *w / total;
    }
}

/// Turns the gradient with respect to softmax weights `w` into the one with respect to their
/// logits, in place: dL/dl_p = w_p (dL/dw_p - sum_q w_q dL/dw_q).
#[inline(always)]
fn softmax_backward<L: Lane>(w: &[L], grad: &mut [L]) {
    let along = w
        .iter()
        .zip(grad.iter())
        .fold(L::zero(), |s, (&w, &g)| s + w * g);
    for (g, &w) in grad.iter_mut().zip(w) {
        *g = w * (*g - along);
    }
}

/// Deforms Gaussians `range` (a whole number of lanes) into `out`, whose row 0 is Gaussian
/// `base`.
#[inline(always)]
fn forward_lanes<L: Lane>(
    input: &DeformInput<'_, L::Scalar>,
    range: Range<usize>,
    base: usize,
    out: &mut Rows<L::Scalar>,
) {
    let k = input.parts();
    let motions = Motions::<L>::new(input.qr, input.qd);
    let (mut weights, mut signs) = (vec![L::zero(); k], vec![L::zero(); k]);
    for first in range.step_by(L::WIDTH) {
        weights_of(input, first, &mut weights);
        motions.align(&weights, &mut signs);
        let mean = gather::<L, 3>(input.means, first);
        let quat = gather::<L, 4>(input.quats, first);
        let (m, q) = forward_one(&mean, &quat, &weights, &signs, &motions);
        let at = first - base;
        scatter(out.means, at, &m);
        scatter(out.quats, at, &q);
        if input.softmax {
            scatter(out.weights, at, &weights);
        }
    }
}

/// The gradients of Gaussians `range` (a whole number of lanes) into `out`, whose row 0 is
/// Gaussian `base`; the motions' added to `sums` when given.
#[inline(always)]
fn backward_lanes<L: Lane>(
    input: &DeformInput<'_, L::Scalar>,
    (grad_means, grad_quats): (&[L::Scalar], &[L::Scalar]),
    (range, base): (Range<usize>, usize),
    out: &mut Rows<L::Scalar>,
    mut sums: Option<&mut [Quat<L>]>,
) {
    let k = input.parts();
    let motions = Motions::<L>::new(input.qr, input.qd);
    let mut weights = vec![L::zero(); k];
    let mut signs = vec![L::zero(); k];
    let mut grad_weights = vec![L::zero(); k];
    for first in range.step_by(L::WIDTH) {
        weights_of(input, first, &mut weights);
        motions.align(&weights, &mut signs);
        let mean = gather::<L, 3>(input.means, first);
        let quat = gather::<L, 4>(input.quats, first);
        let grad_mean = gather::<L, 3>(grad_means, first);
        let grad_quat = gather::<L, 4>(grad_quats, first);
        let (gm, gq) = backward_one(
            (&mean, &quat),
            (&weights, &signs),
            &motions,
            (&grad_mean, &grad_quat),
            GradientsOne {
                weights: &mut grad_weights,
                motions: sums.as_deref_mut(),
            },
        );
        if input.softmax {
            softmax_backward(&weights, &mut grad_weights);
        }
        let at = first - base;
        scatter(out.means, at, &gm);
        scatter(out.quats, at, &gq);
        scatter(out.weights, at, &grad_weights);
    }
}
