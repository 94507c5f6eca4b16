// Stage 5: [start, end) of each tile's run in the tile-sorted pair list. Tiles without pairs
// keep the zeros the host cleared them to.

struct RangeParams {
    pairs: u32,
}

@group(0) @binding(0) var<storage, read> tile_keys: array<u32>;
@group(0) @binding(1) var<storage, read_write> ranges: array<u32>;
@group(0) @binding(2) var<uniform> params: RangeParams;

@compute @workgroup_size(WG)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = thread_index(gid, nwg, WG);
    if i >= params.pairs {
        return;
    }
    let tile = tile_keys[i];
    if i == 0u || tile_keys[i - 1u] != tile {
        ranges[2u * tile] = i;
    }
    if i + 1u == params.pairs || tile_keys[i + 1u] != tile {
        ranges[2u * tile + 1u] = i + 1u;
    }
}
