// Stage 6, one workgroup per TILE x TILE tile, one thread per pixel: blends the tile's
// depth-sorted list front to back with the contract's guards. Writes the image (features, alpha, and depth
// when WITH_DEPTH) and, for the backward pass, each pixel's final transmittance and the end of
// the list prefix it consumed. Specialised with: CHANNELS, WITH_DEPTH, contract constants.

// Per Gaussian: (u, v, z, opacity), (conic a, b, c, 0), pixel box (see project.wgsl).
@group(0) @binding(0) var<storage, read> projected: array<vec4<f32>>;
@group(0) @binding(1) var<storage, read> tile_values: array<u32>;
@group(0) @binding(2) var<storage, read> ranges: array<u32>;
@group(0) @binding(3) var<storage, read> features: array<f32>;
// [H*W*C features][H*W alpha][H*W depth, when WITH_DEPTH].
@group(0) @binding(4) var<storage, read_write> image: array<f32>;
// Per pixel: (bits of final T, end of the consumed list prefix).
@group(0) @binding(5) var<storage, read_write> pixel_state: array<u32>;

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
    let end = ranges[2u * tile + 1u];

    var acc: array<f32, CHANNELS>;
    var depth = 0.0;
    var transmittance = 1.0;
    var consumed = start;
    for (var k = start; k < end; k++) {
        let g = tile_values[k];
        let bounds = projected[3u * g + 2u];
        if any(centre < bounds.xy) || any(centre > bounds.zw) {
            continue;
        }
        let head = projected[3u * g];
        let power = gaussian_power(centre - head.xy, projected[3u * g + 1u].xyz);
        if power > 0.0 {
            continue;
        }
        let alpha = min(MAX_ALPHA, head.w * exp(power));
        if alpha < MIN_ALPHA {
            continue;
        }
        let next = transmittance * (1.0 - alpha);
        if next < MIN_TRANSMITTANCE {
            break;
        }
        let w = alpha * transmittance;
        for (var c = 0u; c < CHANNELS; c++) {
            acc[c] += w * features[g * CHANNELS + c];
        }
        if WITH_DEPTH {
            depth += w * head.z;
        }
        transmittance = next;
        consumed = k + 1u;
    }
    for (var c = 0u; c < CHANNELS; c++) {
        image[pix * CHANNELS + c] = acc[c] + transmittance * background(c);
    }
    image[pixels * CHANNELS + pix] = 1.0 - transmittance;
    if WITH_DEPTH {
        image[pixels * (CHANNELS + 1u) + pix] = depth;
    }
    pixel_state[2u * pix] = bitcast<u32>(transmittance);
    pixel_state[2u * pix + 1u] = consumed;
}
