// Backward of stage 1, one thread per Gaussian, no atomics: recomputes the projection
// (project_common.wgsl) and chains the accumulated screen-space gradients (conic, 2D mean,
// opacity, z) back to means, quats, log_scales and opacity logits. Culled Gaussians get zero.

// Per Gaussian 8 values: dL/d(conic a, b, c, u, v, opacity, z, unused).
@group(0) @binding(4) var<storage, read> geometry: array<f32>;
// Packed output: means 3N, quats 4N, log_scales 3N, opacity N (features follow, written by
// blend_backward.wgsl).
@group(0) @binding(5) var<storage, read_write> gradients: array<f32>;

fn write_gradients(i: u32, d_mean: vec3<f32>, d_quat: vec4<f32>, d_log_scale: vec3<f32>, d_logit: f32) {
    let n = frame.n;
    for (var k = 0u; k < 3u; k++) {
        gradients[3u * i + k] = d_mean[k];
        gradients[7u * n + 3u * i + k] = d_log_scale[k];
    }
    for (var k = 0u; k < 4u; k++) {
        gradients[3u * n + 4u * i + k] = d_quat[k];
    }
    gradients[10u * n + i] = d_logit;
}

// dL/dq_n from dL/dR for R = rotation(q_n), q_n = (w, x, y, z); g[c][r] is dL/dR[r][c].
fn rotation_backward(q: vec4<f32>, g: mat3x3<f32>) -> vec4<f32> {
    let w = q.x;
    let x = q.y;
    let y = q.z;
    let z = q.w;
    let g00 = g[0][0];
    let g01 = g[1][0];
    let g02 = g[2][0];
    let g10 = g[0][1];
    let g11 = g[1][1];
    let g12 = g[2][1];
    let g20 = g[0][2];
    let g21 = g[1][2];
    let g22 = g[2][2];
    let dw = -z * g01 + y * g02 + z * g10 - x * g12 - y * g20 + x * g21;
    let dx = y * g01 + z * g02 + y * g10 - 2.0 * x * g11 - w * g12 + z * g20 + w * g21 - 2.0 * x * g22;
    let dy = -2.0 * y * g00 + x * g01 + w * g02 + x * g10 + z * g12 - w * g20 + z * g21 - 2.0 * y * g22;
    let dz = -2.0 * z * g00 - w * g01 + x * g02 + w * g10 - 2.0 * z * g11 + y * g12 + x * g20 + y * g21;
    return 2.0 * vec4<f32>(dw, dx, dy, dz);
}

@compute @workgroup_size(WG)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = thread_index(gid, nwg, WG);
    if i >= frame.n {
        return;
    }
    let p = project_gaussian(i);
    // A Gaussian the forward culled, or one that touched no tile, received no screen gradient.
    if !p.visible {
        write_gradients(i, vec3<f32>(0.0), vec4<f32>(0.0), vec3<f32>(0.0), 0.0);
        return;
    }
    let ga = geometry[8u * i];
    let gb = geometry[8u * i + 1u];
    let gc = geometry[8u * i + 2u];
    let g_mean2d = vec2<f32>(geometry[8u * i + 3u], geometry[8u * i + 4u]);
    let g_opacity = geometry[8u * i + 5u];
    let g_depth = geometry[8u * i + 6u];

    // conic = Σ2D⁻¹ => dL/dΣ2D = -conic G conic, written with conic entries (no 1/det², which
    // overflows f32 for large footprints). The off-diagonal is one parameter appearing twice.
    let a = p.conic.x;
    let b = p.conic.y;
    let c = p.conic.z;
    let g_cov_a = -ga * a * a - gb * a * b - gc * b * b;
    let g_cov_c = -ga * b * b - gb * b * c - gc * c * c;
    let g_cov_b = -2.0 * ga * a * b - gb * (a * c + b * b) - 2.0 * gc * b * c;
    // Σ2D = P Pᵀ + λI with rows p0, p1 of P = J K.
    let g_p0 = 2.0 * g_cov_a * p.p0 + g_cov_b * p.p1;
    let g_p1 = g_cov_b * p.p0 + 2.0 * g_cov_c * p.p1;
    let g_j0 = p.k * g_p0;
    let g_j1 = p.k * g_p1;
    // dL/dK = j0 g_p0ᵀ + j1 g_p1ᵀ (column k: j0 * g_p0[k] + j1 * g_p1[k]).
    let g_k = mat3x3<f32>(
        p.j0 * g_p0.x + p.j1 * g_p1.x,
        p.j0 * g_p0.y + p.j1 * g_p1.y,
        p.j0 * g_p0.z + p.j1 * g_p1.z,
    );
    // K = W_rot M, M = R diag(s).
    let g_m = transpose(world_rotation()) * g_k;
    let g_rot = mat3x3<f32>(g_m[0] * p.scale.x, g_m[1] * p.scale.y, g_m[2] * p.scale.z);
    let g_scale = vec3<f32>(dot(g_m[0], p.rot[0]), dot(g_m[1], p.rot[1]), dot(g_m[2], p.rot[2]));
    let g_qn = rotation_backward(p.qn, g_rot);
    var g_quat: vec4<f32>;
    if p.qnorm > QUAT_EPS {
        g_quat = (g_qn - p.qn * dot(p.qn, g_qn)) / p.qnorm;
    } else {
        g_quat = g_qn / QUAT_EPS;
    }

    // t enters through the 2D mean, the Jacobian (x', y' constant when clamped) and depth.
    let fx = frame.focal.x;
    let fy = frame.focal.y;
    let t = p.t;
    let z2 = t.z * t.z;
    let xc = -p.j0.z * z2 / fx;
    let yc = -p.j1.z * z2 / fy;
    var g_t = vec3<f32>(
        g_mean2d.x * fx / t.z,
        g_mean2d.y * fy / t.z,
        -(g_mean2d.x * fx * t.x + g_mean2d.y * fy * t.y) / z2 + g_depth,
    );
    g_t.z += -g_j0.x * fx / z2 + 2.0 * g_j0.z * fx * xc / (z2 * t.z) - g_j1.y * fy / z2
        + 2.0 * g_j1.z * fy * yc / (z2 * t.z);
    if !p.clamped.x {
        g_t.x -= g_j0.z * fx / z2;
    }
    if !p.clamped.y {
        g_t.y -= g_j1.z * fy / z2;
    }
    let g_mean = transpose(world_rotation()) * g_t;
    let g_logit = g_opacity * p.opacity * (1.0 - p.opacity);
    write_gradients(i, g_mean, g_quat, g_scale * p.scale, g_logit);
}
