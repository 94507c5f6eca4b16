//! The rasterizer contract on the CPU in f64: forward and analytic backward, written for clarity.
//!
//! This is the yardstick of the GPU kernels' parity tests, so it follows the contract
//! (`docs/raster-contract.md`) step by step and favours plain code over speed: every
//! Gaussian is tested against every pixel of its tile rectangle, per-tile lists are sorted by
//! depth, and the backward pass replays each pixel's blend from back to front.
//!
//! Entry points: [`forward`] and [`backward`]. Inputs are the f32 arrays the GPU sees; every
//! computation (and every output) is f64.

use glam::{DMat2, DMat3, DVec2, DVec3};
use rayon::prelude::*;

use super::constants::{
    CLAMP_FACTOR, FAR, LOW_PASS, MAX_ALPHA, MIN_ALPHA, MIN_TRANSMITTANCE, NEAR, QUAT_EPS, TILE,
};
use super::types::{
    Camera, GaussianGradients, Gaussians, OutputGradients, RenderOptions, RenderOutput,
};
use crate::error::Result;

/// Renders `gaussians` seen by `camera`: the forward pass of the contract, in f64.
pub fn forward(
    gaussians: &Gaussians,
    camera: &Camera,
    options: &RenderOptions,
) -> Result<RenderOutput<f64>> {
    validate(gaussians, camera, options)?;
    let scene = Scene::new(gaussians);
    let view = View::new(camera);
    let background = widen(&options.background);
    Ok(render(
        &scene,
        &view,
        &background,
        options.depth,
        Cutoff::Hard,
    ))
}

/// Gradients of a loss with respect to every Gaussian input, given the gradients of the loss
/// with respect to the images [`forward`] renders for the same arguments.
pub fn backward(
    gaussians: &Gaussians,
    camera: &Camera,
    options: &RenderOptions,
    grads: &OutputGradients<f64>,
) -> Result<GaussianGradients<f64>> {
    validate(gaussians, camera, options)?;
    grads.validate(camera.pixels(), gaussians.channels)?;
    let scene = Scene::new(gaussians);
    let view = View::new(camera);
    let background = widen(&options.background);
    // Without a depth image there is no depth gradient to apply.
    let image_grads = OutputGradients {
        depth: grads.depth.filter(|_| options.depth),
        ..*grads
    };
    Ok(gradients(
        &scene,
        &view,
        &background,
        &image_grads,
        Cutoff::Hard,
    ))
}

fn validate(gaussians: &Gaussians, camera: &Camera, options: &RenderOptions) -> Result<()> {
    camera.validate()?;
    gaussians.validate()?;
    options.validate(gaussians.channels)
}

fn widen(values: &[f32]) -> Vec<f64> {
    values.iter().map(|&v| f64::from(v)).collect()
}

/// How alphas below [`MIN_ALPHA`] are dropped. The contract's hard skip is a step, so finite
/// differences cannot check it; the gradient tests swap in a C² ramp that is zero wherever the
/// hard skip applies (so tile rectangles still bound every contribution) and only that.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Cutoff {
    Hard,
    #[cfg(test)]
    Smooth,
}

/// The camera in f64.
struct View {
    rot: DMat3,
    trans: DVec3,
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    width: usize,
    height: usize,
    /// |x/z| and |y/z| beyond which the Jacobian is evaluated at the clamped direction.
    clamp: DVec2,
}

impl View {
    fn new(camera: &Camera) -> Self {
        let m = camera.world_to_cam.map(|row| row.map(f64::from));
        let rows = [
            [m[0][0], m[0][1], m[0][2]],
            [m[1][0], m[1][1], m[1][2]],
            [m[2][0], m[2][1], m[2][2]],
        ];
        let (fx, fy) = (f64::from(camera.fx), f64::from(camera.fy));
        let (width, height) = (camera.width as usize, camera.height as usize);
        Self {
            rot: mat_from_rows(rows),
            trans: DVec3::new(m[0][3], m[1][3], m[2][3]),
            fx,
            fy,
            cx: f64::from(camera.cx),
            cy: f64::from(camera.cy),
            width,
            height,
            clamp: DVec2::new(
                CLAMP_FACTOR * 0.5 * width as f64 / fx,
                CLAMP_FACTOR * 0.5 * height as f64 / fy,
            ),
        }
    }

    fn tiles_x(&self) -> usize {
        self.width.div_ceil(TILE as usize)
    }

    fn tiles_y(&self) -> usize {
        self.height.div_ceil(TILE as usize)
    }
}

/// The Gaussians in f64 (the finite-difference tests perturb these directly).
#[derive(Debug, Clone)]
struct Scene {
    means: Vec<DVec3>,
    /// (w, x, y, z), unnormalised.
    quats: Vec<[f64; 4]>,
    log_scales: Vec<DVec3>,
    opacity_logits: Vec<f64>,
    /// N x channels, row-major.
    features: Vec<f64>,
    channels: usize,
}

impl Scene {
    fn new(g: &Gaussians) -> Self {
        let vec3 = |v: &[f32; 3]| DVec3::new(v[0].into(), v[1].into(), v[2].into());
        Self {
            means: g.means.iter().map(vec3).collect(),
            quats: g.quats.iter().map(|q| q.map(f64::from)).collect(),
            log_scales: g.log_scales.iter().map(vec3).collect(),
            opacity_logits: widen(g.opacity_logits),
            features: widen(g.features),
            channels: g.channels,
        }
    }

    fn len(&self) -> usize {
        self.means.len()
    }

    fn feature(&self, i: usize) -> &[f64] {
        &self.features[i * self.channels..(i + 1) * self.channels]
    }

    /// True when every input value of Gaussian `i` is finite (the others are culled).
    fn is_finite(&self, i: usize) -> bool {
        self.means[i].is_finite()
            && self.quats[i].iter().all(|v| v.is_finite())
            && self.log_scales[i].is_finite()
            && self.opacity_logits[i].is_finite()
            && self.feature(i).iter().all(|v| v.is_finite())
    }
}

/// Inclusive ranges of the tiles a Gaussian may touch.
#[derive(Debug, Clone, Copy)]
struct TileRect {
    x: (usize, usize),
    y: (usize, usize),
}

impl TileRect {
    /// Tiles overlapping the box [u ± r] x [v ± r], clipped to the image; None when empty.
    fn around(center: DVec2, radius: f64, view: &View) -> Option<Self> {
        let span = |c: f64, tiles: usize| {
            let lo = ((c - radius) / f64::from(TILE)).floor().max(0.0);
            let hi = ((c + radius) / f64::from(TILE))
                .floor()
                .min(tiles as f64 - 1.0);
            (lo <= hi).then_some((lo as usize, hi as usize))
        };
        Some(Self {
            x: span(center.x, view.tiles_x())?,
            y: span(center.y, view.tiles_y())?,
        })
    }

    fn contains(&self, tile_x: usize, tile_y: usize) -> bool {
        (self.x.0..=self.x.1).contains(&tile_x) && (self.y.0..=self.y.1).contains(&tile_y)
    }
}

/// A Gaussian that survived culling, with every intermediate the backward pass needs.
#[derive(Debug, Clone)]
struct Projected {
    index: usize,
    /// Camera-space mean; `t.z` is the depth.
    t: DVec3,
    /// R(q_n), exp(log_scales) and M = R diag(s), so that Σ = M Mᵀ.
    rot: DMat3,
    scale: DVec3,
    cov3d_factor: DMat3,
    cov3d: DMat3,
    /// Rows of the clamped Jacobian J and whether x' (resp. y') was clamped.
    jacobian: [DVec3; 2],
    clamped: [bool; 2],
    /// Rows of J W_rot.
    jw: [DVec3; 2],
    /// inverse(Σ2D), low-pass included.
    conic: DMat2,
    mean2d: DVec2,
    opacity: f64,
    tiles: TileRect,
}

/// R(q) for a unit quaternion (w, x, y, z), the contract's formula.
fn rotation([w, x, y, z]: [f64; 4]) -> DMat3 {
    mat_from_rows([
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
    ])
}

/// ∂R/∂(w, x, y, z) of [`rotation`], one matrix per quaternion component.
fn rotation_derivatives([w, x, y, z]: [f64; 4]) -> [DMat3; 4] {
    let (w2, x2, y2, z2) = (2.0 * w, 2.0 * x, 2.0 * y, 2.0 * z);
    [
        mat_from_rows([[0.0, -z2, y2], [z2, 0.0, -x2], [-y2, x2, 0.0]]),
        mat_from_rows([[0.0, y2, z2], [y2, -2.0 * x2, -w2], [z2, w2, -2.0 * x2]]),
        mat_from_rows([[-2.0 * y2, x2, w2], [x2, 0.0, z2], [-w2, z2, -2.0 * y2]]),
        mat_from_rows([[-2.0 * z2, -w2, x2], [w2, -2.0 * z2, y2], [x2, y2, 0.0]]),
    ]
}

fn normalized_quat(q: [f64; 4]) -> [f64; 4] {
    let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    q.map(|v| v / norm.max(QUAT_EPS))
}

fn mat_from_rows(rows: [[f64; 3]; 3]) -> DMat3 {
    DMat3::from_cols_array_2d(&rows).transpose()
}

/// Σ_ij a_ij b_ij.
fn frobenius(a: DMat3, b: DMat3) -> f64 {
    a.x_axis.dot(b.x_axis) + a.y_axis.dot(b.y_axis) + a.z_axis.dot(b.z_axis)
}

/// The per-Gaussian stage: culling, EWA projection, conic, radius and tile rectangle.
fn project(scene: &Scene, i: usize, view: &View) -> Option<Projected> {
    if !scene.is_finite(i) {
        return None;
    }
    let t = view.rot * scene.means[i] + view.trans;
    let opacity = sigmoid(scene.opacity_logits[i]);
    if !(NEAR..=FAR).contains(&t.z) || opacity < MIN_ALPHA {
        return None;
    }

    let rot = rotation(normalized_quat(scene.quats[i]));
    let scale = scene.log_scales[i].exp();
    let cov3d_factor = rot * DMat3::from_diagonal(scale);
    let cov3d = cov3d_factor * cov3d_factor.transpose();

    // The Jacobian of the perspective map, evaluated at a direction clamped to 1.3x the frustum
    // so Gaussians far outside the image do not get huge screen footprints.
    let clamped_xy = |t_xy: f64, limit: f64| {
        let ratio = t_xy / t.z;
        (t.z * ratio.clamp(-limit, limit), ratio.abs() > limit)
    };
    let (x_c, clamped_x) = clamped_xy(t.x, view.clamp.x);
    let (y_c, clamped_y) = clamped_xy(t.y, view.clamp.y);
    let jacobian = [
        DVec3::new(view.fx / t.z, 0.0, -view.fx * x_c / (t.z * t.z)),
        DVec3::new(0.0, view.fy / t.z, -view.fy * y_c / (t.z * t.z)),
    ];
    // Row i of J W_rot is W_rotᵀ (row i of J).
    let jw = jacobian.map(|row| view.rot.transpose() * row);
    let cov2d = DMat2::from_cols(
        DVec2::new(jw[0].dot(cov3d * jw[0]), jw[1].dot(cov3d * jw[0])),
        DVec2::new(jw[0].dot(cov3d * jw[1]), jw[1].dot(cov3d * jw[1])),
    ) + DMat2::from_diagonal(DVec2::splat(LOW_PASS));
    let det = cov2d.determinant();
    if !(det > 0.0 && det.is_finite()) {
        return None;
    }
    let conic = cov2d.inverse();
    let mean2d = DVec2::new(view.fx * t.x / t.z + view.cx, view.fy * t.y / t.z + view.cy);

    // Opacity-aware extent: o·exp(-½ dᵀ conic d) >= 1/255 only inside this radius.
    let mid = 0.5 * (cov2d.x_axis.x + cov2d.y_axis.y);
    let lambda_max = mid + (mid * mid - det).max(0.0).sqrt();
    let radius = (2.0 * (opacity / MIN_ALPHA).ln().max(0.0) * lambda_max)
        .sqrt()
        .ceil();
    if !(mean2d.is_finite() && radius.is_finite() && conic.is_finite()) {
        return None;
    }
    let tiles = TileRect::around(mean2d, radius, view)?;

    Some(Projected {
        index: i,
        t,
        rot,
        scale,
        cov3d_factor,
        cov3d,
        jacobian,
        clamped: [clamped_x, clamped_y],
        jw,
        conic,
        mean2d,
        opacity,
        tiles,
    })
}

fn sigmoid(x: f64) -> f64 {
    1.0 / (1.0 + (-x).exp())
}

/// Every surviving Gaussian, sorted by increasing depth (ties: lower index first).
fn project_all(scene: &Scene, view: &View) -> Vec<Projected> {
    let mut projected: Vec<Projected> = (0..scene.len())
        .filter_map(|i| project(scene, i, view))
        .collect();
    // A stable sort keeps index order among equal depths.
    projected.sort_by(|a, b| a.t.z.total_cmp(&b.t.z));
    projected
}

/// For each tile (row-major), the positions in `projected` whose rectangle covers it, in
/// depth order.
fn tile_lists(projected: &[Projected], view: &View) -> Vec<Vec<usize>> {
    let (tiles_x, tiles_y) = (view.tiles_x(), view.tiles_y());
    (0..tiles_x * tiles_y)
        .map(|tile| {
            let (tx, ty) = (tile % tiles_x, tile / tiles_x);
            (0..projected.len())
                .filter(|&k| projected[k].tiles.contains(tx, ty))
                .collect()
        })
        .collect()
}

/// Pixels (column, row) of one tile, clipped to the image.
fn tile_pixels(tile: usize, view: &View) -> impl Iterator<Item = (usize, usize)> {
    let tile_size = TILE as usize;
    let (tx, ty) = (tile % view.tiles_x(), tile / view.tiles_x());
    let cols = tx * tile_size..((tx + 1) * tile_size).min(view.width);
    let rows = ty * tile_size..((ty + 1) * tile_size).min(view.height);
    rows.flat_map(move |row| cols.clone().map(move |col| (col, row)))
}

fn pixel_center(col: usize, row: usize) -> DVec2 {
    DVec2::new(col as f64 + 0.5, row as f64 + 0.5)
}

/// One Gaussian's alpha at one pixel, with the local derivatives the backward pass needs.
#[derive(Debug, Clone, Copy)]
struct AlphaAt {
    alpha: f64,
    /// Pixel centre minus the 2D mean.
    offset: DVec2,
    /// exp(power), power = -½ dᵀ conic d.
    falloff: f64,
    /// ∂alpha / ∂(o·exp(power)): zero under the 0.999 clamp.
    slope: f64,
}

fn alpha_at(p: &Projected, pixel: DVec2, cutoff: Cutoff) -> Option<AlphaAt> {
    let offset = pixel - p.mean2d;
    let power = -0.5 * offset.dot(p.conic * offset);
    if power > 0.0 {
        return None;
    }
    let falloff = power.exp();
    let raw = p.opacity * falloff;
    let alpha = raw.min(MAX_ALPHA);
    let clamp_slope = if raw > MAX_ALPHA { 0.0 } else { 1.0 };
    match cutoff {
        Cutoff::Hard => (alpha >= MIN_ALPHA).then_some(AlphaAt {
            alpha,
            offset,
            falloff,
            slope: clamp_slope,
        }),
        #[cfg(test)]
        Cutoff::Smooth => {
            // alpha · s(alpha), s rising from 0 at 1/255 to 1 at 2/255 (quintic smoothstep).
            let x = ((alpha - MIN_ALPHA) / MIN_ALPHA).clamp(0.0, 1.0);
            let s = x * x * x * (x * (6.0 * x - 15.0) + 10.0);
            let ds = 30.0 * x * x * (1.0 - x) * (1.0 - x) / MIN_ALPHA;
            (s > 0.0).then_some(AlphaAt {
                alpha: alpha * s,
                offset,
                falloff,
                slope: clamp_slope * (s + alpha * ds),
            })
        }
    }
}

/// A Gaussian blended into a pixel: its position in `projected`, alpha, and the
/// transmittance in front of it.
#[derive(Debug, Clone, Copy)]
struct Blended {
    k: usize,
    at: AlphaAt,
    transmittance: f64,
}

/// Front-to-back blending of one pixel: what was blended, and the final transmittance.
fn blend_pixel(
    list: &[usize],
    projected: &[Projected],
    pixel: DVec2,
    cutoff: Cutoff,
) -> (Vec<Blended>, f64) {
    let mut blended = Vec::new();
    let mut transmittance = 1.0;
    for &k in list {
        let Some(at) = alpha_at(&projected[k], pixel, cutoff) else {
            continue;
        };
        let next = transmittance * (1.0 - at.alpha);
        if next < MIN_TRANSMITTANCE {
            break;
        }
        blended.push(Blended {
            k,
            at,
            transmittance,
        });
        transmittance = next;
    }
    (blended, transmittance)
}

fn render(
    scene: &Scene,
    view: &View,
    background: &[f64],
    depth: bool,
    cutoff: Cutoff,
) -> RenderOutput<f64> {
    let channels = scene.channels;
    let pixels = view.width * view.height;
    let mut out = RenderOutput {
        features: vec![0.0; pixels * channels],
        alpha: vec![0.0; pixels],
        depth: depth.then(|| vec![0.0; pixels]),
    };
    let projected = project_all(scene, view);
    for (tile, list) in tile_lists(&projected, view).iter().enumerate() {
        for (col, row) in tile_pixels(tile, view) {
            let (blended, t_final) = blend_pixel(list, &projected, pixel_center(col, row), cutoff);
            let pix = row * view.width + col;
            let color = &mut out.features[pix * channels..(pix + 1) * channels];
            for (c, bg) in color.iter_mut().zip(background) {
                *c = t_final * bg;
            }
            for b in &blended {
                let p = &projected[b.k];
                let weight = b.at.alpha * b.transmittance;
                for (c, f) in color.iter_mut().zip(scene.feature(p.index)) {
                    *c += weight * f;
                }
                if let Some(d) = out.depth.as_mut() {
                    d[pix] += weight * p.t.z;
                }
            }
            out.alpha[pix] = 1.0 - t_final;
        }
    }
    out
}

/// Per-Gaussian gradients with respect to the screen-space quantities of [`Projected`].
#[derive(Debug, Clone, Copy)]
struct ScreenGrad {
    mean2d: DVec2,
    /// ∂L/∂conic as a general 2x2 matrix (each off-diagonal entry separately).
    conic: DMat2,
    opacity: f64,
    /// Through the depth image only (the projection adds its own share later).
    depth: f64,
}

impl ScreenGrad {
    // Not `Default`: glam's default matrix is the identity.
    const ZERO: Self = Self {
        mean2d: DVec2::ZERO,
        conic: DMat2::ZERO,
        opacity: 0.0,
        depth: 0.0,
    };
}

/// Screen-space gradients of every projected Gaussian, plus ∂L/∂features (N x C).
#[derive(Debug, Clone)]
struct BlendGrads {
    screen: Vec<ScreenGrad>,
    features: Vec<f64>,
}

impl BlendGrads {
    fn zeros(projected: usize, feature_values: usize) -> Self {
        Self {
            screen: vec![ScreenGrad::ZERO; projected],
            features: vec![0.0; feature_values],
        }
    }

    fn add(mut self, other: Self) -> Self {
        for (a, b) in self.screen.iter_mut().zip(&other.screen) {
            a.mean2d += b.mean2d;
            a.conic += b.conic;
            a.opacity += b.opacity;
            a.depth += b.depth;
        }
        for (a, b) in self.features.iter_mut().zip(&other.features) {
            *a += b;
        }
        self
    }
}

/// The blend backward of one pixel, accumulated into `acc`.
///
/// Back to front, `behind` holds what lies behind Gaussian k normalised by the transmittance
/// after it: features (starting at the background), alpha (starting at 0) and depth (0). Then
/// ∂out/∂alpha_k = T_k (value_k - behind) for each output, with value 1 for alpha, z_k for depth.
#[allow(clippy::too_many_arguments)]
fn blend_pixel_backward(
    blended: &[Blended],
    projected: &[Projected],
    scene: &Scene,
    background: &[f64],
    grad_features: &[f64],
    grad_alpha: f64,
    grad_depth: f64,
    acc: &mut BlendGrads,
) {
    let channels = scene.channels;
    let mut behind_features = background.to_vec();
    let mut behind_alpha = 0.0;
    let mut behind_depth = 0.0;
    for b in blended.iter().rev() {
        let p = &projected[b.k];
        let (alpha, weight) = (b.at.alpha, b.at.alpha * b.transmittance);
        let feature = scene.feature(p.index);
        let z = p.t.z;

        let mut grad_alpha_k = grad_alpha * (1.0 - behind_alpha) + grad_depth * (z - behind_depth);
        for c in 0..channels {
            grad_alpha_k += grad_features[c] * (feature[c] - behind_features[c]);
            acc.features[p.index * channels + c] += weight * grad_features[c];
            behind_features[c] = alpha * feature[c] + (1.0 - alpha) * behind_features[c];
        }
        grad_alpha_k *= b.transmittance;
        behind_alpha = alpha + (1.0 - alpha) * behind_alpha;
        behind_depth = alpha * z + (1.0 - alpha) * behind_depth;

        // alpha = clamp(o·exp(power)); power = -½ dᵀ conic d with d = pixel - mean2d.
        let grad_raw = grad_alpha_k * b.at.slope;
        let grad_power = grad_raw * p.opacity * b.at.falloff;
        let d = b.at.offset;
        let screen = &mut acc.screen[b.k];
        screen.opacity += grad_raw * b.at.falloff;
        screen.mean2d += grad_power * (p.conic * d);
        screen.conic += grad_power * -0.5 * DMat2::from_cols(d * d.x, d * d.y);
        screen.depth += weight * grad_depth;
    }
}

/// The per-Gaussian backward: screen-space gradients to the inputs of Gaussian `p.index`.
fn project_backward(
    p: &Projected,
    g: &ScreenGrad,
    scene: &Scene,
    view: &View,
    out: &mut GaussianGradients<f64>,
) {
    let t = p.t;
    // conic = cov2d⁻¹  =>  ∂L/∂cov2d = -conicᵀ (∂L/∂conic) conicᵀ.
    let grad_cov2d = -(p.conic.transpose() * g.conic * p.conic.transpose());
    let g2 = |row: usize, col: usize| grad_cov2d.col(col)[row];

    // cov2d_ab = jw_aᵀ Σ jw_b (+ low-pass).
    let mut grad_cov3d = DMat3::ZERO;
    let mut grad_jw = [DVec3::ZERO; 2];
    for a in 0..2 {
        for b in 0..2 {
            let gab = g2(a, b);
            // ∂(uᵀ Σ v)/∂Σ = u vᵀ, as columns: column j is u * v_j.
            grad_cov3d += gab
                * DMat3::from_cols(
                    p.jw[a] * p.jw[b].x,
                    p.jw[a] * p.jw[b].y,
                    p.jw[a] * p.jw[b].z,
                );
            grad_jw[a] += gab * (p.cov3d * p.jw[b]);
            grad_jw[b] += gab * (p.cov3d.transpose() * p.jw[a]);
        }
    }
    // jw_a = W_rotᵀ J_a.
    let grad_jacobian = grad_jw.map(|gj| view.rot * gj);

    // t enters through the 2D mean, the Jacobian and the depth image.
    let (tz2, tz3) = (t.z * t.z, t.z * t.z * t.z);
    let x_c = -p.jacobian[0].z * tz2 / view.fx;
    let y_c = -p.jacobian[1].z * tz2 / view.fy;
    let mut grad_t = DVec3::new(
        g.mean2d.x * view.fx / t.z,
        g.mean2d.y * view.fy / t.z,
        -g.mean2d.x * view.fx * t.x / tz2 - g.mean2d.y * view.fy * t.y / tz2 + g.depth,
    );
    grad_t.z += -grad_jacobian[0].x * view.fx / tz2
        + grad_jacobian[0].z * 2.0 * view.fx * x_c / tz3
        - grad_jacobian[1].y * view.fy / tz2
        + grad_jacobian[1].z * 2.0 * view.fy * y_c / tz3;
    // x' = t.x unless clamped, then a constant (the contract: no gradient through the clamp).
    if !p.clamped[0] {
        grad_t.x += -grad_jacobian[0].z * view.fx / tz2;
    }
    if !p.clamped[1] {
        grad_t.y += -grad_jacobian[1].z * view.fy / tz2;
    }
    out.means[p.index] = (view.rot.transpose() * grad_t).to_array();

    // Σ = M Mᵀ with M = R diag(s)  =>  ∂L/∂M = (G + Gᵀ) M.
    let grad_factor = (grad_cov3d + grad_cov3d.transpose()) * p.cov3d_factor;
    let grad_rot = grad_factor * DMat3::from_diagonal(p.scale);
    let grad_scale = DVec3::new(
        grad_factor.x_axis.dot(p.rot.x_axis),
        grad_factor.y_axis.dot(p.rot.y_axis),
        grad_factor.z_axis.dot(p.rot.z_axis),
    );
    out.log_scales[p.index] = (grad_scale * p.scale).to_array();

    // R(q_n), q_n = q / max(|q|, eps).
    let q = scene.quats[p.index];
    let q_n = normalized_quat(q);
    let grad_qn = rotation_derivatives(q_n).map(|d| frobenius(grad_rot, d));
    let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    out.quats[p.index] = if norm > QUAT_EPS {
        let radial: f64 = q_n.iter().zip(&grad_qn).map(|(a, b)| a * b).sum();
        std::array::from_fn(|k| (grad_qn[k] - q_n[k] * radial) / norm)
    } else {
        grad_qn.map(|v| v / QUAT_EPS)
    };

    out.opacity_logits[p.index] = g.opacity * p.opacity * (1.0 - p.opacity);
}

fn gradients(
    scene: &Scene,
    view: &View,
    background: &[f64],
    grads: &OutputGradients<f64>,
    cutoff: Cutoff,
) -> GaussianGradients<f64> {
    let channels = scene.channels;
    let n = scene.len();
    let projected = project_all(scene, view);
    let lists = tile_lists(&projected, view);
    let blend = lists
        .par_iter()
        .enumerate()
        .fold(
            || BlendGrads::zeros(projected.len(), n * channels),
            |mut acc, (tile, list)| {
                for (col, row) in tile_pixels(tile, view) {
                    let pix = row * view.width + col;
                    let (blended, _) =
                        blend_pixel(list, &projected, pixel_center(col, row), cutoff);
                    blend_pixel_backward(
                        &blended,
                        &projected,
                        scene,
                        background,
                        &grads.features[pix * channels..(pix + 1) * channels],
                        grads.alpha[pix],
                        grads.depth.map_or(0.0, |d| d[pix]),
                        &mut acc,
                    );
                }
                acc
            },
        )
        .reduce(
            || BlendGrads::zeros(projected.len(), n * channels),
            BlendGrads::add,
        );

    let mut out = GaussianGradients {
        means: vec![[0.0; 3]; n],
        quats: vec![[0.0; 4]; n],
        log_scales: vec![[0.0; 3]; n],
        opacity_logits: vec![0.0; n],
        features: blend.features,
    };
    for (p, g) in projected.iter().zip(&blend.screen) {
        project_backward(p, g, scene, view, &mut out);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::splat::test_rng::Rng;
    use crate::splat::OwnedGaussians;

    /// A camera at `eye` looking along +z of a world rotated by `yaw` about the y axis.
    fn camera(width: u32, height: u32, focal: f32, yaw: f32, eye: [f32; 3]) -> Camera {
        let (s, c) = yaw.sin_cos();
        let rot = [[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]];
        let trans: [f32; 3] =
            std::array::from_fn(|r| -(0..3).map(|k| rot[r][k] * eye[k]).sum::<f32>());
        let mut world_to_cam = [[0.0; 4]; 4];
        for r in 0..3 {
            world_to_cam[r][..3].copy_from_slice(&rot[r]);
            world_to_cam[r][3] = trans[r];
        }
        world_to_cam[3][3] = 1.0;
        Camera {
            world_to_cam,
            fx: focal,
            fy: focal * 1.1,
            cx: width as f32 * 0.5,
            cy: height as f32 * 0.47,
            width,
            height,
        }
    }

    /// `n` Gaussians in front of `cam` (centre about 4 units away), a few pixels wide, with
    /// opacities in [0.27, 0.73], unnormalised quaternions and features in [-1, 1].
    fn random_gaussians(rng: &mut Rng, n: usize, channels: usize, cam: &Camera) -> OwnedGaussians {
        let view = View::new(cam);
        let mut g = OwnedGaussians::new(channels);
        for _ in 0..n {
            let z = f64::from(rng.uniform(3.0, 5.0));
            let t = DVec3::new(
                f64::from(rng.uniform(-0.4, 0.4)) * z * view.clamp.x / 1.3,
                f64::from(rng.uniform(-0.4, 0.4)) * z * view.clamp.y / 1.3,
                z,
            );
            let mean = view.rot.transpose() * (t - view.trans);
            g.means.push(mean.as_vec3().to_array());
            g.quats
                .push(std::array::from_fn(|_| rng.uniform(-1.5, 1.5)));
            g.log_scales
                .push(std::array::from_fn(|_| rng.uniform(-2.0, -0.6)));
            g.opacity_logits.push(rng.uniform(-1.0, 1.0));
            for _ in 0..channels {
                g.features.push(rng.uniform(-1.0, 1.0));
            }
        }
        g
    }

    fn options(channels: usize, depth: bool) -> RenderOptions {
        RenderOptions {
            depth,
            background: (0..channels).map(|c| 0.2 + 0.1 * c as f32).collect(),
        }
    }

    /// Σ grads·images: the scalar loss whose gradient the backward pass computes.
    fn loss(out: &RenderOutput<f64>, grads: &OutputGradients<f64>) -> f64 {
        let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
        dot(&out.features, grads.features)
            + dot(&out.alpha, grads.alpha)
            + grads
                .depth
                .map_or(0.0, |d| dot(out.depth.as_ref().unwrap(), d))
    }

    /// One input array of the scene: its name, values per Gaussian, a mutable accessor into
    /// the scene and a reader of the matching analytic gradient.
    struct InputArray {
        name: &'static str,
        width: fn(&Scene) -> usize,
        value: fn(&mut Scene, usize, usize) -> &mut f64,
        grad: fn(&GaussianGradients<f64>, usize, usize) -> f64,
    }

    const INPUT_ARRAYS: [InputArray; 5] = [
        InputArray {
            name: "means",
            width: |_| 3,
            value: |s, i, k| &mut s.means[i][k],
            grad: |g, i, k| g.means[i][k],
        },
        InputArray {
            name: "quats",
            width: |_| 4,
            value: |s, i, k| &mut s.quats[i][k],
            grad: |g, i, k| g.quats[i][k],
        },
        InputArray {
            name: "log_scales",
            width: |_| 3,
            value: |s, i, k| &mut s.log_scales[i][k],
            grad: |g, i, k| g.log_scales[i][k],
        },
        InputArray {
            name: "opacity_logits",
            width: |_| 1,
            value: |s, i, _| &mut s.opacity_logits[i],
            grad: |g, i, _| g.opacity_logits[i],
        },
        InputArray {
            name: "features",
            width: |s| s.channels,
            value: |s, i, k| &mut s.features[i * s.channels + k],
            grad: |g, i, k| g.features[i * g.features.len() / g.means.len() + k],
        },
    ];

    /// Checks the analytic backward (smooth cut-off) of a random scene against central finite
    /// differences of the forward, for every input array: relative L2 error <= `tol`.
    fn check_against_finite_differences(seed: u64, n: usize, channels: usize, depth: bool) {
        const STEP: f64 = 1e-6;
        const TOL: f64 = 1e-6;
        let mut rng = Rng(seed);
        let cam = camera(12, 10, 11.0, 0.3, [0.2, -0.1, -0.5]);
        let owned = random_gaussians(&mut rng, n, channels, &cam);
        let scene = Scene::new(&owned.view());
        let view = View::new(&cam);
        let background = widen(&options(channels, depth).background);
        let pixels = view.width * view.height;
        let g_features: Vec<f64> = (0..pixels * channels)
            .map(|_| f64::from(rng.uniform(-1.0, 1.0)))
            .collect();
        let g_alpha: Vec<f64> = (0..pixels)
            .map(|_| f64::from(rng.uniform(-1.0, 1.0)))
            .collect();
        let g_depth: Vec<f64> = (0..pixels)
            .map(|_| f64::from(rng.uniform(-1.0, 1.0)))
            .collect();
        let grads = OutputGradients {
            features: &g_features,
            alpha: &g_alpha,
            depth: depth.then_some(&g_depth[..]),
        };
        let analytic = gradients(&scene, &view, &background, &grads, Cutoff::Smooth);
        let eval = |s: &Scene| {
            loss(
                &render(s, &view, &background, depth, Cutoff::Smooth),
                &grads,
            )
        };

        for array in &INPUT_ARRAYS {
            let (mut err2, mut ref2) = (0.0, 0.0);
            for i in 0..n {
                for k in 0..(array.width)(&scene) {
                    let mut plus = scene.clone();
                    *(array.value)(&mut plus, i, k) += STEP;
                    let mut minus = scene.clone();
                    *(array.value)(&mut minus, i, k) -= STEP;
                    let numeric = (eval(&plus) - eval(&minus)) / (2.0 * STEP);
                    let exact = (array.grad)(&analytic, i, k);
                    err2 += (exact - numeric).powi(2);
                    ref2 += numeric.powi(2);
                }
            }
            let rel = err2.sqrt() / ref2.sqrt().max(1e-12);
            assert!(
                ref2 > 0.0 && rel <= TOL,
                "seed {seed} {}: relative L2 error {rel:e} (|fd| {:e})",
                array.name,
                ref2.sqrt()
            );
        }
    }

    #[test]
    fn backward_matches_finite_differences_with_depth() {
        check_against_finite_differences(1, 5, 3, true);
    }

    #[test]
    fn backward_matches_finite_differences_without_depth() {
        check_against_finite_differences(2, 6, 2, false);
    }

    /// 12x10 pixels, identity pose, principal point on the centre of pixel (6, 5).
    fn axis_camera() -> Camera {
        let mut world_to_cam = [[0.0; 4]; 4];
        for (i, row) in world_to_cam.iter_mut().enumerate() {
            row[i] = 1.0;
        }
        Camera {
            world_to_cam,
            fx: 10.0,
            fy: 10.0,
            cx: 6.5,
            cy: 5.5,
            width: 12,
            height: 10,
        }
    }

    const IDENTITY: [f32; 4] = [1.0, 0.0, 0.0, 0.0];

    fn assert_close(got: f64, want: f64, what: &str) {
        assert!(
            (got - want).abs() <= 1e-12,
            "{what}: got {got}, want {want}"
        );
    }

    #[test]
    fn centre_pixel_of_a_single_gaussian() {
        let mut g = OwnedGaussians::new(3);
        g.push([0.0, 0.0, 2.0], IDENTITY, [-2.0; 3], 0.5, &[0.2, 0.5, 0.9]);
        let opts = options(3, true);
        let out = forward(&g.view(), &axis_camera(), &opts).unwrap();
        // At the centre power = 0, so alpha = sigmoid(0.5) and T_final = 1 - alpha.
        let o = 1.0 / (1.0 + (-0.5f64).exp());
        let pix = 5 * 12 + 6;
        for c in 0..3 {
            let want = o * f64::from(g.features[c]) + (1.0 - o) * f64::from(opts.background[c]);
            assert_close(out.features[pix * 3 + c], want, "feature");
        }
        assert_close(out.alpha[pix], o, "alpha");
        assert_close(out.depth.unwrap()[pix], o * 2.0, "depth");
    }

    #[test]
    fn background_shows_through_where_there_are_no_gaussians() {
        let opts = options(2, true);
        let empty = forward(&OwnedGaussians::new(2).view(), &axis_camera(), &opts).unwrap();
        let bg: Vec<f64> = widen(&opts.background).repeat(120);
        assert_eq!(empty.features, bg);
        assert!(empty
            .alpha
            .iter()
            .chain(empty.depth.as_ref().unwrap())
            .all(|&v| v == 0.0));

        // A small Gaussian over pixel (0, 0) leaves the opposite corner untouched.
        let mut g = OwnedGaussians::new(2);
        g.push([-0.6, -0.5, 1.0], IDENTITY, [-4.0; 3], 3.0, &[1.0, 1.0]);
        let out = forward(&g.view(), &axis_camera(), &opts).unwrap();
        assert!(out.alpha[0] > 0.5);
        let last = 119;
        assert_eq!(&out.features[last * 2..], &bg[last * 2..]);
        assert_eq!(out.alpha[last], 0.0);
    }

    #[test]
    fn alpha_stays_in_unit_interval_and_outputs_are_finite() {
        let mut rng = Rng(7);
        let cam = camera(40, 30, 30.0, -0.2, [0.0, 0.1, -1.0]);
        let mut g = random_gaussians(&mut rng, 300, 3, &cam);
        for logit in &mut g.opacity_logits {
            *logit *= 8.0; // many near-opaque Gaussians, some under the 0.999 clamp
        }
        let out = forward(&g.view(), &cam, &options(3, true)).unwrap();
        assert!(out.alpha.iter().all(|a| (0.0..=1.0).contains(a)));
        assert!(out.alpha.iter().any(|&a| a > 0.99));
        // Blending stops before T falls below 1e-4, so alpha never exceeds 1 - 1e-4.
        assert!(out.alpha.iter().all(|&a| a <= 1.0 - MIN_TRANSMITTANCE));
        let depth = out.depth.unwrap();
        assert!(out.features.iter().chain(&depth).all(|v| v.is_finite()));
    }

    #[test]
    fn blending_stops_before_transmittance_falls_below_the_cut_off() {
        // Five stacked Gaussians of alpha 0.95 at the centre pixel: T goes 1, 0.05, 0.0025,
        // 1.25e-4, and the fourth would take it to 6.25e-6 < 1e-4, so only three blend.
        let logit = (0.95f32 / 0.05).ln();
        let mut g = OwnedGaussians::new(1);
        for k in 0..5 {
            g.push(
                [0.0, 0.0, 1.0 + k as f32],
                IDENTITY,
                [-1.0; 3],
                logit,
                &[k as f32 + 1.0],
            );
        }
        let opts = RenderOptions {
            depth: true,
            background: vec![10.0],
        };
        let out = forward(&g.view(), &axis_camera(), &opts).unwrap();
        let pix = 5 * 12 + 6;
        // The f32 logit makes alpha 0.95 only up to rounding, hence the 1e-6 tolerances.
        let a = 1.0 / (1.0 + (-f64::from(logit)).exp());
        let weights = [a, a * (1.0 - a), a * (1.0 - a) * (1.0 - a)];
        let t_final = (1.0 - a).powi(3);
        let want_feature = weights[0] + 2.0 * weights[1] + 3.0 * weights[2] + 10.0 * t_final;
        let want_depth = weights[0] + 2.0 * weights[1] + 3.0 * weights[2];
        assert!((out.features[pix] - want_feature).abs() < 1e-9);
        assert!((out.depth.unwrap()[pix] - want_depth).abs() < 1e-9);
        assert!((out.alpha[pix] - (1.0 - t_final)).abs() < 1e-12);
    }

    /// Gradients of `g` for all-ones image gradients.
    fn ones_backward(
        g: &OwnedGaussians,
        cam: &Camera,
        opts: &RenderOptions,
    ) -> GaussianGradients<f64> {
        let pixels = cam.pixels();
        let (gf, ga, gd) = (
            vec![1.0; pixels * g.channels],
            vec![1.0; pixels],
            vec![1.0; pixels],
        );
        let grads = OutputGradients {
            features: &gf,
            alpha: &ga,
            depth: Some(&gd[..]),
        };
        backward(&g.view(), cam, opts, &grads).unwrap()
    }

    #[test]
    fn culled_gaussians_change_nothing_and_get_zero_gradients() {
        let mut rng = Rng(3);
        let cam = camera(20, 18, 16.0, 0.1, [0.0, 0.0, -0.5]);
        let opts = options(2, true);
        let visible = random_gaussians(&mut rng, 8, 2, &cam);
        let mut all = visible.clone();
        let behind =
            View::new(&cam).rot.transpose() * (DVec3::new(0.0, 0.0, -1.0) - View::new(&cam).trans);
        let behind = behind.as_vec3().to_array();
        all.push(behind, IDENTITY, [-1.0; 3], 2.0, &[1.0, 1.0]); // behind the camera
        all.push([f32::NAN, 0.0, 4.0], IDENTITY, [-1.0; 3], 2.0, &[1.0, 1.0]); // non-finite mean
        all.push(
            visible.means[0],
            IDENTITY,
            [-1.0; 3],
            2.0,
            &[f32::INFINITY, 0.0],
        ); // non-finite feature
        all.push(visible.means[1], IDENTITY, [-1.0; 3], -50.0, &[1.0, 1.0]); // opacity < 1/255
        all.push(visible.means[2], IDENTITY, [f32::MAX; 3], 0.0, &[1.0, 1.0]); // overflowing scale
        all.push([1e6, 0.0, 1e6], IDENTITY, [-1.0; 3], 2.0, &[1.0, 1.0]); // far outside the image

        assert_eq!(
            forward(&all.view(), &cam, &opts).unwrap(),
            forward(&visible.view(), &cam, &opts).unwrap()
        );
        let grads = ones_backward(&all, &cam, &opts);
        let reference = ones_backward(&visible, &cam, &opts);
        let n = visible.means.len();
        assert_eq!(grads.means[..n], reference.means[..]);
        assert_eq!(grads.features[..2 * n], reference.features[..]);
        assert!(grads.means[n..].iter().flatten().all(|&v| v == 0.0));
        assert!(grads.quats[n..].iter().flatten().all(|&v| v == 0.0));
        assert!(grads.log_scales[n..].iter().flatten().all(|&v| v == 0.0));
        assert!(grads.opacity_logits[n..].iter().all(|&v| v == 0.0));
        assert!(grads.features[2 * n..].iter().all(|&v| v == 0.0));
    }

    #[test]
    fn zero_quaternion_is_the_identity_with_zero_gradient() {
        let mut zero = OwnedGaussians::new(1);
        zero.push([0.1, 0.0, 2.0], [0.0; 4], [-1.5; 3], 1.0, &[0.7]);
        zero.log_scales[0] = [-1.0, -1.8, -1.3];
        let mut identity = zero.clone();
        identity.quats[0] = IDENTITY;
        let (cam, opts) = (axis_camera(), options(1, true));
        assert_eq!(
            forward(&zero.view(), &cam, &opts).unwrap(),
            forward(&identity.view(), &cam, &opts).unwrap()
        );
        let grads = ones_backward(&zero, &cam, &opts);
        assert_eq!(grads.quats[0], [0.0; 4]);
        assert!(grads.log_scales[0]
            .iter()
            .all(|&v| v != 0.0 && v.is_finite()));
    }

    #[test]
    fn mismatched_arrays_are_rejected() {
        let mut g = OwnedGaussians::new(2);
        g.push([0.0, 0.0, 2.0], IDENTITY, [-1.0; 3], 0.0, &[1.0, 1.0]);
        g.opacity_logits.push(0.0);
        assert!(forward(&g.view(), &axis_camera(), &options(2, false)).is_err());
    }
}
