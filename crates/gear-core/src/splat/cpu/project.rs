//! The per-Gaussian stage of the contract in f32, as project_common.wgsl, project.wgsl and
//! project_backward.wgsl compute it: culling, the EWA projection with the low-pass, the conic,
//! the opacity level of the 1/255 cut-off, and the backward chain from screen-space gradients
//! to the four geometric input arrays. The backward redoes the arithmetic part of the
//! projection from what the forward kept of it ([`Prepared`]), exactly as the forward did it.

use glam::{Mat3, Vec2, Vec3, Vec4};

use crate::splat::constants::{CLAMP_FACTOR, FAR, LOW_PASS, MIN_ALPHA, NEAR, QUAT_EPS};
use crate::splat::types::{Camera, Gaussians};

const LP: f32 = LOW_PASS as f32;

/// The camera as the per-Gaussian stage uses it.
#[derive(Debug, Clone, Copy)]
pub(super) struct View {
    /// World-to-camera rotation W and translation.
    pub w_rot: Mat3,
    pub trans: Vec3,
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    /// |x/z|, |y/z| limits of the Jacobian clamp.
    pub limits: Vec2,
}

impl View {
    pub fn new(camera: &Camera) -> Self {
        let w = &camera.world_to_cam;
        let limit = |size: u32, focal: f32| {
            (CLAMP_FACTOR * 0.5 * f64::from(size) / f64::from(focal)) as f32
        };
        View {
            w_rot: Mat3::from_cols(
                Vec3::new(w[0][0], w[1][0], w[2][0]),
                Vec3::new(w[0][1], w[1][1], w[2][1]),
                Vec3::new(w[0][2], w[1][2], w[2][2]),
            ),
            trans: Vec3::new(w[0][3], w[1][3], w[2][3]),
            fx: camera.fx,
            fy: camera.fy,
            cx: camera.cx,
            cy: camera.cy,
            limits: Vec2::new(
                limit(camera.width, camera.fx),
                limit(camera.height, camera.fy),
            ),
        }
    }
}

/// A Gaussian that survived culling, with what the backward chain needs.
#[derive(Debug, Clone, Copy)]
pub(super) struct Projection {
    /// Camera-space centre.
    pub t: Vec3,
    /// Normalised quaternion (w, x, y, z) and the raw quaternion's norm.
    pub qn: Vec4,
    pub qnorm: f32,
    pub rot: Mat3,
    pub scale: Vec3,
    /// Rows of the clamped Jacobian, and whether x', y' were clamped.
    pub j0: Vec3,
    pub j1: Vec3,
    pub clamped: [bool; 2],
    /// K = W R diag(s) and the rows of P = J K.
    pub k: Mat3,
    pub p0: Vec3,
    pub p1: Vec3,
    /// Σ2D = (a, b, c), its determinant, and the conic (its inverse).
    pub cov: Vec3,
    pub det: f32,
    pub conic: Vec3,
    pub mean2d: Vec2,
    pub opacity: f32,
}

impl Projection {
    /// 2 ln(255 o): beyond this dᵀ conic d, alpha is below 1/255.
    pub fn level(&self) -> f32 {
        2.0 * (self.opacity / MIN_ALPHA as f32).ln().max(0.0)
    }
}

/// R(q) for a unit quaternion (w, x, y, z).
fn rotation(q: Vec4) -> Mat3 {
    let (w, x, y, z) = (q.x, q.y, q.z, q.w);
    Mat3::from_cols(
        Vec3::new(
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y + w * z),
            2.0 * (x * z - w * y),
        ),
        Vec3::new(
            2.0 * (x * y - w * z),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z + w * x),
        ),
        Vec3::new(
            2.0 * (x * z + w * y),
            2.0 * (y * z - w * x),
            1.0 - 2.0 * (x * x + y * y),
        ),
    )
}

/// What the projection of a Gaussian keeps of its inputs after culling: everything that needs a
/// transcendental function or a check of the inputs. The backward keeps one per Gaussian so
/// that it can redo the rest of the projection ([`Prepared::project`]) from it.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Prepared {
    /// Camera-space centre.
    pub t: Vec3,
    /// Normalised quaternion (w, x, y, z) and the raw quaternion's norm.
    pub qn: Vec4,
    pub qnorm: f32,
    pub scale: Vec3,
    pub opacity: f32,
}

impl Prepared {
    /// Gaussian `i` seen by `view`, or None when the contract culls it before its footprint.
    #[inline(always)]
    pub fn new(g: &Gaussians, i: usize, view: &View) -> Option<Prepared> {
        let m = Vec3::from(g.means[i]);
        let q = Vec4::from(g.quats[i]);
        let ls = Vec3::from(g.log_scales[i]);
        let logit = g.opacity_logits[i];
        let features = &g.features[i * g.channels..(i + 1) * g.channels];
        let finite = m.is_finite()
            && q.is_finite()
            && ls.is_finite()
            && logit.is_finite()
            && features.iter().all(|f| f.is_finite());
        if !finite {
            return None;
        }
        let t = view.w_rot * m + view.trans;
        let opacity = 1.0 / (1.0 + (-logit).exp());
        if !(t.z >= NEAR as f32 && t.z <= FAR as f32 && opacity >= MIN_ALPHA as f32) {
            return None;
        }
        let qnorm = q.length();
        Some(Prepared {
            t,
            qn: q / qnorm.max(QUAT_EPS as f32),
            qnorm,
            scale: Vec3::new(ls.x.exp(), ls.y.exp(), ls.z.exp()),
            opacity,
        })
    }

    /// The rest of the projection (the footprint), or None when the contract culls it: the
    /// same operations whenever it is called, so the backward's footprint is the forward's.
    #[inline(always)]
    pub fn project(&self, view: &View) -> Option<Projection> {
        let Prepared {
            t,
            qn,
            qnorm,
            scale,
            opacity,
        } = *self;
        let rot = rotation(qn);
        let k = view.w_rot
            * Mat3::from_cols(
                rot.x_axis * scale.x,
                rot.y_axis * scale.y,
                rot.z_axis * scale.z,
            );
        let (fx, fy) = (view.fx, view.fy);
        let z = t.z;
        let (rx, ry) = (t.x / z, t.y / z);
        let lim = view.limits;
        let clamped = [rx.abs() > lim.x, ry.abs() > lim.y];
        let xc = z * rx.max(-lim.x).min(lim.x);
        let yc = z * ry.max(-lim.y).min(lim.y);
        let j0 = Vec3::new(fx / z, 0.0, -fx * xc / (z * z));
        let j1 = Vec3::new(0.0, fy / z, -fy * yc / (z * z));
        let p0 = k.transpose() * j0;
        let p1 = k.transpose() * j1;
        let cov = Vec3::new(p0.dot(p0) + LP, p0.dot(p1), p1.dot(p1) + LP);
        // det(P Pᵀ + λI) without the cancellation of a·c - b² (as project_common.wgsl).
        let cr = p0.cross(p1);
        let det = cr.dot(cr) + LP * (cov.x + cov.z - 2.0 * LP) + LP * LP;
        if !(det > 0.0 && det.is_finite()) {
            return None;
        }
        let conic = Vec3::new(cov.z / det, -cov.y / det, cov.x / det);
        let mean2d = Vec2::new(fx * t.x / z + view.cx, fy * t.y / z + view.cy);
        if !(mean2d.is_finite() && conic.is_finite()) {
            return None;
        }
        Some(Projection {
            t,
            qn,
            qnorm,
            rot,
            scale,
            j0,
            j1,
            clamped,
            k,
            p0,
            p1,
            cov,
            det,
            conic,
            mean2d,
            opacity,
        })
    }
}

/// Screen-space gradients of one Gaussian: conic a, b, c, mean u, v, opacity, z.
pub(super) type ScreenGradients = [f32; 7];

/// Gradients of one Gaussian's inputs: means 3, quats 4, log_scales 3, opacity logit.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(super) struct InputGradients {
    pub mean: [f32; 3],
    pub quat: [f32; 4],
    pub log_scale: [f32; 3],
    pub logit: f32,
}

/// dL/dq_n from dL/dR for R = rotation(q_n); `g.col(c)[r]` is dL/dR[r][c].
fn rotation_backward(q: Vec4, g: Mat3) -> Vec4 {
    let (w, x, y, z) = (q.x, q.y, q.z, q.w);
    let e = |r: usize, c: usize| g.col(c)[r];
    let (g00, g01, g02) = (e(0, 0), e(0, 1), e(0, 2));
    let (g10, g11, g12) = (e(1, 0), e(1, 1), e(1, 2));
    let (g20, g21, g22) = (e(2, 0), e(2, 1), e(2, 2));
    let dw = -z * g01 + y * g02 + z * g10 - x * g12 - y * g20 + x * g21;
    let dx =
        y * g01 + z * g02 + y * g10 - 2.0 * x * g11 - w * g12 + z * g20 + w * g21 - 2.0 * x * g22;
    let dy =
        -2.0 * y * g00 + x * g01 + w * g02 + x * g10 + z * g12 - w * g20 + z * g21 - 2.0 * y * g22;
    let dz =
        -2.0 * z * g00 - w * g01 + x * g02 + w * g10 - 2.0 * z * g11 + y * g12 + x * g20 + y * g21;
    2.0 * Vec4::new(dw, dx, dy, dz)
}

/// The backward of [`project`]: screen-space gradients `s` of projection `p` to the inputs.
pub(super) fn project_backward(p: &Projection, s: &ScreenGradients, view: &View) -> InputGradients {
    let [ga, gb, gc, gu, gv, g_opacity, g_depth] = *s;
    // conic = Σ2D⁻¹ => dL/dΣ2D = -conic G conic, written with conic entries.
    let (a, b, c) = (p.conic.x, p.conic.y, p.conic.z);
    let g_cov_a = -ga * a * a - gb * a * b - gc * b * b;
    let g_cov_c = -ga * b * b - gb * b * c - gc * c * c;
    let g_cov_b = -2.0 * ga * a * b - gb * (a * c + b * b) - 2.0 * gc * b * c;
    let g_p0 = 2.0 * g_cov_a * p.p0 + g_cov_b * p.p1;
    let g_p1 = g_cov_b * p.p0 + 2.0 * g_cov_c * p.p1;
    let g_j0 = p.k * g_p0;
    let g_j1 = p.k * g_p1;
    let g_k = Mat3::from_cols(
        p.j0 * g_p0.x + p.j1 * g_p1.x,
        p.j0 * g_p0.y + p.j1 * g_p1.y,
        p.j0 * g_p0.z + p.j1 * g_p1.z,
    );
    let g_m = view.w_rot.transpose() * g_k;
    let g_rot = Mat3::from_cols(
        g_m.x_axis * p.scale.x,
        g_m.y_axis * p.scale.y,
        g_m.z_axis * p.scale.z,
    );
    let g_scale = Vec3::new(
        g_m.x_axis.dot(p.rot.x_axis),
        g_m.y_axis.dot(p.rot.y_axis),
        g_m.z_axis.dot(p.rot.z_axis),
    );
    let g_qn = rotation_backward(p.qn, g_rot);
    let g_quat = if p.qnorm > QUAT_EPS as f32 {
        (g_qn - p.qn * p.qn.dot(g_qn)) / p.qnorm
    } else {
        g_qn / QUAT_EPS as f32
    };

    // t enters through the 2D mean, the Jacobian (x', y' constant when clamped) and depth.
    let (fx, fy) = (view.fx, view.fy);
    let t = p.t;
    let z2 = t.z * t.z;
    let xc = -p.j0.z * z2 / fx;
    let yc = -p.j1.z * z2 / fy;
    let mut g_t = Vec3::new(
        gu * fx / t.z,
        gv * fy / t.z,
        -(gu * fx * t.x + gv * fy * t.y) / z2 + g_depth,
    );
    g_t.z += -g_j0.x * fx / z2 + 2.0 * g_j0.z * fx * xc / (z2 * t.z) - g_j1.y * fy / z2
        + 2.0 * g_j1.z * fy * yc / (z2 * t.z);
    if !p.clamped[0] {
        g_t.x -= g_j0.z * fx / z2;
    }
    if !p.clamped[1] {
        g_t.y -= g_j1.z * fy / z2;
    }
    let g_mean = view.w_rot.transpose() * g_t;
    InputGradients {
        mean: g_mean.to_array(),
        quat: g_quat.to_array(),
        log_scale: (g_scale * p.scale).to_array(),
        logit: g_opacity * p.opacity * (1.0 - p.opacity),
    }
}
