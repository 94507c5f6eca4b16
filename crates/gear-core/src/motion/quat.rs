//! Quaternions as `[T; 4]` = (w, x, y, z), generic over f32 / f64, with the transposes the
//! backward needs. Products are the plain polynomials (no normalisation), so their derivatives
//! are exact for any input, unit or not.

use num_traits::Float;

pub type Quat<T> = [T; 4];
pub type Vec3<T> = [T; 3];

pub fn two<T: Float>() -> T {
    T::one() + T::one()
}

/// Hamilton product a * b (apply b first, then a).
pub fn mul<T: Float>(a: &Quat<T>, b: &Quat<T>) -> Quat<T> {
    let [aw, ax, ay, az] = *a;
    let [bw, bx, by, bz] = *b;
    [
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ]
}

pub fn conj<T: Float>(q: &Quat<T>) -> Quat<T> {
    [q[0], -q[1], -q[2], -q[3]]
}

pub fn dot<T: Float, const D: usize>(a: &[T; D], b: &[T; D]) -> T {
    a.iter().zip(b).fold(T::zero(), |s, (&x, &y)| s + x * y)
}

/// a + s b, element-wise.
pub fn add_scaled<T: Float, const D: usize>(a: &[T; D], s: T, b: &[T; D]) -> [T; D] {
    std::array::from_fn(|i| a[i] + s * b[i])
}

pub fn scale<T: Float, const D: usize>(s: T, a: &[T; D]) -> [T; D] {
    std::array::from_fn(|i| s * a[i])
}

pub fn cross<T: Float>(a: &Vec3<T>, b: &Vec3<T>) -> Vec3<T> {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn vector<T: Float>(q: &Quat<T>) -> Vec3<T> {
    [q[1], q[2], q[3]]
}

/// v rotated by q = (w, u): v + 2 w (u x v) + 2 u x (u x v) (the rotation when |q| = 1).
pub fn rotate<T: Float>(q: &Quat<T>, v: &Vec3<T>) -> Vec3<T> {
    let (w, u) = (q[0], vector(q));
    let uv = cross(&u, v);
    let uuv = cross(&u, &uv);
    std::array::from_fn(|i| v[i] + two::<T>() * (w * uv[i] + uuv[i]))
}

/// Gradients (to q, to v) of `g · rotate(q, v)`.
pub fn rotate_backward<T: Float>(q: &Quat<T>, v: &Vec3<T>, g: &Vec3<T>) -> (Quat<T>, Vec3<T>) {
    let (w, u) = (q[0], vector(q));
    let t = two::<T>();
    let uv = cross(&u, v);
    let gu = cross(g, &u);
    // d/dw: 2 (u x v); d/du of 2w (u x v) + 2 u x (u x v), each cross product's transpose.
    let vg = cross(v, g);
    let uv_g = cross(&uv, g);
    let v_gu = cross(v, &gu);
    let grad_u: Vec3<T> = std::array::from_fn(|i| t * (w * vg[i] + uv_g[i] + v_gu[i]));
    let gu_u = cross(&gu, &u);
    let grad_v: Vec3<T> = std::array::from_fn(|i| g[i] + t * (w * gu[i] + gu_u[i]));
    ([t * dot(g, &uv), grad_u[0], grad_u[1], grad_u[2]], grad_v)
}

#[cfg(test)]
pub fn dot_slices<T: Float>(a: &[T], b: &[T]) -> T {
    a.iter().zip(b).fold(T::zero(), |s, (&x, &y)| s + x * y)
}
