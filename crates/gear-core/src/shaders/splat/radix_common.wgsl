// Shared by radix_count.wgsl and radix_scatter.wgsl (both bind `params` here): the pass
// parameters, the chunk of keys each thread owns, and the digit a pass sorts by.
// Specialised with: BITS (digit width), WG (threads per workgroup).

struct SortParams {
    n: u32,
    shift: u32,
    chunk: u32,
    threads: u32,
}

@group(0) @binding(5) var<uniform> params: SortParams;

const BINS: u32 = 1u << BITS;

// [begin, end) of thread t's chunk of keys.
fn chunk_of(t: u32) -> vec2<u32> {
    let begin = t * params.chunk;
    return vec2<u32>(begin, min(begin + params.chunk, params.n));
}

// This pass's digit of key.
fn digit(key: u32) -> u32 {
    return (key >> params.shift) & (BINS - 1u);
}
