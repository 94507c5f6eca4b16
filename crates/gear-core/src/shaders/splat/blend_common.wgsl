// Shared by blend.wgsl and blend_backward.wgsl, which must agree on it: the inputs both read,
// the tile row a thread works on, the fetch of a list entry for all rows of a tile (who loads
// it is up to tile_share_*.wgsl, included before), the test of which quads of a row an entry
// can reach, and the contract's evaluation of an entry at four pixels of a row.

// Per Gaussian: (u, v, z, opacity), (conic a, b, c, det Σ2D) (see project.wgsl).
@group(0) @binding(0) var<storage, read> projected: array<vec4<f32>>;
// Per tile, its Gaussians in depth order ([start, end) of each tile in `ranges`).
@group(0) @binding(1) var<storage, read> tile_values: array<u32>;
@group(0) @binding(2) var<storage, read> ranges: array<u32>;
@group(0) @binding(3) var<storage, read> features: array<f32>;

// The pixel row `row` of `tile` that a blend thread works on.
struct TileRow {
    // Index of the row's first pixel in the band's images.
    start: u32,
    // Pixels of the row inside the image (0 for a row below it).
    len: u32,
    // Pixel-centre y (in the whole image), and the x of the centres of its first four pixels.
    cy: f32,
    xs: vec4<f32>,
}

fn tile_row(tile: u32, row: u32) -> TileRow {
    let py = (tile / frame.tiles_x) * TILE + row;
    let x0 = (tile % frame.tiles_x) * TILE;
    return TileRow(
        py * frame.width + x0,
        select(0u, min(TILE, frame.width - x0), py < frame.height),
        f32(frame.row0 + py) + 0.5,
        f32(x0) + vec4<f32>(0.5, 1.5, 2.5, 3.5),
    );
}

// A list entry as every row of the tile sees it.
struct Entry {
    // The Gaussian's index: set on the leading row only (leads_tile()).
    gaussian: u32,
    // (u, v, z, opacity).
    head: vec4<f32>,
    // Conic a, b, c and det Σ2D.
    conic: vec4<f32>,
}

// List entry k, its features into `own`. Call in uniform control flow, with `leader` from
// leads_tile().
fn load_entry(k: u32, leader: bool, own: ptr<function, array<f32, CHANNELS>>) -> Entry {
    var g = 0u;
    var head = vec4<f32>(0.0);
    var conic = vec4<f32>(0.0);
    if leader {
        g = tile_values[k];
        head = projected[2u * g];
        conic = projected[2u * g + 1u];
        for (var c = 0u; c < CHANNELS; c++) {
            (*own)[c] = features[g * CHANNELS + c];
        }
    }
    for (var c = 0u; c < CHANNELS; c++) {
        (*own)[c] = from_leader_f32((*own)[c]);
    }
    return Entry(g, from_leader_vec4(head), from_leader_vec4(conic));
}

// The x interval [lo, hi] that entry `e`'s 1/255 ellipse spans on the pixel row y = cy,
// widened by ROW_SPAN_SLACK pixels; empty (lo > hi) where the ellipse misses the row. The
// blend kernels test it before evaluating a quad, and skip the quads no row of the tile needs
// (those whose pixel centres lie outside it on every row, or whose pixels have all stopped).
// With conic (a, b, c) and D = det Σ2D, dᵀ conic d <= level' on the row at dy spans
// u - (b / a)·dy ± sqrt((level'·a·D - dy²) / (a²·D)): no a·c - b², so no cancellation for long
// thin Gaussians. level' is the level widened by ROW_LEVEL_MARGIN (relative and absolute) so
// that f32 rounding never makes a quad skip a pixel its own alpha test would take. The
// bounds are recomputed per entry rather than stored: on the software adapter loading a third
// vec4 per entry cost more (10-25 % of the forward) than the row test saves.
fn row_span(e: Entry, cy: f32) -> vec2<f32> {
    let level = level_of(e.head.w) * (1.0 + ROW_LEVEL_MARGIN) + ROW_LEVEL_MARGIN;
    let a = e.conic.x;
    let dy = cy - e.head.y;
    let room = level * a * e.conic.w - dy * dy;
    let half = sqrt(max(room, 0.0) / (a * a * e.conic.w)) + ROW_SPAN_SLACK;
    let centre = e.head.x - e.conic.y / a * dy;
    return select(vec2<f32>(1.0, -1.0), vec2<f32>(centre - half, centre + half), room >= 0.0);
}

// Whether `span` (row_span) holds one of the pixel centres xs (ascending) of a quad.
fn span_meets(span: vec2<f32>, xs: vec4<f32>) -> bool {
    return span.y >= xs.x && span.x <= xs.w;
}

// An entry at four pixels of a row.
struct QuadEval {
    // Pixel centres minus the mean.
    dx: vec4<f32>,
    dy: f32,
    // exp(-½ dᵀ conic d).
    gauss: vec4<f32>,
    // opacity · gauss, and alpha = that clamped to MAX_ALPHA.
    raw: vec4<f32>,
    alpha: vec4<f32>,
    // The contract's per-pixel guards pass: power <= 0 and alpha >= MIN_ALPHA.
    passes: vec4<bool>,
}

// Entry `e` at the pixels x = xs, y = cy.
fn evaluate_quad(e: Entry, xs: vec4<f32>, cy: f32) -> QuadEval {
    let dx = xs - e.head.x;
    let dy = cy - e.head.y;
    let power = -0.5 * (e.conic.x * dx * dx + e.conic.z * dy * dy) - e.conic.y * dx * dy;
    let gauss = exp(power);
    let raw = e.head.w * gauss;
    let alpha = min(vec4<f32>(MAX_ALPHA), raw);
    let passes = power <= vec4<f32>(0.0) & alpha >= vec4<f32>(MIN_ALPHA);
    return QuadEval(dx, dy, gauss, raw, alpha, passes);
}
