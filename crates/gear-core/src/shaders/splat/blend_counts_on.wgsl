// The forward blend's work counters (the counting variant; blend_counts_off.wgsl is the
// normal one). Each thread counts in private variables and adds its totals once at the end,
// so the atomics cost nothing per entry. Every counter is 64 bits: (low, high) words, the
// high word taking the low word's carry.
//
// counts[0..2] quad evaluations: pixels inside the image of every quad the thread evaluated
//               (its work; with subgroups this includes quads evaluated for another row);
// counts[2..4] row-rule evaluations: the pixels inside the image of every row still
//               blending whose row span meets one of their centres (the CPU executor's
//               evaluation rule, counted here for comparison);
// counts[4..6] contributions: pixels an entry was blended into.
@group(0) @binding(6) var<storage, read_write> counts: array<atomic<u32>, 6>;

var<private> quad_evaluations: u32;
var<private> row_evaluations: u32;
var<private> contributions: u32;

// Before entry `span` is blended into `row` with `live` of its pixels still blending.
fn count_row(span: vec2<f32>, row: TileRow, live: u32) {
    let last = row.xs.x + f32(max(row.len, 1u) - 1u);
    if live > 0u && span.y >= row.xs.x && span.x <= last {
        row_evaluations += row.len;
    }
}

// A quad of pixels [first, first + 4) of a row of `row_len` pixels was evaluated, and blended
// into the pixels `blended`.
fn count_quad(first: u32, row_len: u32, blended: vec4<bool>) {
    quad_evaluations += min(4u, row_len - min(first, row_len));
    contributions += dot(vec4<u32>(blended), vec4<u32>(1u));
}

fn add_count(word: u32, value: u32) {
    let old = atomicAdd(&counts[word], value);
    if old > 0xffffffffu - value {
        atomicAdd(&counts[word + 1u], 1u);
    }
}

fn flush_counts() {
    add_count(0u, quad_evaluations);
    add_count(2u, row_evaluations);
    add_count(4u, contributions);
}
