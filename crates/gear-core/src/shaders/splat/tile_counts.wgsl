// Stage 2 input: the number of tiles each Gaussian touches, in depth order, plus a trailing
// zero so that the exclusive scan's last element is the total number of intersections.

struct CountParams {
    n: u32,
}

@group(0) @binding(0) var<storage, read> order: array<u32>;
@group(0) @binding(1) var<storage, read> rects: array<vec4<u32>>;
@group(0) @binding(2) var<storage, read_write> counts: array<u32>;
@group(0) @binding(3) var<uniform> params: CountParams;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = gid.x + gid.y * nwg.x * 256u;
    if i < params.n {
        let r = rects[order[i]];
        counts[i] = (r.z - r.x) * (r.w - r.y);
    } else if i == params.n {
        counts[i] = 0u;
    }
}
