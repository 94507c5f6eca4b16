// Stage 3, one thread per Gaussian in depth order: writes a (tile id, Gaussian) pair for every
// tile of its rectangle (within the band) that it reaches (tile_test.wgsl) at the scanned offset, never past the
// next Gaussian's offset; should rounding make it find fewer tiles than tile_counts.wgsl did,
// the rest of its slots get other tiles of its rectangle (harmless: the blend tests pixels).
// Pairs are thus in depth order, and a stable sort by tile id alone leaves each tile's list
// sorted by depth (ties by index).

struct EmitParams {
    n: u32,
    tiles_x: u32,
    // The band's tile rows [tile_y0, tile_y1) of the whole image's grid (tile ids are the
    // band's: counted from its first row).
    tile_y0: u32,
    tile_y1: u32,
}

@group(0) @binding(0) var<storage, read> order: array<u32>;
@group(0) @binding(1) var<storage, read> rects: array<vec4<u32>>;
@group(0) @binding(2) var<storage, read> offsets: array<u32>;
@group(0) @binding(3) var<storage, read_write> tile_keys: array<u32>;
@group(0) @binding(4) var<storage, read_write> tile_values: array<u32>;
@group(0) @binding(5) var<uniform> params: EmitParams;
@group(0) @binding(6) var<storage, read> projected: array<vec4<f32>>;

@compute @workgroup_size(WG)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = thread_index(gid, nwg, WG);
    if i >= params.n {
        return;
    }
    let g = order[i];
    let r = rects[g];
    let gaussian = tile_test_of(g);
    var slot = offsets[i];
    let end = offsets[i + 1u];
    for (var round = 0u; round < 2u && slot < end; round++) {
        for (var y = max(r.y, params.tile_y0); y < min(r.w, params.tile_y1); y++) {
            for (var x = r.x; x < r.z; x++) {
                if slot < end && meets_tile(gaussian, x, y) == (round == 0u) {
                    tile_keys[slot] = (y - params.tile_y0) * params.tiles_x + x;
                    tile_values[slot] = g;
                    slot++;
                }
            }
        }
    }
}
