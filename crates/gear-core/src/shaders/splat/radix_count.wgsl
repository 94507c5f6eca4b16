// Radix sort pass, step 1: each thread counts the digits of its own contiguous chunk of keys.
// Counts are laid out digit-major (hist[digit * threads + thread]) so that one exclusive scan
// of hist gives every (digit, thread) its first output slot, which keeps the sort stable.
// Prefixed with radix_common.wgsl.

@group(0) @binding(0) var<storage, read> keys: array<u32>;
@group(0) @binding(1) var<storage, read_write> hist: array<u32>;

@compute @workgroup_size(WG)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let t = thread_index(gid, nwg, WG);
    if t >= params.threads {
        return;
    }
    for (var d = 0u; d < BINS; d++) {
        hist[d * params.threads + t] = 0u;
    }
    let chunk = chunk_of(t);
    for (var i = chunk.x; i < chunk.y; i++) {
        hist[digit(keys[i]) * params.threads + t] += 1u;
    }
}
