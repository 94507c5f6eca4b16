//! One Gaussian's deformation and its backward, per lane of a [`Lane`] (one Gaussian in a
//! scalar, eight in an eight-lane f32): its K part motions (unit dual quaternions)
//! sign-aligned with its heaviest part, mixed by its weights, normalised, and applied to its
//! mean and composed with its rotation. The maths of `gear.kinematics.deform`, written out per
//! Gaussian instead of as a chain of [N, K] tensor operations.

use super::lane::Lane;
use super::quat::{
    add_scaled, conj, dot, mul, rotate, rotate_backward, scale, select, two, Quat, Vec3,
};
use crate::splat::cpu::lanes::array;

/// The K part motions in every lane: rotation halves `qr` and dual halves `qd`.
pub struct Motions<L> {
    pub qr: Vec<Quat<L>>,
    pub qd: Vec<Quat<L>>,
}

impl<L: Lane> Motions<L> {
    /// The motions of the flat K x 4 halves `qr`, `qd`.
    pub fn new(qr: &[L::Scalar], qd: &[L::Scalar]) -> Self {
        let quats = |flat: &[L::Scalar]| -> Vec<Quat<L>> {
            flat.chunks_exact(4)
                .map(|q| array(|i| L::splat(q[i])))
                .collect()
        };
        Self {
            qr: quats(qr),
            qd: quats(qd),
        }
    }

    /// Each part's quaternion sign that agrees with the lane's heaviest part (its first
    /// largest weight, ties to the lowest part as torch's argmax), +1 or -1, written to
    /// `signs` [K]: q and -q are the same motion, but averaging them would cancel.
    #[inline(always)]
    pub fn align(&self, weights: &[L], signs: &mut [L]) {
        // The heaviest part's rotation half, per lane, held in registers (a selected copy of
        // one part's values, so each sign is the scalar code's).
        let (mut best, mut lead) = (weights[0], self.qr[0]);
        for (w, q) in weights.iter().zip(&self.qr).skip(1) {
            let heavier = w.gt(best);
            best = L::select(heavier, *w, best);
            lead = select(heavier, q, &lead);
        }
        for (s, q) in signs.iter_mut().zip(&self.qr) {
            let opposed = L::zero().gt(dot(&lead, q));
            *s = L::select(opposed, -L::one(), L::one());
        }
    }
}

/// The sign-aligned weighted sums (rotation half, dual half).
#[inline(always)]
fn mix<L: Lane>(weights: &[L], signs: &[L], motions: &Motions<L>) -> (Quat<L>, Quat<L>) {
    let (mut br, mut bd) = ([L::zero(); 4], [L::zero(); 4]);
    for (k, (&w, &sign)) in weights.iter().zip(signs).enumerate() {
        let s = w * sign;
        br = add_scaled(&br, s, &motions.qr[k]);
        bd = add_scaled(&bd, s, &motions.qd[k]);
    }
    (br, bd)
}

/// The nearest unit dual quaternion of a mix and what its backward needs.
struct Unit<L> {
    real: Quat<L>,
    dual: Quat<L>,
    /// The dual half before its projection (dual / |real|).
    scaled_dual: Quat<L>,
    /// |real| of the mix, or zero when it vanished (the rotation is then the identity, a
    /// constant: no gradient flows to the rotation half).
    norm: L,
}

#[inline(always)]
fn normalise<L: Lane>(br: &Quat<L>, bd: &Quat<L>) -> Unit<L> {
    let sq = dot(br, br);
    // Lanes whose mix vanished take the identity; their quotients below are discarded.
    let live = sq.gt(L::zero());
    let n = sq.sqrt();
    let inv = L::one() / n;
    let identity = [L::one(), L::zero(), L::zero(), L::zero()];
    let real = select(live, &scale(inv, br), &identity);
    let scaled_dual = select(live, &scale(inv, bd), bd);
    let dual = add_scaled(&scaled_dual, -dot(&real, &scaled_dual), &real);
    Unit {
        real,
        dual,
        scaled_dual,
        norm: L::select(live, n, L::zero()),
    }
}

/// The deformed mean and rotation of a Gaussian at `mean` with rotation `quat`, given its
/// weights and its parts' signs ([`Motions::align`]).
#[inline(always)]
pub fn forward_one<L: Lane>(
    mean: &Vec3<L>,
    quat: &Quat<L>,
    weights: &[L],
    signs: &[L],
    motions: &Motions<L>,
) -> (Vec3<L>, Quat<L>) {
    let (br, bd) = mix(weights, signs, motions);
    let u = normalise(&br, &bd);
    // Translation 2 vec(dual * conj(real)).
    let p = mul(&u.dual, &conj(&u.real));
    let r = rotate(&u.real, mean);
    let t = two::<L>();
    (
        [r[0] + t * p[1], r[1] + t * p[2], r[2] + t * p[3]],
        mul(&u.real, quat),
    )
}

/// Where one Gaussian's backward writes besides its mean's and rotation's gradients (which
/// it returns): its weights' gradients, and the motions' (summed into).
pub struct GradientsOne<'a, L> {
    pub weights: &'a mut [L],
    /// Rotation then dual halves of every part ([2K] quaternions), added to; None when the
    /// motions are held.
    pub motions: Option<&'a mut [Quat<L>]>,
}

/// Backward of [`forward_one`] for upstream gradients `grad_mean`, `grad_quat`: returns the
/// gradients to the mean and the rotation.
#[inline(always)]
pub fn backward_one<L: Lane>(
    (mean, quat): (&Vec3<L>, &Quat<L>),
    (weights, signs): (&[L], &[L]),
    motions: &Motions<L>,
    (grad_mean, grad_quat): (&Vec3<L>, &Quat<L>),
    out: GradientsOne<L>,
) -> (Vec3<L>, Quat<L>) {
    let (br, bd) = mix(weights, signs, motions);
    let u = normalise(&br, &bd);
    let t = two::<L>();
    // quat' = real * quat.
    let g_quat = mul(&conj(&u.real), grad_quat);
    let mut g_real = mul(grad_quat, &conj(quat));
    // mean' = rotate(real, mean) + 2 vec(dual * conj(real)).
    let (g_rot, g_mean) = rotate_backward(&u.real, mean, grad_mean);
    g_real = add_scaled(&g_real, L::one(), &g_rot);
    let gp = [
        L::zero(),
        t * grad_mean[0],
        t * grad_mean[1],
        t * grad_mean[2],
    ];
    let g_dual = mul(&gp, &u.real);
    g_real = add_scaled(&g_real, L::one(), &conj(&mul(&conj(&u.dual), &gp)));
    // dual = scaled_dual - (real . scaled_dual) real.
    let along = dot(&u.real, &g_dual);
    let g_scaled_dual = add_scaled(&g_dual, -along, &u.real);
    let d = dot(&u.real, &u.scaled_dual);
    g_real = add_scaled(&g_real, -along, &u.scaled_dual);
    g_real = add_scaled(&g_real, -d, &g_dual);
    // real = br / |br|, scaled_dual = bd / |br| (on lanes whose mix vanished: real is a
    // constant, scaled_dual = bd).
    let live = u.norm.gt(L::zero());
    let radial = dot(&g_real, &u.real) + dot(&g_scaled_dual, &u.scaled_dual);
    let inv = L::one() / u.norm;
    let g_br = select(
        live,
        &scale(inv, &add_scaled(&g_real, -radial, &u.real)),
        &[L::zero(); 4],
    );
    let g_bd = select(live, &scale(inv, &g_scaled_dual), &g_scaled_dual);
    let mut motion_grads = out.motions;
    for (k, ((&w, &s), gw)) in weights.iter().zip(signs).zip(out.weights).enumerate() {
        *gw = s * (dot(&g_br, &motions.qr[k]) + dot(&g_bd, &motions.qd[k]));
        if let Some(m) = motion_grads.as_deref_mut() {
            let parts = m.len() / 2;
            m[k] = add_scaled(&m[k], w * s, &g_br);
            m[parts + k] = add_scaled(&m[parts + k], w * s, &g_bd);
        }
    }
    (g_mean, g_quat)
}
