// Stage 6, one thread per pixel row of an 8 x 8 tile (TILE_GROUP tiles per workgroup): blends
// the tile's depth-sorted list front to back with the contract's guards, for the row's eight
// pixels at once (two vec4 quads). Writes the image (features, alpha, and depth when
// WITH_DEPTH) and, for the backward pass, each pixel's final transmittance and the end of the
// list prefix it consumed. Specialised with: CHANNELS, WITH_DEPTH, TILE (must be 8),
// TILE_GROUP, contract constants. Its work counters (blend_counts_*.wgsl, included before)
// are compiled in only for the counting variant.
//
// With subgroup operations (tile_share_subgroup.wgsl, TILE_GROUP = 1 so that a subgroup never
// spans two tiles) one invocation loads each Gaussian and broadcasts it to the other rows,
// and the rows stop walking the list together once all their pixels have stopped; without
// them (tile_share_rows.wgsl) every row loads for itself and stops on its own.
//
// Why rows of vec4s: on the software adapter every load from memory inside a loop is a
// per-lane gather, and with one thread per pixel those gathers took most of the time; here a
// Gaussian is loaded once per eight pixels. The per-pixel state lives in vectors, not arrays
// indexed by pixel (which would be gathers again), and per-pixel decisions are selects.
// Before any exponential, each row asks the entry which of its two quads the entry's 1/255
// ellipse reaches (row_span, blend_common.wgsl); a quad no row of the tile needs is skipped.
// With subgroups that skip is taken by the whole tile at once, which is what saves time on
// the software adapter (there a branch that differs between rows is masked, not skipped).

// Bindings 0-3 (projected, tile_values, ranges, features): blend_common.wgsl.
// [H*W*C features][H*W alpha][H*W depth, when WITH_DEPTH].
@group(0) @binding(4) var<storage, read_write> image: array<f32>;
// Per pixel: (bits of final T, end of the consumed list prefix).
@group(0) @binding(5) var<storage, read_write> pixel_state: array<u32>;

// Four pixels of a row.
struct Quad {
    features: array<vec4<f32>, CHANNELS>,
    depth: vec4<f32>,
    transmittance: vec4<f32>,
    consumed: vec4<u32>,
    // Blending has stopped (or the pixel is past the image edge).
    stopped: vec4<bool>,
}

fn new_quad(first: u32, row_len: u32, start: u32) -> Quad {
    var q: Quad;
    q.transmittance = vec4<f32>(1.0);
    q.consumed = vec4<u32>(start);
    q.stopped = vec4<u32>(first) + vec4<u32>(0u, 1u, 2u, 3u) >= vec4<u32>(row_len);
    return q;
}

// Blends list entry k (`e`, colour `own`) into the quad's pixels at x = xs, y = cy (pixels
// [first, first + 4) of a row of row_len); returns how many of them stopped.
fn blend_quad(
    q: ptr<function, Quad>,
    xs: vec4<f32>,
    cy: f32,
    first: u32,
    row_len: u32,
    e: Entry,
    own: ptr<function, array<f32, CHANNELS>>,
    k: u32,
) -> u32 {
    let v = evaluate_quad(e, xs, cy);
    let t = (*q).transmittance;
    let next = t * (1.0 - v.alpha);
    let hit = !(*q).stopped & v.passes;
    let stop = hit & next < vec4<f32>(MIN_TRANSMITTANCE);
    let blend = hit & !stop;
    count_quad(first, row_len, blend);
    (*q).stopped = (*q).stopped | stop;
    let w = select(vec4<f32>(0.0), v.alpha * t, blend);
    for (var c = 0u; c < CHANNELS; c++) {
        (*q).features[c] += w * (*own)[c];
    }
    if WITH_DEPTH {
        (*q).depth += w * e.head.z;
    }
    (*q).transmittance = select(t, next, blend);
    (*q).consumed = select((*q).consumed, vec4<u32>(k + 1u), blend);
    return dot(vec4<u32>(stop), vec4<u32>(1u));
}

fn store_quad(q: ptr<function, Quad>, first: u32, row_len: u32, row_start: u32) {
    let pixels = frame.width * frame.height;
    for (var i = 0u; i < 4u && first + i < row_len; i++) {
        let pix = row_start + first + i;
        let t = (*q).transmittance[i];
        for (var c = 0u; c < CHANNELS; c++) {
            image[pix * CHANNELS + c] = (*q).features[c][i] + t * background(c);
        }
        image[pixels * CHANNELS + pix] = 1.0 - t;
        if WITH_DEPTH {
            image[pixels * (CHANNELS + 1u) + pix] = (*q).depth[i];
        }
        pixel_state[2u * pix] = bitcast<u32>(t);
        pixel_state[2u * pix + 1u] = (*q).consumed[i];
    }
}

@compute @workgroup_size(TILE * TILE_GROUP)
fn main(
    @builtin(local_invocation_id) lid: vec3<u32>,
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
) {
    let tile = workgroup_index(wg, nwg) * TILE_GROUP + lid.x / TILE;
    if tile >= frame.tiles_x * frame.tiles_y {
        return;
    }
    // Rows below the image walk the list with the others, with no pixels.
    let row = tile_row(tile, lid.x % TILE);
    let start = ranges[2u * tile];
    let end = ranges[2u * tile + 1u];

    var left = new_quad(0u, row.len, start);
    var right = new_quad(4u, row.len, start);
    var live = row.len;
    let leader = leads_tile();
    var own: array<f32, CHANNELS>;
    for (var k = start; k < end; k++) {
        if tile_all(live == 0u) {
            break;
        }
        let entry = load_entry(k, leader, &own);
        // A quad whose pixel centres the entry's ellipse misses, or whose pixels have all
        // stopped, would blend nothing: skip it, exponentials included.
        let span = row_span(entry, row.cy);
        count_row(entry, span, tile, row, live);
        if tile_any(span_meets(span, row.xs) && !all(left.stopped)) {
            live -= blend_quad(&left, row.xs, row.cy, 0u, row.len, entry, &own, k);
        }
        if tile_any(span_meets(span, row.xs + 4.0) && !all(right.stopped)) {
            live -= blend_quad(&right, row.xs + 4.0, row.cy, 4u, row.len, entry, &own, k);
        }
    }
    store_quad(&left, 0u, row.len, row.start);
    store_quad(&right, 4u, row.len, row.start);
    flush_counts();
}
