// Exclusive prefix sum, first level: each workgroup scans one block of WG * ITEMS u32 in
// place and writes the block's total to block_sums (scanned by the next level, then added back
// by scan_add.wgsl). One thread scans the WG partial sums serially: on a software adapter that
// beats a tree of barriers.
// Specialised with: WG, ITEMS.

struct ScanParams {
    n: u32,
    blocks: u32,
}

@group(0) @binding(0) var<storage, read_write> data: array<u32>;
@group(0) @binding(1) var<storage, read_write> block_sums: array<u32>;
@group(0) @binding(2) var<uniform> params: ScanParams;

var<workgroup> partial: array<u32, WG>;

@compute @workgroup_size(WG)
fn main(
    @builtin(local_invocation_index) lid: u32,
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
) {
    let block = workgroup_index(wg, nwg);
    let base = block * WG * ITEMS + lid * ITEMS;
    var local: array<u32, ITEMS>;
    var sum = 0u;
    for (var k = 0u; k < ITEMS; k++) {
        let idx = base + k;
        local[k] = sum;
        if idx < params.n {
            sum += data[idx];
        }
    }
    partial[lid] = sum;
    workgroupBarrier();
    if lid == 0u {
        var running = 0u;
        for (var j = 0u; j < WG; j++) {
            let v = partial[j];
            partial[j] = running;
            running += v;
        }
        if block < params.blocks {
            block_sums[block] = running;
        }
    }
    workgroupBarrier();
    let offset = partial[lid];
    for (var k = 0u; k < ITEMS; k++) {
        let idx = base + k;
        if idx < params.n {
            data[idx] = local[k] + offset;
        }
    }
}
