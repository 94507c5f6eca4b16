// Backward of stage 6, one thread per pixel: replays the pixel's consumed list prefix back to
// front, recovering each T_i = T_{i+1} / (1 - alpha_i) from the stored final T, and accumulates
// per-Gaussian gradients (screen-space geometry, opacity, z, and features) with
// add_geometry / add_gradient (atomic_float.wgsl or atomic_cas.wgsl, chosen by the host).
// Specialised with: CHANNELS, WITH_DEPTH, contract constants.

@group(0) @binding(0) var<storage, read> projected: array<vec4<f32>>;
@group(0) @binding(1) var<storage, read> tile_values: array<u32>;
@group(0) @binding(2) var<storage, read> ranges: array<u32>;
@group(0) @binding(3) var<storage, read> features: array<f32>;
@group(0) @binding(4) var<storage, read> pixel_state: array<u32>;
// [H*W*C dL/dfeatures][H*W dL/dalpha][H*W dL/ddepth, when WITH_DEPTH].
@group(0) @binding(5) var<storage, read> image_grads: array<f32>;

// Offset of dL/dfeatures in the packed output: means 3N, quats 4N, log_scales 3N, opacity N.
fn feature_base() -> u32 {
    return 11u * frame.n;
}

@compute @workgroup_size(TILE, TILE)
fn main(
    @builtin(local_invocation_id) lid: vec3<u32>,
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
) {
    let tile = wg.x + wg.y * nwg.x;
    let px = (tile % frame.tiles_x) * TILE + lid.x;
    let py = (tile / frame.tiles_x) * TILE + lid.y;
    if tile >= frame.tiles_x * frame.tiles_y || px >= frame.width || py >= frame.height {
        return;
    }
    let pixels = frame.width * frame.height;
    let pix = py * frame.width + px;
    let centre = vec2<f32>(f32(px) + 0.5, f32(py) + 0.5);
    let start = ranges[2u * tile];
    let final_t = bitcast<f32>(pixel_state[2u * pix]);
    let consumed = pixel_state[2u * pix + 1u];

    var grad_f: array<f32, CHANNELS>;
    // Σ_{j>i} w_j f_j + T_final · background, built up from the back.
    var behind_f: array<f32, CHANNELS>;
    for (var c = 0u; c < CHANNELS; c++) {
        grad_f[c] = image_grads[pix * CHANNELS + c];
        behind_f[c] = final_t * background(c);
    }
    let grad_alpha_img = image_grads[pixels * CHANNELS + pix];
    var grad_depth = 0.0;
    if WITH_DEPTH {
        grad_depth = image_grads[pixels * (CHANNELS + 1u) + pix];
    }
    var behind_d = 0.0;
    var transmittance = final_t;
    let base = feature_base();
    for (var k = consumed; k > start; k--) {
        let g = tile_values[k - 1u];
        let bounds = projected[3u * g + 2u];
        if any(centre < bounds.xy) || any(centre > bounds.zw) {
            continue;
        }
        let head = projected[3u * g];
        let conic = projected[3u * g + 1u].xyz;
        let d = centre - head.xy;
        let power = gaussian_power(d, conic);
        if power > 0.0 {
            continue;
        }
        let gauss = exp(power);
        let raw = head.w * gauss;
        let alpha = min(MAX_ALPHA, raw);
        if alpha < MIN_ALPHA {
            continue;
        }
        let keep = 1.0 - alpha;
        let t_i = transmittance / keep;
        let w = alpha * t_i;
        // dL/dalpha_i: own contribution T_i·f_i minus what it hides behind it, 1/(1-alpha_i)
        // times everything blended after it (including the background and alpha image).
        var grad_a = grad_alpha_img * final_t / keep;
        for (var c = 0u; c < CHANNELS; c++) {
            let f = features[g * CHANNELS + c];
            grad_a += grad_f[c] * (f * t_i - behind_f[c] / keep);
            add_gradient(base + g * CHANNELS + c, w * grad_f[c]);
            behind_f[c] += w * f;
        }
        if WITH_DEPTH {
            grad_a += grad_depth * (head.z * t_i - behind_d / keep);
            add_geometry(8u * g + 6u, w * grad_depth);
            behind_d += w * head.z;
        }
        if raw <= MAX_ALPHA {
            let grad_power = grad_a * alpha;
            add_geometry(8u * g, -0.5 * d.x * d.x * grad_power);
            add_geometry(8u * g + 1u, -d.x * d.y * grad_power);
            add_geometry(8u * g + 2u, -0.5 * d.y * d.y * grad_power);
            add_geometry(8u * g + 3u, (conic.x * d.x + conic.y * d.y) * grad_power);
            add_geometry(8u * g + 4u, (conic.y * d.x + conic.z * d.y) * grad_power);
            add_geometry(8u * g + 5u, grad_a * gauss);
        }
        transmittance = t_i;
    }
}
