//! Quaternions as `[L; 4]` = (w, x, y, z) over any [`Lane`] (a scalar, or eight Gaussians'
//! values at once), with the transposes the backward needs. Products are the plain
//! polynomials (no normalisation), so their derivatives are exact for any input, unit or not.
//! Arrays are built with the always-inlined `array` (`std::array::from_fn`'s element calls
//! would stay out-of-line, outside the AVX2 code).

use super::lane::Lane;
use crate::splat::cpu::lanes::array;

pub type Quat<L> = [L; 4];
pub type Vec3<L> = [L; 3];

#[inline(always)]
pub fn two<L: Lane>() -> L {
    L::one() + L::one()
}

/// Hamilton product a * b (apply b first, then a).
#[inline(always)]
pub fn mul<L: Lane>(a: &Quat<L>, b: &Quat<L>) -> Quat<L> {
    let [aw, ax, ay, az] = *a;
    let [bw, bx, by, bz] = *b;
    [
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ]
}

#[inline(always)]
pub fn conj<L: Lane>(q: &Quat<L>) -> Quat<L> {
    [q[0], -q[1], -q[2], -q[3]]
}

#[inline(always)]
pub fn dot<L: Lane, const D: usize>(a: &[L; D], b: &[L; D]) -> L {
    a.iter().zip(b).fold(L::zero(), |s, (&x, &y)| s + x * y)
}

/// a + s b, element-wise.
#[inline(always)]
pub fn add_scaled<L: Lane, const D: usize>(a: &[L; D], s: L, b: &[L; D]) -> [L; D] {
    array(|i| a[i] + s * b[i])
}

#[inline(always)]
pub fn scale<L: Lane, const D: usize>(s: L, a: &[L; D]) -> [L; D] {
    array(|i| s * a[i])
}

/// `a` on the lanes where `m` holds, else `b`, element-wise.
#[inline(always)]
pub fn select<L: Lane, const D: usize>(m: L::Mask, a: &[L; D], b: &[L; D]) -> [L; D] {
    array(|i| L::select(m, a[i], b[i]))
}

#[inline(always)]
pub fn cross<L: Lane>(a: &Vec3<L>, b: &Vec3<L>) -> Vec3<L> {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

#[inline(always)]
fn vector<L: Lane>(q: &Quat<L>) -> Vec3<L> {
    [q[1], q[2], q[3]]
}

/// v rotated by q = (w, u): v + 2 w (u x v) + 2 u x (u x v) (the rotation when |q| = 1).
#[inline(always)]
pub fn rotate<L: Lane>(q: &Quat<L>, v: &Vec3<L>) -> Vec3<L> {
    let (w, u) = (q[0], vector(q));
    let uv = cross(&u, v);
    let uuv = cross(&u, &uv);
    array(|i| v[i] + two::<L>() * (w * uv[i] + uuv[i]))
}

/// Gradients (to q, to v) of `g · rotate(q, v)`.
#[inline(always)]
pub fn rotate_backward<L: Lane>(q: &Quat<L>, v: &Vec3<L>, g: &Vec3<L>) -> (Quat<L>, Vec3<L>) {
    let (w, u) = (q[0], vector(q));
    let t = two::<L>();
    let uv = cross(&u, v);
    let gu = cross(g, &u);
    // d/dw: 2 (u x v); d/du of 2w (u x v) + 2 u x (u x v), each cross product's transpose.
    let vg = cross(v, g);
    let uv_g = cross(&uv, g);
    let v_gu = cross(v, &gu);
    let grad_u: Vec3<L> = array(|i| t * (w * vg[i] + uv_g[i] + v_gu[i]));
    let gu_u = cross(&gu, &u);
    let grad_v: Vec3<L> = array(|i| g[i] + t * (w * gu[i] + gu_u[i]));
    ([t * dot(g, &uv), grad_u[0], grad_u[1], grad_u[2]], grad_v)
}

#[cfg(test)]
pub fn dot_slices(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).fold(0.0, |s, (&x, &y)| s + x * y)
}
