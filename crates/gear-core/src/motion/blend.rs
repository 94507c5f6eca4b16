//! One Gaussian's deformation and its backward: its K part motions (unit dual quaternions)
//! sign-aligned with its heaviest part, mixed by its weights, normalised, and applied to its
//! mean and composed with its rotation. The maths of `gear.kinematics.deform`, written out
//! once per Gaussian instead of as a chain of [N, K] tensor operations.

use num_traits::Float;

use super::quat::{add_scaled, conj, dot, mul, rotate, rotate_backward, scale, two, Quat, Vec3};

/// The K part motions: rotation halves `qr` and dual halves `qd`, with the sign each part
/// takes against each possible leading part (worked out once per call, not per Gaussian).
pub struct Motions<T> {
    pub qr: Vec<Quat<T>>,
    pub qd: Vec<Quat<T>>,
    /// `signs[lead * K + k]`: +1 or -1, part k's quaternion sign that agrees with part
    /// `lead`'s (q and -q are the same motion, but averaging them would cancel).
    signs: Vec<T>,
}

impl<T: Float> Motions<T> {
    pub fn new(qr: Vec<Quat<T>>, qd: Vec<Quat<T>>) -> Self {
        let k = qr.len();
        let signs = (0..k * k)
            .map(|i| {
                if dot(&qr[i / k], &qr[i % k]) < T::zero() {
                    -T::one()
                } else {
                    T::one()
                }
            })
            .collect();
        Self { qr, qd, signs }
    }

    fn sign(&self, lead: usize, k: usize) -> T {
        self.signs[lead * self.qr.len() + k]
    }
}

/// Index of the first largest weight (ties go to the lowest part, as torch's argmax).
fn lead<T: Float>(weights: &[T]) -> usize {
    let mut best = 0;
    for (k, &w) in weights.iter().enumerate().skip(1) {
        if w > weights[best] {
            best = k;
        }
    }
    best
}

/// The sign-aligned weighted sums (rotation half, dual half).
fn mix<T: Float>(weights: &[T], motions: &Motions<T>) -> (Quat<T>, Quat<T>) {
    let first = lead(weights);
    let (mut br, mut bd) = ([T::zero(); 4], [T::zero(); 4]);
    for (k, &w) in weights.iter().enumerate() {
        let s = w * motions.sign(first, k);
        br = add_scaled(&br, s, &motions.qr[k]);
        bd = add_scaled(&bd, s, &motions.qd[k]);
    }
    (br, bd)
}

/// The nearest unit dual quaternion of a mix and what its backward needs.
struct Unit<T> {
    real: Quat<T>,
    dual: Quat<T>,
    /// The dual half before its projection (dual / |real|).
    scaled_dual: Quat<T>,
    /// |real| of the mix, or zero when it vanished (the rotation is then the identity, a
    /// constant: no gradient flows to the rotation half).
    norm: T,
}

fn normalise<T: Float>(br: &Quat<T>, bd: &Quat<T>) -> Unit<T> {
    let sq = dot(br, br);
    let (norm, real) = if sq > T::zero() {
        let n = sq.sqrt();
        (n, scale(T::one() / n, br))
    } else {
        (T::zero(), [T::one(), T::zero(), T::zero(), T::zero()])
    };
    let scaled_dual = if norm > T::zero() {
        scale(T::one() / norm, bd)
    } else {
        *bd
    };
    let dual = add_scaled(&scaled_dual, -dot(&real, &scaled_dual), &real);
    Unit {
        real,
        dual,
        scaled_dual,
        norm,
    }
}

/// The deformed mean and rotation of a Gaussian at `mean` with rotation `quat`.
pub fn forward_one<T: Float>(
    mean: &Vec3<T>,
    quat: &Quat<T>,
    weights: &[T],
    motions: &Motions<T>,
) -> (Vec3<T>, Quat<T>) {
    let (br, bd) = mix(weights, motions);
    let u = normalise(&br, &bd);
    // Translation 2 vec(dual * conj(real)).
    let p = mul(&u.dual, &conj(&u.real));
    let r = rotate(&u.real, mean);
    let t = two::<T>();
    (
        [r[0] + t * p[1], r[1] + t * p[2], r[2] + t * p[3]],
        mul(&u.real, quat),
    )
}

/// Where one Gaussian's backward writes: its own gradients, and the motions' (summed into).
pub struct GradientsOne<'a, T> {
    pub mean: &'a mut [T],
    pub quat: &'a mut [T],
    pub weights: &'a mut [T],
    /// Rotation then dual halves of every part ([2K] quaternions), added to; None when the
    /// motions are held.
    pub motions: Option<&'a mut [Quat<T>]>,
}

/// Backward of [`forward_one`] for upstream gradients `grad_mean`, `grad_quat`.
pub fn backward_one<T: Float>(
    mean: &Vec3<T>,
    quat: &Quat<T>,
    weights: &[T],
    motions: &Motions<T>,
    grad_mean: &Vec3<T>,
    grad_quat: &Quat<T>,
    out: GradientsOne<T>,
) {
    let (br, bd) = mix(weights, motions);
    let u = normalise(&br, &bd);
    let t = two::<T>();
    // quat' = real * quat.
    let g_quat = mul(&conj(&u.real), grad_quat);
    let mut g_real = mul(grad_quat, &conj(quat));
    // mean' = rotate(real, mean) + 2 vec(dual * conj(real)).
    let (g_rot, g_mean) = rotate_backward(&u.real, mean, grad_mean);
    g_real = add_scaled(&g_real, T::one(), &g_rot);
    let gp = [
        T::zero(),
        t * grad_mean[0],
        t * grad_mean[1],
        t * grad_mean[2],
    ];
    let g_dual = mul(&gp, &u.real);
    g_real = add_scaled(&g_real, T::one(), &conj(&mul(&conj(&u.dual), &gp)));
    // dual = scaled_dual - (real . scaled_dual) real.
    let along = dot(&u.real, &g_dual);
    let g_scaled_dual = add_scaled(&g_dual, -along, &u.real);
    let d = dot(&u.real, &u.scaled_dual);
    g_real = add_scaled(&g_real, -along, &u.scaled_dual);
    g_real = add_scaled(&g_real, -d, &g_dual);
    // real = br / |br|, scaled_dual = bd / |br|.
    let (g_br, g_bd) = if u.norm > T::zero() {
        let radial = dot(&g_real, &u.real) + dot(&g_scaled_dual, &u.scaled_dual);
        let inv = T::one() / u.norm;
        (
            scale(inv, &add_scaled(&g_real, -radial, &u.real)),
            scale(inv, &g_scaled_dual),
        )
    } else {
        ([T::zero(); 4], g_scaled_dual)
    };
    out.mean.copy_from_slice(&g_mean);
    out.quat.copy_from_slice(&g_quat);
    let first = lead(weights);
    let mut motion_grads = out.motions;
    for (k, (&w, gw)) in weights.iter().zip(out.weights.iter_mut()).enumerate() {
        let s = motions.sign(first, k);
        *gw = s * (dot(&g_br, &motions.qr[k]) + dot(&g_bd, &motions.qd[k]));
        if let Some(m) = motion_grads.as_deref_mut() {
            let parts = m.len() / 2;
            m[k] = add_scaled(&m[k], w * s, &g_br);
            m[parts + k] = add_scaled(&m[parts + k], w * s, &g_bd);
        }
    }
}
