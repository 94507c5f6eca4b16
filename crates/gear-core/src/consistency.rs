//! Stage 3's KNN consistency term: the mean Euclidean distance between each Gaussian's part
//! logits and those of its listed neighbours, with its gradient, in one pass.
//!
//! The torch form of the same term (`gear.losses.knn_consistency_loss`, the reference the
//! tests compare with) gathers an [N, n, K] tensor, takes norms and scatters the gradient back
//! through an index_add: ~15 ms per E-step at 86k Gaussians on one thread. Here every pair is
//! visited once, in order, on the calling thread, with the rows of the pairs ahead fetched
//! into the cache and the part count a constant where it is a common one (6.5 ms at 96.6k
//! Gaussians, K = 8, 3 neighbours): the sums have one fixed order, so the result is the same on
//! every run. The loss is summed in f64.

use crate::counts::{channels, with_channels};
use crate::error::{check_finite, invalid, Result};
use crate::motion::Real;

/// The term's value and its gradient with respect to the logits ([N, K], row-major).
#[derive(Debug, Clone, PartialEq)]
pub struct Consistency<T> {
    pub loss: T,
    pub grad: Vec<T>,
}

/// Mean over the valid pairs (i, j) of |logits_i - logits_j|, where `neighbours` [N, n]
/// lists j for each i and a negative entry is padding (skipped); the gradient of a pair whose
/// logits agree is zero, not NaN. No valid pair gives a loss of 0 and a zero gradient.
///
/// Errors: `logits` not N x `parts`, `neighbours` not N x n, a non-finite logit, or an index
/// >= N.
pub fn knn_consistency<T: Real>(
    logits: &[T],
    parts: usize,
    neighbours: &[i64],
) -> Result<Consistency<T>> {
    if parts == 0 || !logits.len().is_multiple_of(parts) {
        return Err(invalid(format!(
            "knn consistency: logits must hold N x K values with K >= 1, got {} values for K = {parts}",
            logits.len()
        )));
    }
    let n = logits.len() / parts;
    // (A multiple of 0 is 0 only: no points admit no indices.)
    if !neighbours.len().is_multiple_of(n) {
        return Err(invalid(format!(
            "knn consistency: neighbours must hold N x n indices for N = {n}, got {}",
            neighbours.len()
        )));
    }
    check_finite("knn consistency logits", logits)?;
    if let Some(&bad) = neighbours.iter().find(|&&j| j >= n as i64) {
        return Err(invalid(format!(
            "knn consistency neighbours: index {bad} >= N = {n}"
        )));
    }
    let valid = neighbours.iter().filter(|&&j| j >= 0).count();
    let mut grad = vec![T::zero(); logits.len()];
    if valid == 0 {
        return Ok(Consistency {
            loss: T::zero(),
            grad,
        });
    }
    let scale = T::one() / T::from(valid).expect("a count fits every float type");
    let total = with_channels!(
        parts,
        sum_pairs::<T>(logits, parts, neighbours, scale, &mut grad)
    );
    let loss = T::from(total / valid as f64).expect("a finite mean converts");
    Ok(Consistency { loss, grad })
}

/// The distances of the valid pairs summed (f64, in pair order), and each pair's gradient,
/// `scale` times the unit difference, added to `grad` in pair order. `K` is the part count
/// `parts` when [`with_channels!`] has it as a constant (the per-part loops then unroll), else
/// 0; the sums run in the same order either way.
fn sum_pairs<T: Real, const K: usize>(
    logits: &[T],
    parts: usize,
    neighbours: &[i64],
    scale: T,
    grad: &mut [T],
) -> f64 {
    let parts = channels::<K>(parts);
    let n = logits.len() / parts;
    let per_point = neighbours.len() / n;
    let mut total = 0.0f64;
    let mut diff = vec![T::zero(); parts];
    let diff = &mut diff[..parts];
    for i in 0..n {
        let own = &logits[i * parts..(i + 1) * parts];
        let first = i * per_point;
        for (q, &j) in neighbours[first..first + per_point].iter().enumerate() {
            if let Some(&ahead) = neighbours.get(first + q + PREFETCH_PAIRS) {
                prefetch_row(logits, grad, ahead, parts);
            }
            if j < 0 {
                continue;
            }
            let j = j as usize;
            let other = &logits[j * parts..(j + 1) * parts];
            let mut squared = T::zero();
            for ((d, &a), &b) in diff.iter_mut().zip(own).zip(other) {
                *d = a - b;
                squared = squared + *d * *d;
            }
            if squared <= T::zero() {
                continue; // distance 0: no gradient (the norm's subgradient chosen as 0)
            }
            let distance = squared.sqrt();
            total += distance.into();
            // d|a - b| / da = (a - b) / |a - b|, and the opposite for b.
            let unit = scale / distance;
            let (row_i, row_j) = (i * parts, j * parts);
            for (p, &d) in diff.iter().enumerate() {
                let g = d * unit;
                grad[row_i + p] = grad[row_i + p] + g;
                grad[row_j + p] = grad[row_j + p] - g;
            }
        }
    }
    total
}

/// How many pairs ahead the rows of a neighbour are fetched into the cache. The neighbours of
/// a Gaussian lie anywhere in the arrays (densification appends), so without it nearly every
/// pair waits on memory: 96.6k Gaussians x 3 neighbours took 24.7 ms, against 7.3 ms with
/// each Gaussian's neighbours next to it in memory.
const PREFETCH_PAIRS: usize = 16;

/// Asks the cache for row `j` (when it is one: padding is negative) of `logits` and of
/// `grad`, both [N, parts]; a hint only, which changes no value.
#[inline(always)]
fn prefetch_row<T>(logits: &[T], grad: &[T], j: i64, parts: usize) {
    #[cfg(target_arch = "x86_64")]
    if j >= 0 {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        let (first, last) = (j as usize * parts, (j as usize + 1) * parts - 1);
        for row in [logits, grad] {
            // The row's first and last values: a row may straddle two cache lines.
            for at in [first, last] {
                // SAFETY: `at` is inside the row of a checked index (< N), and a prefetch
                // reads nothing that the program sees.
                unsafe { _mm_prefetch::<_MM_HINT_T0>(row.as_ptr().add(at).cast::<i8>()) };
            }
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (logits, grad, j, parts);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn uniform(rng: &mut fastrand::Rng, n: usize) -> Vec<f64> {
        (0..n).map(|_| 4.0 * rng.f64() - 2.0).collect()
    }

    /// Random neighbour lists over n points with some padding.
    fn lists(rng: &mut fastrand::Rng, n: usize, per_point: usize) -> Vec<i64> {
        (0..n * per_point)
            .map(|_| {
                if rng.f64() < 0.1 {
                    -1
                } else {
                    rng.i64(0..n as i64)
                }
            })
            .collect()
    }

    /// The hand-computed example: distances 5, 0 | 5 | 0, 5 over five valid pairs.
    #[test]
    fn matches_a_hand_computation() {
        let logits = [0.0, 0.0, 3.0, 4.0, 0.0, 0.0];
        let neighbours = [1, 2, 0, -1, 0, 1];
        let out = knn_consistency(&logits, 2, &neighbours).unwrap();
        assert!((out.loss - 3.0f64).abs() < 1e-15);
        // Each pair 5 apart adds ±(0.6, 0.8) / 5 / 5 (the unit difference over the distance,
        // divided by the five pairs): point 0 sits in two (0->1, 1->0), point 1 in three,
        // point 2 in one (2->1); the pairs with distance 0 add nothing.
        let want = [-0.24, -0.32, 0.36, 0.48, -0.12, -0.16];
        for (g, w) in out.grad.iter().zip(want) {
            assert!((g - w).abs() < 1e-15, "{:?}", out.grad);
        }
    }

    /// The gradient against central finite differences of the loss, in f64.
    #[test]
    fn gradient_matches_finite_differences() {
        let mut rng = fastrand::Rng::with_seed(3);
        for parts in [1, 2, 5] {
            let n = 40;
            let logits = uniform(&mut rng, n * parts);
            let neighbours = lists(&mut rng, n, 4);
            let out = knn_consistency(&logits, parts, &neighbours).unwrap();
            let h = 1e-6;
            for k in 0..logits.len() {
                let at = |delta: f64| {
                    let mut shifted = logits.clone();
                    shifted[k] += delta;
                    knn_consistency(&shifted, parts, &neighbours).unwrap().loss
                };
                let numeric = (at(h) - at(-h)) / (2.0 * h);
                assert!(
                    (numeric - out.grad[k]).abs() < 1e-8,
                    "K = {parts}, value {k}: {numeric} vs {}",
                    out.grad[k]
                );
            }
        }
    }

    /// float32 against float64 on the same inputs.
    #[test]
    fn f32_agrees_with_f64() {
        let mut rng = fastrand::Rng::with_seed(5);
        let (n, parts) = (5000, 3);
        let logits = uniform(&mut rng, n * parts);
        let neighbours = lists(&mut rng, n, 3);
        let wide = knn_consistency(&logits, parts, &neighbours).unwrap();
        let narrow: Vec<f32> = logits.iter().map(|&v| v as f32).collect();
        let low = knn_consistency(&narrow, parts, &neighbours).unwrap();
        assert!((f64::from(low.loss) - wide.loss).abs() < 1e-6 * wide.loss);
        let err: f64 = low
            .grad
            .iter()
            .zip(&wide.grad)
            .map(|(&a, &b)| (f64::from(a) - b).powi(2))
            .sum();
        let norm: f64 = wide.grad.iter().map(|b| b * b).sum();
        assert!((err / norm).sqrt() < 1e-5);
    }

    /// The part counts compiled as constants sum in the order the run-time count does: the
    /// same bits, on lists long enough for the prefetch to run ahead of the pairs.
    #[test]
    fn constant_part_counts_give_the_bits_of_the_run_time_count() {
        let mut rng = fastrand::Rng::with_seed(11);
        for parts in [1, 3, 8, 13] {
            let n = 300;
            let logits: Vec<f32> = (0..n * parts).map(|_| 4.0 * rng.f32() - 2.0).collect();
            let neighbours = lists(&mut rng, n, 3);
            let scale = 1.0 / neighbours.iter().filter(|&&j| j >= 0).count() as f32;
            let mut fixed = vec![0.0f32; logits.len()];
            let mut generic = vec![0.0f32; logits.len()];
            let total = with_channels!(
                parts,
                sum_pairs::<f32>(&logits, parts, &neighbours, scale, &mut fixed)
            );
            let generic_total =
                sum_pairs::<f32, 0>(&logits, parts, &neighbours, scale, &mut generic);
            assert_eq!(total.to_bits(), generic_total.to_bits(), "K = {parts}");
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&fixed), bits(&generic), "K = {parts}");
        }
    }

    /// Agreeing logits, only padding, no points at all: finite zeros.
    #[test]
    fn degenerate_inputs_give_zeros() {
        let same = [1.5f32; 8];
        let out = knn_consistency(&same, 2, &[1, 2, 3, 0]).unwrap();
        assert_eq!(out.loss, 0.0);
        assert!(out.grad.iter().all(|&g| g == 0.0));
        let padded = knn_consistency(&[1.0f32, 2.0], 1, &[-1, -1]).unwrap();
        assert_eq!((padded.loss, padded.grad), (0.0, vec![0.0, 0.0]));
        let empty = knn_consistency::<f32>(&[], 2, &[]).unwrap();
        assert!(empty.grad.is_empty() && empty.loss == 0.0);
    }

    #[test]
    fn bad_inputs_are_errors() {
        let message = |r: Result<Consistency<f32>>| r.unwrap_err().to_string();
        assert!(message(knn_consistency(&[0.0; 6], 2, &[3, 0, 1])).contains("index 3 >= N = 3"));
        assert!(message(knn_consistency(&[0.0; 6], 4, &[0])).contains("N x K"));
        assert!(message(knn_consistency(&[0.0; 6], 2, &[0, 1])).contains("N x n"));
        assert!(message(knn_consistency(&[0.0, f32::NAN], 1, &[1, 0])).contains("non-finite"));
    }
}
