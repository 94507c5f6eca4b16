//! The per-Gaussian stage of the contract in f32, as project_common.wgsl, project.wgsl and
//! project_backward.wgsl compute it: culling, the EWA projection with the low-pass, the conic,
//! and the backward chain from screen-space gradients to the four geometric input arrays.
//! Eight Gaussians at a time, one per SIMD lane ([`F8`]). The backward redoes the arithmetic
//! part of the projection from what the forward kept of it ([`Prepared`]), with the same
//! operations, so it sees exactly the forward's footprint.

// Lane loops index several [f32; 8] arrays in step: the form the compiler vectorises.
#![allow(clippy::needless_range_loop)]

use super::lanes::{array, mask, Mask, LANES};
use super::wide::{and, cross, dot, F8, V3};
use crate::splat::constants::{CLAMP_FACTOR, FAR, LOW_PASS, MIN_ALPHA, NEAR, QUAT_EPS};
use crate::splat::types::{Camera, Gaussians};

const LP: f32 = LOW_PASS as f32;
const EPS: f32 = QUAT_EPS as f32;

/// The camera as the per-Gaussian stage uses it.
#[derive(Debug, Clone, Copy)]
pub(super) struct View {
    /// World-to-camera rotation W (`w[row][column]`) and translation.
    pub w: [[f32; 3]; 3],
    pub trans: [f32; 3],
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    /// |x/z|, |y/z| limits of the Jacobian clamp.
    pub limits: [f32; 2],
}

impl View {
    pub fn new(camera: &Camera) -> Self {
        let w = &camera.world_to_cam;
        let limit = |size: u32, focal: f32| {
            (CLAMP_FACTOR * 0.5 * f64::from(size) / f64::from(focal)) as f32
        };
        View {
            w: array(|r| [w[r][0], w[r][1], w[r][2]]),
            trans: [w[0][3], w[1][3], w[2][3]],
            fx: camera.fx,
            fy: camera.fy,
            cx: camera.cx,
            cy: camera.cy,
            limits: [
                limit(camera.width, camera.fx),
                limit(camera.height, camera.fy),
            ],
        }
    }

    /// W v.
    #[inline(always)]
    fn rotate(&self, v: &V3) -> V3 {
        array(|r| self.w[r][0] * v[0] + self.w[r][1] * v[1] + self.w[r][2] * v[2])
    }

    /// Wᵀ v.
    #[inline(always)]
    fn rotate_back(&self, v: &V3) -> V3 {
        array(|c| self.w[0][c] * v[0] + self.w[1][c] * v[1] + self.w[2][c] * v[2])
    }
}

/// What the projection of eight Gaussians keeps of their inputs: everything that needs a
/// transcendental function or a check of the inputs. The backward keeps one per eight
/// Gaussians so that it can redo the rest of the projection ([`Prepared::project`]).
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Prepared {
    /// Camera-space centre.
    pub t: V3,
    /// Normalised quaternion (w, x, y, z) and the raw quaternion's norm.
    pub qn: [F8; 4],
    pub qnorm: F8,
    pub scale: V3,
    pub opacity: F8,
    /// Lanes with finite inputs that pass the depth and opacity culls (all ones).
    pub valid: Mask,
}

/// A block of eight Gaussians projected (culled lanes hold anything; `valid` is zero there).
#[derive(Debug, Clone, Copy)]
pub(super) struct Projection {
    pub t: V3,
    pub qn: [F8; 4],
    pub qnorm: F8,
    /// R(qn), `rot[row][column]`.
    pub rot: [V3; 3],
    pub scale: V3,
    /// The non-zero entries of the clamped Jacobian's rows (fx/z, 0, j0z), (0, fy/z, j1z),
    /// and where x', y' were clamped.
    pub j0x: F8,
    pub j0z: F8,
    pub j1y: F8,
    pub j1z: F8,
    pub clamped: [Mask; 2],
    /// K = W R diag(s) (`k[row][column]`) and the rows of P = J K.
    pub k: [V3; 3],
    pub p0: V3,
    pub p1: V3,
    /// Σ2D = (a, b, c), its determinant, and the conic (its inverse).
    pub cov: V3,
    pub det: F8,
    pub conic: V3,
    pub mean2d: [F8; 2],
    pub opacity: F8,
    pub valid: Mask,
}

/// One lane of a [`Projection`]: what the blend and binning read of a Gaussian.
#[derive(Debug, Clone, Copy)]
pub(super) struct Screen {
    pub mean2d: [f32; 2],
    pub cov: [f32; 3],
    pub det: f32,
    pub conic: [f32; 3],
    pub opacity: f32,
    pub z: f32,
}

impl Screen {
    /// 2 ln(255 o): beyond this dᵀ conic d, alpha is below 1/255.
    pub fn level(&self) -> f32 {
        2.0 * (self.opacity / MIN_ALPHA as f32).ln().max(0.0)
    }
}

/// R(q) for unit quaternions (w, x, y, z), `[row][column]`.
#[inline(always)]
fn rotation(q: &[F8; 4]) -> [V3; 3] {
    let [w, x, y, z] = *q;
    [
        [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y - w * z),
            2.0 * (x * z + w * y),
        ],
        [
            2.0 * (x * y + w * z),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z - w * x),
        ],
        [
            2.0 * (x * z - w * y),
            2.0 * (y * z + w * x),
            1.0 - 2.0 * (x * x + y * y),
        ],
    ]
}

/// All ones where every lane of `values` is finite.
#[inline(always)]
fn all_finite(values: &[F8]) -> Mask {
    values
        .iter()
        .fold([u32::MAX; LANES], |m, v| and(m, v.finite()))
}

impl Prepared {
    /// Gaussians `first..first + 8` (lanes past the end are culled) seen by `view`.
    #[inline(always)]
    pub fn new(g: &Gaussians, first: usize, view: &View) -> Self {
        let (mut m, mut q, mut ls, mut logit) = (
            [F8::default(); 3],
            [F8::default(); 4],
            [F8::default(); 3],
            F8::default(),
        );
        let mut features_finite = [0u32; LANES];
        for i in 0..LANES.min(g.len().saturating_sub(first)) {
            let idx = first + i;
            for c in 0..3 {
                m[c].0[i] = g.means[idx][c];
                ls[c].0[i] = g.log_scales[idx][c];
            }
            for c in 0..4 {
                q[c].0[i] = g.quats[idx][c];
            }
            logit.0[i] = g.opacity_logits[idx];
            let features = &g.features[idx * g.channels..(idx + 1) * g.channels];
            features_finite[i] = mask(features.iter().all(|f| f.is_finite()));
        }
        let finite = and(
            features_finite,
            all_finite(&[
                m[0], m[1], m[2], q[0], q[1], q[2], q[3], ls[0], ls[1], ls[2], logit,
            ]),
        );
        let rotated = view.rotate(&m);
        let t: V3 = array(|r| rotated[r] + view.trans[r]);
        let opacity = 1.0 / (1.0 + (-logit).exp());
        let valid = and(
            and(finite, t[2].ge(F8::splat(NEAR as f32))),
            and(
                t[2].le(F8::splat(FAR as f32)),
                opacity.ge(F8::splat(MIN_ALPHA as f32)),
            ),
        );
        let qnorm = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
        let denominator = qnorm.max(F8::splat(EPS));
        Prepared {
            t,
            qn: array(|c| q[c] / denominator),
            qnorm,
            scale: array(|c| ls[c].exp()),
            opacity,
            valid,
        }
    }

    /// The rest of the projection (the footprint) and the lanes the contract keeps: the same
    /// operations whenever it is called, so the backward's footprint is the forward's.
    #[inline(always)]
    pub fn project(&self, view: &View) -> Projection {
        let Prepared {
            t,
            qn,
            qnorm,
            scale,
            opacity,
            valid,
        } = *self;
        let rot = rotation(&qn);
        // K = W M with M = R diag(s). Plain loops: closures nested in closures are not inlined.
        let mut m = [[F8::default(); 3]; 3];
        for r in 0..3 {
            for c in 0..3 {
                m[r][c] = rot[r][c] * scale[c];
            }
        }
        let mut k = [[F8::default(); 3]; 3];
        for r in 0..3 {
            for c in 0..3 {
                k[r][c] = view.w[r][0] * m[0][c] + view.w[r][1] * m[1][c] + view.w[r][2] * m[2][c];
            }
        }
        let (fx, fy) = (view.fx, view.fy);
        let z = t[2];
        let (rx, ry) = (t[0] / z, t[1] / z);
        let (lx, ly) = (F8::splat(view.limits[0]), F8::splat(view.limits[1]));
        let clamped = [rx.abs().gt(lx), ry.abs().gt(ly)];
        let xc = z * rx.max(-lx).min(lx);
        let yc = z * ry.max(-ly).min(ly);
        let (j0x, j0z) = (fx / z, -fx * xc / (z * z));
        let (j1y, j1z) = (fy / z, -fy * yc / (z * z));
        let p0: V3 = array(|c| k[0][c] * j0x + k[2][c] * j0z);
        let p1: V3 = array(|c| k[1][c] * j1y + k[2][c] * j1z);
        let cov = [dot(&p0, &p0) + LP, dot(&p0, &p1), dot(&p1, &p1) + LP];
        // det(P Pᵀ + λI) without the cancellation of a·c - b² (as project_common.wgsl).
        let cr = cross(&p0, &p1);
        let det = dot(&cr, &cr) + LP * (cov[0] + cov[2] - 2.0 * LP) + LP * LP;
        let conic = [cov[2] / det, -cov[1] / det, cov[0] / det];
        let mean2d = [fx * t[0] / z + view.cx, fy * t[1] / z + view.cy];
        let valid = and(
            and(valid, det.gt(F8::default())),
            all_finite(&[det, conic[0], conic[1], conic[2], mean2d[0], mean2d[1]]),
        );
        Projection {
            t,
            qn,
            qnorm,
            rot,
            scale,
            j0x,
            j0z,
            j1y,
            j1z,
            clamped,
            k,
            p0,
            p1,
            cov,
            det,
            conic,
            mean2d,
            opacity,
            valid,
        }
    }
}

impl Projection {
    /// Lane `i`.
    pub fn screen(&self, i: usize) -> Screen {
        Screen {
            mean2d: array(|c| self.mean2d[c].0[i]),
            cov: array(|c| self.cov[c].0[i]),
            det: self.det.0[i],
            conic: array(|c| self.conic[c].0[i]),
            opacity: self.opacity.0[i],
            z: self.t[2].0[i],
        }
    }
}

/// Screen-space gradients of eight Gaussians: conic a, b, c, mean u, v, opacity, z.
pub(super) type ScreenGradients = [F8; 7];

/// Gradients of eight Gaussians' inputs: means 3, quats 4, log_scales 3, opacity logit.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct InputGradients {
    pub mean: V3,
    pub quat: [F8; 4],
    pub log_scale: V3,
    pub logit: F8,
}

/// dL/dq_n from dL/dR (`g[row][column]`) for R = rotation(q_n).
#[inline(always)]
fn rotation_backward(q: &[F8; 4], g: &[V3; 3]) -> [F8; 4] {
    let [w, x, y, z] = *q;
    let [[g00, g01, g02], [g10, g11, g12], [g20, g21, g22]] = *g;
    let dw = -z * g01 + y * g02 + z * g10 - x * g12 - y * g20 + x * g21;
    let dx =
        y * g01 + z * g02 + y * g10 - 2.0 * x * g11 - w * g12 + z * g20 + w * g21 - 2.0 * x * g22;
    let dy =
        -2.0 * y * g00 + x * g01 + w * g02 + x * g10 + z * g12 - w * g20 + z * g21 - 2.0 * y * g22;
    let dz =
        -2.0 * z * g00 - w * g01 + x * g02 + w * g10 - 2.0 * z * g11 + y * g12 + x * g20 + y * g21;
    [2.0 * dw, 2.0 * dx, 2.0 * dy, 2.0 * dz]
}

/// The backward of [`Prepared::project`]: screen-space gradients `s` of projection `p` to the
/// inputs.
#[inline(always)]
pub(super) fn project_backward(p: &Projection, s: &ScreenGradients, view: &View) -> InputGradients {
    let [ga, gb, gc, gu, gv, g_opacity, g_depth] = *s;
    // conic = Σ2D⁻¹ => dL/dΣ2D = -conic G conic, written with conic entries.
    let [a, b, c] = p.conic;
    let g_cov_a = -ga * a * a - gb * a * b - gc * b * b;
    let g_cov_c = -ga * b * b - gb * b * c - gc * c * c;
    let g_cov_b = -2.0 * ga * a * b - gb * (a * c + b * b) - 2.0 * gc * b * c;
    let g_p0: V3 = array(|i| 2.0 * g_cov_a * p.p0[i] + g_cov_b * p.p1[i]);
    let g_p1: V3 = array(|i| g_cov_b * p.p0[i] + 2.0 * g_cov_c * p.p1[i]);
    let g_j0 = [dot(&p.k[0], &g_p0), dot(&p.k[2], &g_p0)];
    let g_j1 = [dot(&p.k[1], &g_p1), dot(&p.k[2], &g_p1)];
    // dL/dK[r][c] = J0[r] dL/dP0[c] + J1[r] dL/dP1[c], with J's zeros left out.
    let g_k: [V3; 3] = [
        array(|c| p.j0x * g_p0[c]),
        array(|c| p.j1y * g_p1[c]),
        array(|c| p.j0z * g_p0[c] + p.j1z * g_p1[c]),
    ];
    // dL/dM = Wᵀ dL/dK, column by column.
    let g_m_cols: [V3; 3] = array(|c| view.rotate_back(&[g_k[0][c], g_k[1][c], g_k[2][c]]));
    let mut g_rot = [[F8::default(); 3]; 3];
    for r in 0..3 {
        for c in 0..3 {
            g_rot[r][c] = g_m_cols[c][r] * p.scale[c];
        }
    }
    let g_scale: V3 = array(|c| {
        g_m_cols[c][0] * p.rot[0][c] + g_m_cols[c][1] * p.rot[1][c] + g_m_cols[c][2] * p.rot[2][c]
    });
    let g_qn = rotation_backward(&p.qn, &g_rot);
    let qn = &p.qn;
    let along = qn[0] * g_qn[0] + qn[1] * g_qn[1] + qn[2] * g_qn[2] + qn[3] * g_qn[3];
    let normal = p.qnorm.gt(F8::splat(EPS));
    let g_quat: [F8; 4] =
        array(|i| ((g_qn[i] - qn[i] * along) / p.qnorm).select(normal, g_qn[i] / EPS));

    // t enters through the 2D mean, the Jacobian (x', y' constant when clamped) and depth.
    let (fx, fy) = (view.fx, view.fy);
    let t = p.t;
    let z2 = t[2] * t[2];
    let xc = -p.j0z * z2 / fx;
    let yc = -p.j1z * z2 / fy;
    let mut g_t = [
        gu * fx / t[2],
        gv * fy / t[2],
        -(gu * fx * t[0] + gv * fy * t[1]) / z2 + g_depth,
    ];
    g_t[2] = g_t[2]
        + (-g_j0[0] * fx / z2 + 2.0 * g_j0[1] * fx * xc / (z2 * t[2]) - g_j1[0] * fy / z2
            + 2.0 * g_j1[1] * fy * yc / (z2 * t[2]));
    g_t[0] = g_t[0].select(p.clamped[0], g_t[0] - g_j0[1] * fx / z2);
    g_t[1] = g_t[1].select(p.clamped[1], g_t[1] - g_j1[1] * fy / z2);
    InputGradients {
        mean: view.rotate_back(&g_t),
        quat: g_quat,
        log_scale: array(|c| g_scale[c] * p.scale[c]),
        logit: g_opacity * p.opacity * (1.0 - p.opacity),
    }
}
