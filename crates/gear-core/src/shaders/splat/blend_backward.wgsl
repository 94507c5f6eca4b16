// Backward of stage 6, one thread per pixel row of an 8 x 8 tile, the row's eight pixels as
// two vec4 quads (as in blend.wgsl, and for the same reason: one load of a Gaussian per eight
// pixels, per-pixel state in vectors, per-pixel decisions as selects). Replays each pixel's
// consumed list prefix back to front, recovering each T_i = T_{i+1} / (1 - alpha_i) from the
// stored final T, sums the row's gradient contributions per Gaussian, and adds them to the
// per-Gaussian gradients (screen-space geometry, opacity, z, features) with add_geometry /
// add_gradient (atomic_float.wgsl or atomic_cas.wgsl, chosen by the host).
//
// The atomics (on the software adapter a compare-and-swap loop per lane: x86 has no float
// atomic add) and the loads of each Gaussian (a gather per lane there) dominate, so with
// subgroup operations one invocation per subgroup does both for all of its rows
// (tile_share_subgroup.wgsl): it loads the Gaussian and broadcasts it, and adds the rows' sums
// totalled over the subgroup. Without them every row does both itself (tile_share_rows.wgsl).
// Either way each row first sums its pixels' contributions, and all rows of a tile walk its
// list in step, from the longest consumed prefix, so a subgroup sees one Gaussian at a time.
// Specialised with: CHANNELS, WITH_DEPTH, FEATURE_GRADS, TILE (must be 8), contract constants.
// Without FEATURE_GRADS (a caller whose features need no gradient) the features are still read,
// since dL/dalpha depends on them, but their gradients are neither summed nor added (per
// channel, a sum over the tile and an atomic per Gaussian the tile touches).

// Bindings 0-3 (projected, tile_values, ranges, features): blend_common.wgsl.
@group(0) @binding(4) var<storage, read> pixel_state: array<u32>;
// [H*W*C dL/dfeatures][H*W dL/dalpha][H*W dL/ddepth, when WITH_DEPTH].
@group(0) @binding(5) var<storage, read> image_grads: array<f32>;

// Offset of dL/dfeatures in the packed output: means 3N, quats 4N, log_scales 3N, opacity N.
fn feature_base() -> u32 {
    return 11u * frame.n;
}

// Four pixels of a row, replayed from the back. Pixels past the image edge have consumed
// nothing (consumed = 0 is below every list entry).
struct Quad {
    // T after the entries replayed so far, i.e. T_{i+1} for the next one, i.
    transmittance: vec4<f32>,
    final_t: vec4<f32>,
    consumed: vec4<u32>,
    grad_alpha: vec4<f32>,
    grad_depth: vec4<f32>,
    grad_f: array<vec4<f32>, CHANNELS>,
    // Σ_{j>i} w_j f_j + T_final · background, and Σ_{j>i} w_j z_j.
    behind_f: array<vec4<f32>, CHANNELS>,
    behind_d: vec4<f32>,
}

// A row's summed contributions to one Gaussian: conic a, b, c, mean u, v, opacity, z
// (add_geometry slots 0..6), and the features.
struct Sums {
    geometry: array<f32, 7>,
    features: array<f32, CHANNELS>,
    touched: bool,
}

// End of the longest consumed prefix among the tile's pixels.
var<workgroup> tile_last: atomic<u32>;
var<workgroup> tile_last_copy: u32;

fn sum4(v: vec4<f32>) -> f32 {
    return dot(v, vec4<f32>(1.0));
}

fn load_quad(first: u32, row_len: u32, row_start: u32) -> Quad {
    let pixels = frame.width * frame.height;
    var q: Quad;
    for (var i = 0u; i < 4u && first + i < row_len; i++) {
        let pix = row_start + first + i;
        q.final_t[i] = bitcast<f32>(pixel_state[2u * pix]);
        q.consumed[i] = pixel_state[2u * pix + 1u];
        q.grad_alpha[i] = image_grads[pixels * CHANNELS + pix];
        if WITH_DEPTH {
            q.grad_depth[i] = image_grads[pixels * (CHANNELS + 1u) + pix];
        }
        for (var c = 0u; c < CHANNELS; c++) {
            q.grad_f[c][i] = image_grads[pix * CHANNELS + c];
        }
    }
    q.transmittance = q.final_t;
    for (var c = 0u; c < CHANNELS; c++) {
        q.behind_f[c] = q.final_t * background(c);
    }
    return q;
}

// Replays list entry k (`e`, colour `own`) at the quad's pixels x = xs, y = cy, adding the
// contributions to sums. Values of pixels the entry does not touch are computed but never
// selected, so they cannot leak an overflow into the sums.
fn replay_quad(
    q: ptr<function, Quad>,
    xs: vec4<f32>,
    cy: f32,
    e: Entry,
    own: ptr<function, array<f32, CHANNELS>>,
    k: u32,
    sums: ptr<function, Sums>,
) {
    let v = evaluate_quad(e, xs, cy);
    let dx = v.dx;
    let dy = v.dy;
    let alpha = v.alpha;
    let hit = vec4<u32>(k) <= (*q).consumed & v.passes;
    let zero = vec4<f32>(0.0);
    let keep = 1.0 - alpha;
    let t_i = (*q).transmittance / keep;
    let w = alpha * t_i;
    // dL/dalpha_i: own contribution T_i·f_i minus what it hides behind it, 1/(1-alpha_i)
    // times everything blended after it (background and alpha image included).
    var grad_a = (*q).grad_alpha * (*q).final_t / keep;
    for (var c = 0u; c < CHANNELS; c++) {
        let f = (*own)[c];
        let behind = (*q).behind_f[c];
        grad_a += (*q).grad_f[c] * (f * t_i - behind / keep);
        if FEATURE_GRADS {
            (*sums).features[c] += sum4(select(zero, w * (*q).grad_f[c], hit));
        }
        (*q).behind_f[c] = select(behind, behind + w * f, hit);
    }
    if WITH_DEPTH {
        grad_a += (*q).grad_depth * (e.head.z * t_i - (*q).behind_d / keep);
        (*sums).geometry[6] += sum4(select(zero, w * (*q).grad_depth, hit));
        (*q).behind_d = select((*q).behind_d, (*q).behind_d + w * e.head.z, hit);
    }
    // The 0.999 clamp passes no gradient to opacity and power.
    let unclamped = hit & v.raw <= vec4<f32>(MAX_ALPHA);
    let grad_power = grad_a * alpha;
    (*sums).geometry[0] += sum4(select(zero, -0.5 * dx * dx * grad_power, unclamped));
    (*sums).geometry[1] += sum4(select(zero, -dx * dy * grad_power, unclamped));
    (*sums).geometry[2] += sum4(select(zero, -0.5 * dy * dy * grad_power, unclamped));
    (*sums).geometry[3] += sum4(
        select(zero, (e.conic.x * dx + e.conic.y * dy) * grad_power, unclamped),
    );
    (*sums).geometry[4] += sum4(
        select(zero, (e.conic.y * dx + e.conic.z * dy) * grad_power, unclamped),
    );
    (*sums).geometry[5] += sum4(select(zero, grad_a * v.gauss, unclamped));
    (*sums).touched = (*sums).touched || any(hit);
    (*q).transmittance = select((*q).transmittance, t_i, hit);
}

@compute @workgroup_size(TILE)
fn main(
    @builtin(local_invocation_id) lid: vec3<u32>,
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
) {
    let tile = workgroup_index(wg, nwg);
    if tile >= frame.tiles_x * frame.tiles_y {
        return;
    }
    // Rows below the image walk the list with the others, with no pixels.
    let row = tile_row(tile, lid.x);
    let start = ranges[2u * tile];

    var left = load_quad(0u, row.len, row.start);
    var right = load_quad(4u, row.len, row.start);
    let consumed = max(left.consumed, right.consumed);
    atomicMax(&tile_last, max(max(consumed.x, consumed.y), max(consumed.z, consumed.w)));
    workgroupBarrier();
    if lid.x == 0u {
        tile_last_copy = max(start, atomicLoad(&tile_last));
    }
    let last = workgroupUniformLoad(&tile_last_copy);

    let base = feature_base();
    let leader = leads_tile();
    var own: array<f32, CHANNELS>;
    for (var k = last; k > start; k--) {
        let entry = load_entry(k - 1u, leader, &own);
        // As in blend.wgsl: a quad the entry's ellipse misses, or whose pixels' consumed
        // prefixes all end before it, replays nothing; an entry no quad of the tile needs
        // adds nothing either.
        let span = row_span(entry, row.cy);
        let need_left = tile_any(span_meets(span, row.xs) && any(vec4<u32>(k) <= left.consumed));
        let need_right = tile_any(
            span_meets(span, row.xs + 4.0) && any(vec4<u32>(k) <= right.consumed),
        );
        if !need_left && !need_right {
            continue;
        }
        var sums = Sums();
        if need_left {
            replay_quad(&left, row.xs, row.cy, entry, &own, k, &sums);
        }
        if need_right {
            replay_quad(&right, row.xs + 4.0, row.cy, entry, &own, k, &sums);
        }
        if FEATURE_GRADS {
            for (var c = 0u; c < CHANNELS; c++) {
                sums.features[c] = tile_sum(sums.features[c]);
            }
        }
        for (var q = 0u; q < 7u; q++) {
            sums.geometry[q] = tile_sum(sums.geometry[q]);
        }
        let touched = tile_sum(select(0.0, 1.0, sums.touched)) > 0.0;
        if touched && leader {
            let g = entry.gaussian;
            if FEATURE_GRADS {
                for (var c = 0u; c < CHANNELS; c++) {
                    add_gradient(base + g * CHANNELS + c, sums.features[c]);
                }
            }
            for (var q = 0u; q < 6u; q++) {
                add_geometry(8u * g + q, sums.geometry[q]);
            }
            if WITH_DEPTH {
                add_geometry(8u * g + 6u, sums.geometry[6]);
            }
        }
    }
}
