//! The real spherical-harmonic basis of degree <= 3 and its gradient, on a unit direction,
//! generic over the float type: the CPU executor runs it in f32, the reference in f64 (the
//! WGSL kernels have their own copy in shaders/sh/basis.wgsl).

use std::ops::{Add, AddAssign, Div, Mul, Neg, Sub};

use super::MIN_DIR_NORM;

/// Normalisation constants of the real basis, per degree (as in 3D Gaussian Splatting).
pub const C0: f64 = 0.282_094_791_773_878_14;
pub const C1: f64 = 0.488_602_511_902_919_9;
pub const C2: [f64; 5] = [
    1.092_548_430_592_079_2,
    -1.092_548_430_592_079_2,
    0.315_391_565_252_520_05,
    -1.092_548_430_592_079_2,
    0.546_274_215_296_039_6,
];
pub const C3: [f64; 7] = [
    -0.590_043_589_926_643_5,
    2.890_611_442_640_554,
    -0.457_045_799_464_465_8,
    0.373_176_332_590_115_4,
    -0.457_045_799_464_465_8,
    1.445_305_721_320_277,
    -0.590_043_589_926_643_5,
];

/// Coefficients per channel at the highest degree.
pub const MAX_COEFFS: usize = 16;

/// The arithmetic the basis needs, for f32 and f64.
pub trait Real:
    Copy
    + Default
    + PartialOrd
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
    + AddAssign
{
    fn lit(v: f64) -> Self;
    fn sqrt(self) -> Self;
    fn abs(self) -> Self;
}

impl Real for f32 {
    fn lit(v: f64) -> Self {
        v as f32
    }
    fn sqrt(self) -> Self {
        f32::sqrt(self)
    }
    fn abs(self) -> Self {
        f32::abs(self)
    }
}

impl Real for f64 {
    fn lit(v: f64) -> Self {
        v
    }
    fn sqrt(self) -> Self {
        f64::sqrt(self)
    }
    fn abs(self) -> Self {
        f64::abs(self)
    }
}

/// `(d / |d|, |d|)`, or None when |d| < MIN_DIR_NORM. Scaled by the largest component first so
/// that neither tiny nor huge components under- or overflow the squared norm.
pub fn unit<T: Real>(d: [T; 3]) -> Option<([T; 3], T)> {
    let mut m = d[0].abs();
    for c in &d[1..] {
        if c.abs() > m {
            m = c.abs();
        }
    }
    if m <= T::default() {
        return None;
    }
    let s = [d[0] / m, d[1] / m, d[2] / m];
    let len = (s[0] * s[0] + s[1] * s[1] + s[2] * s[2]).sqrt();
    let norm = m * len;
    if norm < T::lit(MIN_DIR_NORM) {
        return None;
    }
    Some(([s[0] / len, s[1] / len, s[2] / len], norm))
}

/// The first `k` basis functions at the unit direction `u` (k = 1, 4, 9 or 16).
pub fn basis<T: Real>(u: [T; 3], k: usize) -> [T; MAX_COEFFS] {
    let c = T::lit;
    let [x, y, z] = u;
    let mut out = [T::default(); MAX_COEFFS];
    out[0] = c(C0);
    if k > 1 {
        out[1] = -c(C1) * y;
        out[2] = c(C1) * z;
        out[3] = -c(C1) * x;
    }
    if k > 4 {
        let (xx, yy, zz) = (x * x, y * y, z * z);
        out[4] = c(C2[0]) * x * y;
        out[5] = c(C2[1]) * y * z;
        out[6] = c(C2[2]) * (c(2.0) * zz - xx - yy);
        out[7] = c(C2[3]) * x * z;
        out[8] = c(C2[4]) * (xx - yy);
        if k > 9 {
            out[9] = c(C3[0]) * y * (c(3.0) * xx - yy);
            out[10] = c(C3[1]) * x * y * z;
            out[11] = c(C3[2]) * y * (c(4.0) * zz - xx - yy);
            out[12] = c(C3[3]) * z * (c(2.0) * zz - c(3.0) * xx - c(3.0) * yy);
            out[13] = c(C3[4]) * x * (c(4.0) * zz - xx - yy);
            out[14] = c(C3[5]) * z * (xx - yy);
            out[15] = c(C3[6]) * x * (xx - c(3.0) * yy);
        }
    }
    out
}

/// Gradients of the first `k` basis functions with respect to the components of `u` (the
/// polynomials differentiated as functions on all of R^3; the caller projects onto the
/// sphere's tangent plane).
pub fn basis_gradient<T: Real>(u: [T; 3], k: usize) -> [[T; 3]; MAX_COEFFS] {
    let c = T::lit;
    let zero = T::default();
    let [x, y, z] = u;
    let mut out = [[zero; 3]; MAX_COEFFS];
    if k > 1 {
        out[1] = [zero, -c(C1), zero];
        out[2] = [zero, zero, c(C1)];
        out[3] = [-c(C1), zero, zero];
    }
    if k > 4 {
        out[4] = [c(C2[0]) * y, c(C2[0]) * x, zero];
        out[5] = [zero, c(C2[1]) * z, c(C2[1]) * y];
        out[6] = [c(-2.0 * C2[2]) * x, c(-2.0 * C2[2]) * y, c(4.0 * C2[2]) * z];
        out[7] = [c(C2[3]) * z, zero, c(C2[3]) * x];
        out[8] = [c(2.0 * C2[4]) * x, c(-2.0 * C2[4]) * y, zero];
        if k > 9 {
            let (xx, yy, zz) = (x * x, y * y, z * z);
            out[9] = [c(6.0 * C3[0]) * x * y, c(3.0 * C3[0]) * (xx - yy), zero];
            out[10] = [c(C3[1]) * y * z, c(C3[1]) * x * z, c(C3[1]) * x * y];
            out[11] = [
                c(-2.0 * C3[2]) * x * y,
                c(C3[2]) * (c(4.0) * zz - xx - c(3.0) * yy),
                c(8.0 * C3[2]) * y * z,
            ];
            out[12] = [
                c(-6.0 * C3[3]) * x * z,
                c(-6.0 * C3[3]) * y * z,
                c(3.0 * C3[3]) * (c(2.0) * zz - xx - yy),
            ];
            out[13] = [
                c(C3[4]) * (c(4.0) * zz - c(3.0) * xx - yy),
                c(-2.0 * C3[4]) * x * y,
                c(8.0 * C3[4]) * x * z,
            ];
            out[14] = [
                c(2.0 * C3[5]) * x * z,
                c(-2.0 * C3[5]) * y * z,
                c(C3[5]) * (xx - yy),
            ];
            out[15] = [c(3.0 * C3[6]) * (xx - yy), c(-6.0 * C3[6]) * x * y, zero];
        }
    }
    out
}

/// One Gaussian's colour: `dir` [3], `coeffs` [k * 3] (coefficient-major), into `rgb` [3].
pub fn forward_one<T: Real>(dir: &[T], coeffs: &[T], k: usize, rgb: &mut [T]) {
    let u = unit([dir[0], dir[1], dir[2]]).map_or([T::default(); 3], |(u, _)| u);
    let y = basis(u, k);
    for (ch, out) in rgb.iter_mut().enumerate() {
        let mut sum = T::lit(0.5);
        for (j, yj) in y.iter().enumerate().take(k) {
            sum += *yj * coeffs[3 * j + ch];
        }
        *out = if sum > T::default() {
            sum
        } else {
            T::default()
        };
    }
}

/// One Gaussian's gradients: given `grad_rgb` [3], writes `grad_coeffs` [k * 3] and
/// `grad_dir` [3]. Where the clamp at 0 is active the channel passes no gradient.
pub fn backward_one<T: Real>(
    dir: &[T],
    coeffs: &[T],
    k: usize,
    grad_rgb: &[T],
    grad_coeffs: &mut [T],
    grad_dir: &mut [T],
) {
    let zero = T::default();
    let unit_norm = unit([dir[0], dir[1], dir[2]]);
    let u = unit_norm.map_or([zero; 3], |(u, _)| u);
    let y = basis(u, k);
    // The gradient reaching each channel's pre-clamp sum.
    let mut g = [zero; 3];
    for ch in 0..3 {
        let mut sum = T::lit(0.5);
        for (j, yj) in y.iter().enumerate().take(k) {
            sum += *yj * coeffs[3 * j + ch];
        }
        g[ch] = if sum > zero { grad_rgb[ch] } else { zero };
    }
    for (j, yj) in y.iter().enumerate().take(k) {
        for ch in 0..3 {
            grad_coeffs[3 * j + ch] = *yj * g[ch];
        }
    }
    grad_dir[..3].fill(zero);
    let Some((u, norm)) = unit_norm else {
        return;
    };
    if k == 1 {
        return;
    }
    let dy = basis_gradient(u, k);
    let mut gu = [zero; 3];
    for (j, dyj) in dy.iter().enumerate().take(k).skip(1) {
        let w = coeffs[3 * j] * g[0] + coeffs[3 * j + 1] * g[1] + coeffs[3 * j + 2] * g[2];
        for a in 0..3 {
            gu[a] += w * dyj[a];
        }
    }
    // d(d / |d|)/dd = (I - u u^T) / |d|.
    let along = gu[0] * u[0] + gu[1] * u[1] + gu[2] * u[2];
    for a in 0..3 {
        grad_dir[a] = (gu[a] - along * u[a]) / norm;
    }
}
