// Stage 1, one thread per Gaussian: cull, project (project_common.wgsl), then the
// opacity-aware radius, the tile rectangle, and the depth sort key.

// Per Gaussian: (u, v, z, opacity) then (conic a, b, c, 0).
@group(0) @binding(4) var<storage, read_write> projected: array<vec4<f32>>;
// Tile rectangle [x0, x1) x [y0, y1) as (x0, y0, x1, y1); all zero when culled.
@group(0) @binding(5) var<storage, read_write> rects: array<vec4<u32>>;
// f32 bits of camera z (ordered like the floats since z > 0); culled sort last.
@group(0) @binding(6) var<storage, read_write> depth_keys: array<u32>;
// Identity permutation, the payload the depth sort carries.
@group(0) @binding(7) var<storage, read_write> order: array<u32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = thread_index(gid, nwg, 256u);
    if i >= frame.n {
        return;
    }
    order[i] = i;
    projected[2u * i] = vec4<f32>(0.0);
    projected[2u * i + 1u] = vec4<f32>(0.0);
    rects[i] = vec4<u32>(0u);
    depth_keys[i] = 0xffffffffu;
    let p = project_gaussian(i);
    if !p.visible {
        return;
    }
    // Largest eigenvalue of Σ2D; (a-c)²/4 + b² avoids the cancellation of mid² - det.
    let half_diff = 0.5 * (p.cov.x - p.cov.z);
    let lambda_max = 0.5 * (p.cov.x + p.cov.z) + sqrt(half_diff * half_diff + p.cov.y * p.cov.y);
    let radius = ceil(sqrt(2.0 * max(log(p.opacity / MIN_ALPHA), 0.0) * lambda_max));
    if !is_finite(radius) {
        return;
    }
    let tile = f32(TILE);
    let lo = floor((p.mean2d - vec2<f32>(radius)) / tile);
    let hi = floor((p.mean2d + vec2<f32>(radius)) / tile);
    let last = vec2<f32>(f32(frame.tiles_x) - 1.0, f32(frame.tiles_y) - 1.0);
    if any(hi < vec2<f32>(0.0)) || any(lo > last) {
        return;
    }
    let lo_u = vec2<u32>(max(lo, vec2<f32>(0.0)));
    let hi_u = vec2<u32>(min(hi, last)) + vec2<u32>(1u);
    rects[i] = vec4<u32>(lo_u, hi_u);
    projected[2u * i] = vec4<f32>(p.mean2d, p.t.z, p.opacity);
    projected[2u * i + 1u] = vec4<f32>(p.conic, 0.0);
    depth_keys[i] = bitcast<u32>(p.t.z);
}
