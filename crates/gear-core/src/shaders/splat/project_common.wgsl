// The per-Gaussian projection of the contract, shared by the forward project kernel and the
// project-backward kernel (which recomputes it instead of storing intermediates).

@group(0) @binding(0) var<storage, read> means: array<f32>;
@group(0) @binding(1) var<storage, read> quats: array<f32>;
@group(0) @binding(2) var<storage, read> log_scales: array<f32>;
@group(0) @binding(3) var<storage, read> opacity_logits: array<f32>;
@group(0) @binding(7) var<storage, read> features: array<f32>;

struct Projection {
    visible: bool,
    // Camera-space centre.
    t: vec3<f32>,
    // Normalised quaternion (w, x, y, z) and the raw quaternion's norm.
    qn: vec4<f32>,
    qnorm: f32,
    rot: mat3x3<f32>,
    scale: vec3<f32>,
    // Rows of the clamped Jacobian, and whether x', y' were clamped.
    j0: vec3<f32>,
    j1: vec3<f32>,
    clamped: vec2<bool>,
    // Camera-space covariance factor K = W_rot R diag(s) (Σ_cam = K Kᵀ) and P = J K.
    k: mat3x3<f32>,
    p0: vec3<f32>,
    p1: vec3<f32>,
    // Σ2D = (a, b, c), its inverse (conic) and determinant.
    cov: vec3<f32>,
    conic: vec3<f32>,
    det: f32,
    mean2d: vec2<f32>,
    opacity: f32,
}

fn rotation(q: vec4<f32>) -> mat3x3<f32> {
    let w = q.x;
    let x = q.y;
    let y = q.z;
    let z = q.w;
    let row0 = vec3<f32>(1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y));
    let row1 = vec3<f32>(2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x));
    let row2 = vec3<f32>(2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y));
    return transpose(mat3x3<f32>(row0, row1, row2));
}

fn world_rotation() -> mat3x3<f32> {
    return transpose(mat3x3<f32>(frame.rot0.xyz, frame.rot1.xyz, frame.rot2.xyz));
}

fn all_finite4(v: vec4<f32>) -> bool {
    return is_finite(v.x) && is_finite(v.y) && is_finite(v.z) && is_finite(v.w);
}

// The contract culls a Gaussian with any non-finite input, features included.
fn features_finite(i: u32) -> bool {
    var ok = true;
    for (var c = 0u; c < CHANNELS; c++) {
        ok = ok && is_finite(features[i * CHANNELS + c]);
    }
    return ok;
}

fn project_gaussian(i: u32) -> Projection {
    var p: Projection;
    p.visible = false;
    let m = vec3<f32>(means[3u * i], means[3u * i + 1u], means[3u * i + 2u]);
    let q = vec4<f32>(quats[4u * i], quats[4u * i + 1u], quats[4u * i + 2u], quats[4u * i + 3u]);
    let ls = vec3<f32>(log_scales[3u * i], log_scales[3u * i + 1u], log_scales[3u * i + 2u]);
    let logit = opacity_logits[i];
    let finite = all_finite4(vec4<f32>(m, logit)) && all_finite4(q)
        && all_finite4(vec4<f32>(ls, 0.0)) && features_finite(i);
    if !finite {
        return p;
    }
    let w_rot = world_rotation();
    p.t = w_rot * m + vec3<f32>(frame.rot0.w, frame.rot1.w, frame.rot2.w);
    p.opacity = 1.0 / (1.0 + exp(-logit));
    if !(p.t.z >= NEAR && p.t.z <= FAR && p.opacity >= MIN_ALPHA) {
        return p;
    }
    p.qnorm = length(q);
    p.qn = q / max(p.qnorm, QUAT_EPS);
    p.rot = rotation(p.qn);
    p.scale = exp(ls);
    p.k = w_rot * mat3x3<f32>(p.rot[0] * p.scale.x, p.rot[1] * p.scale.y, p.rot[2] * p.scale.z);

    let fx = frame.focal.x;
    let fy = frame.focal.y;
    let z = p.t.z;
    let rx = p.t.x / z;
    let ry = p.t.y / z;
    p.clamped = vec2<bool>(abs(rx) > frame.limits.x, abs(ry) > frame.limits.y);
    let xc = z * clamp(rx, -frame.limits.x, frame.limits.x);
    let yc = z * clamp(ry, -frame.limits.y, frame.limits.y);
    p.j0 = vec3<f32>(fx / z, 0.0, -fx * xc / (z * z));
    p.j1 = vec3<f32>(0.0, fy / z, -fy * yc / (z * z));
    // Rows of P = J K; Σ2D = P Pᵀ + LOW_PASS I.
    p.p0 = p.j0 * p.k;
    p.p1 = p.j1 * p.k;
    p.cov = vec3<f32>(dot(p.p0, p.p0) + LOW_PASS, dot(p.p0, p.p1), dot(p.p1, p.p1) + LOW_PASS);
    // det(P Pᵀ + λI) = |p0 × p1|² + λ(|p0|² + |p1|²) + λ²: exact algebra, but free of the
    // cancellation a·c - b² suffers in f32 for long thin Gaussians.
    let cr = cross(p.p0, p.p1);
    p.det = dot(cr, cr) + LOW_PASS * (p.cov.x + p.cov.z - 2.0 * LOW_PASS) + LOW_PASS * LOW_PASS;
    if !(p.det > 0.0 && is_finite(p.det)) {
        return p;
    }
    p.conic = vec3<f32>(p.cov.z / p.det, -p.cov.y / p.det, p.cov.x / p.det);
    p.mean2d = vec2<f32>(fx * p.t.x / z + frame.focal.z, fy * p.t.y / z + frame.focal.w);
    p.visible = is_finite(p.mean2d.x) && is_finite(p.mean2d.y) && is_finite(p.conic.x)
        && is_finite(p.conic.y) && is_finite(p.conic.z);
    return p;
}
