// Partial sums: each workgroup reduces WG * ITEMS consecutive-stride elements to one value.
// Specialised with: WG (threads per workgroup), ITEMS (elements per thread).

struct Params { len: u32, }

@group(0) @binding(0) var<storage, read> input: array<f32>;
@group(0) @binding(1) var<storage, read_write> partials: array<f32>;
@group(0) @binding(2) var<uniform> params: Params;

var<workgroup> scratch: array<f32, WG>;

@compute @workgroup_size(WG)
fn main(
    @builtin(local_invocation_index) lid: u32,
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
) {
    let group = wg.x + wg.y * nwg.x;
    let base = group * WG * ITEMS;
    // Strided loads keep neighbouring threads on neighbouring addresses.
    var acc = 0.0;
    for (var k = 0u; k < ITEMS; k++) {
        let i = base + k * WG + lid;
        if (i < params.len) {
            acc += input[i];
        }
    }
    scratch[lid] = acc;
    workgroupBarrier();
    for (var stride = WG / 2u; stride > 0u; stride /= 2u) {
        if (lid < stride) {
            scratch[lid] += scratch[lid + stride];
        }
        workgroupBarrier();
    }
    if (lid == 0u) {
        partials[group] = scratch[0];
    }
}
