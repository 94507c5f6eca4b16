// Radix sort pass, step 3: each thread walks its chunk in order and moves every (key, value)
// to the next free slot of its digit (hist holds the scanned counts of radix_count.wgsl).
// Walking in order within a chunk, and chunks in order within a digit, makes the pass stable.
// Specialised with: BITS (digit width); prefixed with radix_values_*.wgsl, which defines
// value_at(i) (the input values, or the identity on the first pass of an index sort).

struct SortParams {
    n: u32,
    shift: u32,
    chunk: u32,
    threads: u32,
}

@group(0) @binding(0) var<storage, read> keys_in: array<u32>;
@group(0) @binding(2) var<storage, read_write> hist: array<u32>;
@group(0) @binding(3) var<storage, read_write> keys_out: array<u32>;
@group(0) @binding(4) var<storage, read_write> values_out: array<u32>;
@group(0) @binding(5) var<uniform> params: SortParams;

const BINS: u32 = 1u << BITS;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let t = gid.x + gid.y * nwg.x * 64u;
    if t >= params.threads {
        return;
    }
    let begin = t * params.chunk;
    let end = min(begin + params.chunk, params.n);
    for (var i = begin; i < end; i++) {
        let key = keys_in[i];
        let slot = ((key >> params.shift) & (BINS - 1u)) * params.threads + t;
        let dst = hist[slot];
        hist[slot] = dst + 1u;
        keys_out[dst] = key;
        values_out[dst] = value_at(i);
    }
}
