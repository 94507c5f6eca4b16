// Radix sort pass, step 1: each thread counts the digits of its own contiguous chunk of keys.
// Counts are laid out digit-major (hist[digit * threads + thread]) so that one exclusive scan
// of hist gives every (digit, thread) its first output slot, which keeps the sort stable.
// Specialised with: BITS (digit width).

struct SortParams {
    n: u32,
    shift: u32,
    chunk: u32,
    threads: u32,
}

@group(0) @binding(0) var<storage, read> keys: array<u32>;
@group(0) @binding(1) var<storage, read_write> hist: array<u32>;
@group(0) @binding(2) var<uniform> params: SortParams;

const BINS: u32 = 1u << BITS;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let t = gid.x + gid.y * nwg.x * 64u;
    if t >= params.threads {
        return;
    }
    for (var d = 0u; d < BINS; d++) {
        hist[d * params.threads + t] = 0u;
    }
    let begin = t * params.chunk;
    let end = min(begin + params.chunk, params.n);
    for (var i = begin; i < end; i++) {
        let d = (keys[i] >> params.shift) & (BINS - 1u);
        hist[d * params.threads + t] += 1u;
    }
}
