// Stage 2 input: the number of tiles each Gaussian reaches (tile_test.wgsl) within its tile
// rectangle and the band's tile rows, in depth order, plus a trailing zero so that the
// exclusive scan's last element is the total number of intersections. Prefixed with
// tile_test.wgsl; specialised with TILE, WG (threads per workgroup).

struct CountParams {
    n: u32,
    // The band's tile rows [tile_y0, tile_y1) of the whole image's grid.
    tile_y0: u32,
    tile_y1: u32,
}

@group(0) @binding(0) var<storage, read> order: array<u32>;
@group(0) @binding(1) var<storage, read> rects: array<vec4<u32>>;
@group(0) @binding(2) var<storage, read_write> counts: array<u32>;
@group(0) @binding(3) var<uniform> params: CountParams;
@group(0) @binding(4) var<storage, read> projected: array<vec4<f32>>;

@compute @workgroup_size(WG)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = thread_index(gid, nwg, WG);
    if i < params.n {
        let g = order[i];
        let r = rects[g];
        let gaussian = tile_test_of(g);
        var count = 0u;
        for (var y = max(r.y, params.tile_y0); y < min(r.w, params.tile_y1); y++) {
            for (var x = r.x; x < r.z; x++) {
                count += u32(meets_tile(gaussian, x, y));
            }
        }
        counts[i] = count;
    } else if i == params.n {
        counts[i] = 0u;
    }
}
