// Backward of stage 6, one thread per pixel row of a tile: replays each pixel's consumed list
// prefix back to front, recovering each T_i = T_{i+1} / (1 - alpha_i) from the stored final T,
// sums the row's gradient contributions per Gaussian in registers, and adds them to the
// per-Gaussian gradients (screen-space geometry, opacity, z, features) with add_geometry /
// add_gradient (atomic_float.wgsl or atomic_cas.wgsl, chosen by the host). Atomics took over
// half of a per-pixel version's time on lavapipe; summing rows first made backward ~30% faster.
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

@compute @workgroup_size(TILE)
fn main(
    @builtin(local_invocation_id) lid: vec3<u32>,
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
) {
    let tile = wg.x + wg.y * nwg.x;
    let py = (tile / frame.tiles_x) * TILE + lid.x;
    if tile >= frame.tiles_x * frame.tiles_y || py >= frame.height {
        return;
    }
    let x0 = (tile % frame.tiles_x) * TILE;
    let row_len = min(TILE, frame.width - x0);
    let pixels = frame.width * frame.height;
    let start = ranges[2u * tile];
    let cy = f32(py) + 0.5;

    // Per pixel of the row: transmittance (from the back), consumed prefix end, image
    // gradients, and Σ_{j>i} w_j f_j + T_final · background (behind_f), Σ_{j>i} w_j z_j.
    var transmittance: array<f32, TILE>;
    var final_t: array<f32, TILE>;
    var consumed: array<u32, TILE>;
    var grad_alpha_img: array<f32, TILE>;
    var grad_depth: array<f32, TILE>;
    var behind_d: array<f32, TILE>;
    var grad_f: array<f32, TILE * CHANNELS>;
    var behind_f: array<f32, TILE * CHANNELS>;
    var last = start;
    for (var j = 0u; j < row_len; j++) {
        let pix = py * frame.width + x0 + j;
        final_t[j] = bitcast<f32>(pixel_state[2u * pix]);
        transmittance[j] = final_t[j];
        consumed[j] = pixel_state[2u * pix + 1u];
        last = max(last, consumed[j]);
        grad_alpha_img[j] = image_grads[pixels * CHANNELS + pix];
        if WITH_DEPTH {
            grad_depth[j] = image_grads[pixels * (CHANNELS + 1u) + pix];
        }
        behind_d[j] = 0.0;
        for (var c = 0u; c < CHANNELS; c++) {
            grad_f[j * CHANNELS + c] = image_grads[pix * CHANNELS + c];
            behind_f[j * CHANNELS + c] = final_t[j] * background(c);
        }
    }
    let base = feature_base();
    for (var k = last; k > start; k--) {
        let g = tile_values[k - 1u];
        let bounds = projected[3u * g + 2u];
        if cy < bounds.y || cy > bounds.w {
            continue;
        }
        let head = projected[3u * g];
        let conic = projected[3u * g + 1u].xyz;
        // This row's summed contributions to Gaussian g.
        var sum_geometry = array<f32, 7>();
        var sum_f = array<f32, CHANNELS>();
        var touched = false;
        for (var j = 0u; j < row_len; j++) {
            let centre = vec2<f32>(f32(x0 + j) + 0.5, cy);
            if k > consumed[j] || centre.x < bounds.x || centre.x > bounds.z {
                continue;
            }
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
            touched = true;
            let keep = 1.0 - alpha;
            let t_i = transmittance[j] / keep;
            let w = alpha * t_i;
            // dL/dalpha_i: own contribution T_i·f_i minus what it hides behind it,
            // 1/(1-alpha_i) times everything blended after it (background and alpha image
            // included).
            var grad_a = grad_alpha_img[j] * final_t[j] / keep;
            for (var c = 0u; c < CHANNELS; c++) {
                let f = features[g * CHANNELS + c];
                let at = j * CHANNELS + c;
                grad_a += grad_f[at] * (f * t_i - behind_f[at] / keep);
                sum_f[c] += w * grad_f[at];
                behind_f[at] += w * f;
            }
            if WITH_DEPTH {
                grad_a += grad_depth[j] * (head.z * t_i - behind_d[j] / keep);
                sum_geometry[6] += w * grad_depth[j];
                behind_d[j] += w * head.z;
            }
            if raw <= MAX_ALPHA {
                let grad_power = grad_a * alpha;
                sum_geometry[0] += -0.5 * d.x * d.x * grad_power;
                sum_geometry[1] += -d.x * d.y * grad_power;
                sum_geometry[2] += -0.5 * d.y * d.y * grad_power;
                sum_geometry[3] += (conic.x * d.x + conic.y * d.y) * grad_power;
                sum_geometry[4] += (conic.y * d.x + conic.z * d.y) * grad_power;
                sum_geometry[5] += grad_a * gauss;
            }
            transmittance[j] = t_i;
        }
        if touched {
            for (var c = 0u; c < CHANNELS; c++) {
                add_gradient(base + g * CHANNELS + c, sum_f[c]);
            }
            for (var q = 0u; q < 6u; q++) {
                add_geometry(8u * g + q, sum_geometry[q]);
            }
            if WITH_DEPTH {
                add_geometry(8u * g + 6u, sum_geometry[6]);
            }
        }
    }
}
