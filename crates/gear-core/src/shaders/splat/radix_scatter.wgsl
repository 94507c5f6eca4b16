// Radix sort pass, step 3: each thread walks its chunk in order and moves every (key, value)
// to the next free slot of its digit (hist holds the scanned counts of radix_count.wgsl).
// Walking in order within a chunk, and chunks in order within a digit, makes the pass stable.
// Prefixed with radix_common.wgsl and radix_values_*.wgsl, which defines value_at(i) (the
// input values, or the identity on the first pass of an index sort).

@group(0) @binding(0) var<storage, read> keys_in: array<u32>;
@group(0) @binding(2) var<storage, read_write> hist: array<u32>;
@group(0) @binding(3) var<storage, read_write> keys_out: array<u32>;
@group(0) @binding(4) var<storage, read_write> values_out: array<u32>;

@compute @workgroup_size(WG)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let t = thread_index(gid, nwg, WG);
    if t >= params.threads {
        return;
    }
    let chunk = chunk_of(t);
    for (var i = chunk.x; i < chunk.y; i++) {
        let key = keys_in[i];
        let slot = digit(key) * params.threads + t;
        let dst = hist[slot];
        hist[slot] = dst + 1u;
        keys_out[dst] = key;
        values_out[dst] = value_at(i);
    }
}
