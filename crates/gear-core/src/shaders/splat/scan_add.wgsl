// Exclusive prefix sum, second half of a level: adds each block's scanned offset to its
// elements. Specialised with: WG (threads per workgroup), BLOCK (the elements per block of
// scan_block.wgsl).

struct ScanParams {
    n: u32,
    blocks: u32,
}

@group(0) @binding(0) var<storage, read_write> data: array<u32>;
@group(0) @binding(1) var<storage, read> block_sums: array<u32>;
@group(0) @binding(2) var<uniform> params: ScanParams;

@compute @workgroup_size(WG)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = thread_index(gid, nwg, WG);
    if i < params.n {
        data[i] += block_sums[i / BLOCK];
    }
}
