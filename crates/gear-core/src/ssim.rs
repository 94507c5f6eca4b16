//! Structural similarity (SSIM) of two images and its gradient with respect to the first, in
//! one call: the D-SSIM half of every photometric loss of training.
//!
//! The definition is the field's (and `gear.losses.ssim_reference`'s, the torch form the tests
//! compare with): per channel, means, variances and covariance under an 11 x 11 Gaussian window
//! (sigma 1.5, zero padding), SSIM = (2 mu_a mu_b + C1)(2 cov + C2) / ((mu_a² + mu_b² + C1)
//! (var_a + var_b + C2)) averaged over pixels and channels. The window is separable and
//! symmetric, so a blur is two 1-D passes and is its own adjoint: the backward blurs three
//! per-pixel derivative maps with the same window. Planes run in parallel (one channel per
//! task) with every sum in a fixed order, so results do not depend on the thread count.
//!
//! torch spends ~6 ms on a 128 x 128 RGB forward + backward on one thread (its depthwise
//! convolutions and ~30 elementwise kernels); this is one pass over each plane per step.

use rayon::prelude::*;

use crate::error::{check_finite, invalid, Result};
use crate::motion::Real;
use crate::splat::cpu::global_pool;

/// Side of the Gaussian window, its standard deviation, and the stabilising constants
/// (for images in [0, 1]).
pub const WINDOW: usize = 11;
pub const SIGMA: f64 = 1.5;
pub const C1: f64 = 0.01 * 0.01;
pub const C2: f64 = 0.03 * 0.03;

/// Mean SSIM and, when asked for, its gradient with respect to `a` ([H, W, C] like `a`).
#[derive(Debug, Clone, PartialEq)]
pub struct Ssim<T> {
    pub value: T,
    pub grad: Option<Vec<T>>,
}

/// An [H, W, C] image, row-major with interleaved channels.
#[derive(Debug, Clone, Copy)]
pub struct Image<'a, T> {
    pub values: &'a [T],
    pub height: usize,
    pub width: usize,
    pub channels: usize,
}

impl<T: Copy> Image<'_, T> {
    fn pixels(&self) -> usize {
        self.height * self.width
    }

    /// Channel `c` as its own [H, W] plane.
    fn plane(&self, c: usize) -> Vec<T> {
        self.values
            .iter()
            .skip(c)
            .step_by(self.channels)
            .copied()
            .collect()
    }
}

/// The normalised window weights.
fn window<T: Real>() -> [T; WINDOW] {
    let centre = (WINDOW - 1) as f64 / 2.0;
    let raw: [f64; WINDOW] =
        std::array::from_fn(|k| (-((k as f64 - centre).powi(2)) / (2.0 * SIGMA * SIGMA)).exp());
    let total: f64 = raw.iter().sum();
    raw.map(|w| cast(w / total))
}

fn cast<T: Real>(v: f64) -> T {
    T::from(v).expect("a finite f64 converts to every float type")
}

/// `plane` [H, W] blurred by `g` along rows, then along columns, with zero padding. Each pass
/// adds one tap at a time over a whole row (contiguous slices: vector code).
fn blur<T: Real>(plane: &[T], height: usize, width: usize, g: &[T; WINDOW]) -> Vec<T> {
    let pad = WINDOW / 2;
    let mut rows = vec![T::zero(); plane.len()];
    for (out, input) in rows.chunks_exact_mut(width).zip(plane.chunks_exact(width)) {
        for (k, &w) in g.iter().enumerate() {
            // out[i] += w in[i + k - pad] for the i whose source lies inside the row.
            let (lo, hi) = (
                (pad.saturating_sub(k)),
                (width + pad).saturating_sub(k).min(width),
            );
            if lo >= hi {
                continue;
            }
            let src = &input[lo + k - pad..hi + k - pad];
            for (o, &v) in out[lo..hi].iter_mut().zip(src) {
                *o = *o + w * v;
            }
        }
    }
    let mut out = vec![T::zero(); plane.len()];
    for (r, out_row) in out.chunks_exact_mut(width).enumerate() {
        for (k, &w) in g.iter().enumerate() {
            let Some(source) = (r + k).checked_sub(pad).filter(|&s| s < height) else {
                continue;
            };
            let src = &rows[source * width..(source + 1) * width];
            for (o, &v) in out_row.iter_mut().zip(src) {
                *o = *o + w * v;
            }
        }
    }
    out
}

/// The five maps of one channel that are blurred: a, b, a², b², ab.
const MOMENTS: usize = 5;

/// Map `which` (of [`MOMENTS`]) of the planes `a`, `b`.
fn moment<T: Real>(a: &[T], b: &[T], which: usize) -> Vec<T> {
    let f: fn(T, T) -> T = match which {
        0 => |x, _| x,
        1 => |_, y| y,
        2 => |x, _| x * x,
        3 => |_, y| y * y,
        _ => |x, y| x * y,
    };
    a.iter().zip(b).map(|(&x, &y)| f(x, y)).collect()
}

/// One channel's SSIM sum (f64) from its blurred moments (mu_a, mu_b, aa, bb, ab) and, with
/// `want_grad`, d SSIM / d (mu_a, aa, ab) per pixel, divided by `count` (the H W C values
/// averaged).
fn score<T: Real>(m: &[Vec<T>], count: usize, want_grad: bool) -> (f64, [Vec<T>; 3]) {
    let (c1, c2, two) = (cast::<T>(C1), cast::<T>(C2), cast::<T>(2.0));
    let scale = T::one() / cast(count as f64);
    let n = m[0].len();
    let mut total = 0.0f64;
    let mut d: [Vec<T>; 3] = std::array::from_fn(|_| {
        if want_grad {
            vec![T::zero(); n]
        } else {
            vec![]
        }
    });
    for p in 0..n {
        let (ma, mb) = (m[0][p], m[1][p]);
        let cov = m[4][p] - ma * mb;
        let num1 = two * ma * mb + c1;
        let num2 = two * cov + c2;
        let den1 = ma * ma + mb * mb + c1;
        let den2 = (m[2][p] - ma * ma) + (m[3][p] - mb * mb) + c2;
        // One division per pixel: 1 / den1 = den2 · inv and 1 / den2 = den1 · inv.
        let inv = T::one() / (den1 * den2);
        let s = num1 * num2 * inv;
        total += s.into();
        if want_grad {
            let d_num1 = num2 * inv;
            let d_num2 = num1 * inv;
            let d_den1 = -s * den2 * inv;
            let d_den2 = -s * den1 * inv;
            d[0][p] = scale * two * ((d_num1 - d_num2) * mb + (d_den1 - d_den2) * ma);
            d[1][p] = scale * d_den2;
            d[2][p] = scale * two * d_num2;
        }
    }
    (total, d)
}

/// Mean SSIM of `a` and `b` (same shape), and its gradient with respect to `a` if
/// `want_grad`. Errors: shapes that differ or do not match their values, or a non-finite
/// value. An empty image has SSIM 1 (nothing differs) and an empty gradient.
pub fn ssim<T: Real>(a: &Image<'_, T>, b: &Image<'_, T>, want_grad: bool) -> Result<Ssim<T>> {
    let shape = |i: &Image<'_, T>| (i.height, i.width, i.channels);
    if shape(a) != shape(b) {
        return Err(invalid(format!(
            "ssim: the images must have one shape, got {:?} and {:?}",
            shape(a),
            shape(b)
        )));
    }
    for (name, image) in [("a", a), ("b", b)] {
        if image.values.len() != image.pixels() * image.channels {
            return Err(invalid(format!(
                "ssim: {name} must hold H x W x C = {} values, got {}",
                image.pixels() * image.channels,
                image.values.len()
            )));
        }
        check_finite(&format!("ssim {name}"), image.values)?;
    }
    let count = a.values.len();
    if count == 0 {
        let grad = want_grad.then(Vec::new);
        return Ok(Ssim {
            value: T::one(),
            grad,
        });
    }
    let (h, w, channels) = (a.height, a.width, a.channels);
    let g = window::<T>();
    let planes: Vec<(Vec<T>, Vec<T>)> = (0..channels).map(|c| (a.plane(c), b.plane(c))).collect();
    // Every blur is its own task (5 per channel, then 3): enough of them to keep every thread
    // busy at C = 3; each writes its own plane, so nothing depends on the scheduling.
    let (total, grad) = global_pool()?.install(|| {
        let moments: Vec<Vec<T>> = (0..channels * MOMENTS)
            .into_par_iter()
            .map(|t| {
                let (pa, pb) = &planes[t / MOMENTS];
                blur(&moment(pa, pb, t % MOMENTS), h, w, &g)
            })
            .collect();
        let scores: Vec<(f64, [Vec<T>; 3])> = moments
            .par_chunks(MOMENTS)
            .map(|m| score(m, count, want_grad))
            .collect();
        let total: f64 = scores.iter().map(|(s, _)| s).sum();
        if !want_grad {
            return (total, None);
        }
        // The blur is symmetric: its adjoint is itself.
        let blurred: Vec<Vec<T>> = (0..channels * 3)
            .into_par_iter()
            .map(|t| blur(&scores[t / 3].1[t % 3], h, w, &g))
            .collect();
        let mut grad = vec![T::zero(); count];
        for (c, ((pa, pb), d)) in planes.iter().zip(blurred.chunks_exact(3)).enumerate() {
            for p in 0..pa.len() {
                grad[p * channels + c] =
                    d[0][p] + cast::<T>(2.0) * pa[p] * d[1][p] + pb[p] * d[2][p];
            }
        }
        (total, Some(grad))
    });
    Ok(Ssim {
        value: cast(total / count as f64),
        grad,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn image(rng: &mut fastrand::Rng, h: usize, w: usize, c: usize) -> Vec<f64> {
        (0..h * w * c).map(|_| rng.f64()).collect()
    }

    fn view<T>(values: &[T], h: usize, w: usize, c: usize) -> Image<'_, T> {
        Image {
            values,
            height: h,
            width: w,
            channels: c,
        }
    }

    /// The blur against a direct 2-D sum with zero padding.
    #[test]
    fn blur_matches_the_direct_sum() {
        let mut rng = fastrand::Rng::with_seed(1);
        let (h, w) = (7, 13);
        let plane = image(&mut rng, h, w, 1);
        let g = window::<f64>();
        let got = blur(&plane, h, w, &g);
        let pad = (WINDOW / 2) as isize;
        for y in 0..h as isize {
            for x in 0..w as isize {
                let mut want = 0.0;
                for (ky, gy) in g.iter().enumerate() {
                    for (kx, gx) in g.iter().enumerate() {
                        let (sy, sx) = (y + ky as isize - pad, x + kx as isize - pad);
                        if (0..h as isize).contains(&sy) && (0..w as isize).contains(&sx) {
                            want += gy * gx * plane[(sy * w as isize + sx) as usize];
                        }
                    }
                }
                let v = got[(y * w as isize + x) as usize];
                assert!((v - want).abs() < 1e-14, "({y}, {x}): {v} vs {want}");
            }
        }
    }

    /// Identical images: SSIM 1 and a zero gradient (its maximum).
    #[test]
    fn identical_images_score_one() {
        let mut rng = fastrand::Rng::with_seed(2);
        let a = image(&mut rng, 12, 9, 3);
        let out = ssim(&view(&a, 12, 9, 3), &view(&a, 12, 9, 3), true).unwrap();
        assert!((out.value - 1.0).abs() < 1e-12);
        assert!(out.grad.unwrap().iter().all(|g| g.abs() < 1e-12));
    }

    /// The gradient against central finite differences, in f64, on odd sizes smaller and
    /// larger than the window.
    #[test]
    fn gradient_matches_finite_differences() {
        let mut rng = fastrand::Rng::with_seed(3);
        for (h, w, c) in [(5, 7, 1), (14, 12, 2)] {
            let a = image(&mut rng, h, w, c);
            let b = image(&mut rng, h, w, c);
            let out = ssim(&view(&a, h, w, c), &view(&b, h, w, c), true).unwrap();
            let grad = out.grad.unwrap();
            let eps = 1e-6;
            for i in (0..a.len()).step_by(3) {
                let at = |d: f64| {
                    let mut shifted = a.clone();
                    shifted[i] += d;
                    ssim(&view(&shifted, h, w, c), &view(&b, h, w, c), false)
                        .unwrap()
                        .value
                };
                let numeric = (at(eps) - at(-eps)) / (2.0 * eps);
                assert!(
                    (numeric - grad[i]).abs() < 1e-8,
                    "{h}x{w}x{c} value {i}: {numeric} vs {}",
                    grad[i]
                );
            }
        }
    }

    /// float32 against float64.
    #[test]
    fn f32_agrees_with_f64() {
        let mut rng = fastrand::Rng::with_seed(4);
        let (h, w, c) = (64, 48, 3);
        let (a, b) = (image(&mut rng, h, w, c), image(&mut rng, h, w, c));
        let wide = ssim(&view(&a, h, w, c), &view(&b, h, w, c), true).unwrap();
        let (a32, b32): (Vec<f32>, Vec<f32>) = a
            .iter()
            .zip(&b)
            .map(|(&x, &y)| (x as f32, y as f32))
            .unzip();
        let low = ssim(&view(&a32, h, w, c), &view(&b32, h, w, c), true).unwrap();
        assert!((f64::from(low.value) - wide.value).abs() < 1e-6);
        let (g32, g64) = (low.grad.unwrap(), wide.grad.unwrap());
        let err: f64 = g32
            .iter()
            .zip(&g64)
            .map(|(&x, &y)| (f64::from(x) - y).powi(2))
            .sum();
        let norm: f64 = g64.iter().map(|y| y * y).sum();
        assert!((err / norm).sqrt() < 1e-4);
    }

    /// Black against black, a one-pixel image, an empty one: finite.
    #[test]
    fn hard_cases_stay_finite() {
        let zeros = vec![0.0f32; 20 * 20 * 3];
        let out = ssim(&view(&zeros, 20, 20, 3), &view(&zeros, 20, 20, 3), true).unwrap();
        assert!((out.value - 1.0).abs() < 1e-6);
        let ones = vec![1.0f32; 20 * 20 * 3];
        let out = ssim(&view(&zeros, 20, 20, 3), &view(&ones, 20, 20, 3), true).unwrap();
        assert!(out.value.is_finite() && out.grad.unwrap().iter().all(|g| g.is_finite()));
        let one = ssim(&view(&[0.3f32], 1, 1, 1), &view(&[0.7f32], 1, 1, 1), true).unwrap();
        assert!(one.value.is_finite() && one.grad.unwrap()[0].is_finite());
        let empty = ssim::<f32>(&view(&[], 0, 4, 3), &view(&[], 0, 4, 3), true).unwrap();
        assert_eq!((empty.value, empty.grad), (1.0, Some(vec![])));
    }

    #[test]
    fn bad_inputs_are_errors() {
        let a = [0.0f32; 12];
        let message = |r: Result<Ssim<f32>>| r.unwrap_err().to_string();
        assert!(message(ssim(&view(&a, 2, 2, 3), &view(&a, 2, 3, 2), false)).contains("one shape"));
        assert!(message(ssim(&view(&a, 2, 2, 2), &view(&a, 2, 2, 2), false)).contains("H x W x C"));
        let mut nan = a;
        nan[5] = f32::NAN;
        assert!(
            message(ssim(&view(&a, 2, 2, 3), &view(&nan, 2, 2, 3), false))
                .contains("ssim b has a non-finite value at flat index 5")
        );
    }
}
