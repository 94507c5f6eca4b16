// The forward blend's work counters (the counting variant; blend_counts_off.wgsl is the
// normal one). Each thread counts in private variables and adds its totals once at the end,
// so the atomics cost nothing per entry. Every counter is 64 bits: (low, high) words, the
// high word taking the low word's carry.
//
// counts[0..2] quad evaluations: pixels inside the image of every quad the thread evaluated
//               (its work; with subgroups this includes quads evaluated for another row);
// counts[2..4] row-rule evaluations: the CPU executor's evaluation rule applied to the same
//               walk (see count_row), for comparison;
// counts[4..6] contributions: pixels an entry was blended into.
@group(0) @binding(6) var<storage, read_write> counts: array<atomic<u32>, 6>;

var<private> quad_evaluations: u32;
var<private> row_evaluations: u32;
var<private> contributions: u32;

// The pixel columns [first, last] (image-clamped; first > last where the span falls between
// two centres) whose centres `span` holds on `row`, as the CPU executor's binning finds them.
fn span_columns(span: vec2<f32>) -> vec2<f32> {
    let last_column = f32(frame.width - 1u);
    return vec2<f32>(max(ceil(span.x - 0.5), 0.0), min(floor(span.y - 0.5), last_column));
}

// Whether columns [first, last] reach the tile's columns [x0, x0 + TILE - 1].
fn reaches_tile(columns: vec2<f32>, x0: f32) -> bool {
    return columns.x <= x0 + f32(TILE - 1u) && columns.y >= x0;
}

// Before entry `e` (row span `span`) is blended into `row` of `tile` with `live` of the row's
// pixels still blending: the CPU executor's rule, which evaluates the row's pixels when the
// row still blends and the tile is in the entry's list with this row marked. Its binning
// lists the tile when, over the tile's rows inside the image and the ellipse, the columns
// [min first, max last] reach the tile and some row's columns do; it marks the rows whose
// columns reach the tile (a span between two centres included).
fn count_row(e: Entry, span: vec2<f32>, tile: u32, row: TileRow, live: u32) {
    let x0 = row.xs.x - 0.5;
    if live == 0u || row.len == 0u || span.x > span.y || !reaches_tile(span_columns(span), x0) {
        return;
    }
    var lowest = 1e30;
    var highest = -1.0;
    for (var r = 0u; r < TILE; r++) {
        let other = tile_row(tile, r);
        let other_span = row_span(e, other.cy);
        if other.len > 0u && other_span.x <= other_span.y {
            let columns = span_columns(other_span);
            lowest = min(lowest, columns.x);
            highest = max(highest, columns.y);
        }
    }
    let tx = f32(tile % frame.tiles_x);
    let tile_size = f32(TILE);
    if lowest <= highest && floor(lowest / tile_size) <= tx && floor(highest / tile_size) >= tx {
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
