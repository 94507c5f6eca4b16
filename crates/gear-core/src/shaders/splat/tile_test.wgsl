// Whether a Gaussian can reach a pixel of a tile: the blend skips a pixel where
// dᵀ conic d > level = 2 ln(255 o) (alpha below 1/255), so a tile whose every point is past
// that level (with a margin for f32 rounding) needs no (tile, Gaussian) pair. Shared by
// tile_counts.wgsl and emit.wgsl, which must agree; where rounding could make them disagree
// the margin makes either answer correct. Needs `projected` (project.wgsl layout), level_of
// (level.wgsl) and TILE.

// Minimum of a q² + 2 b q t + c t² over t in [lo, hi] for fixed q (c > 0).
fn edge_minimum(q: f32, a: f32, b: f32, c: f32, lo: f32, hi: f32) -> f32 {
    let t = clamp(-b * q / c, lo, hi);
    return a * q * q + 2.0 * b * q * t + c * t * t;
}

// What meets_tile needs of a Gaussian, loaded once for all the tiles of its rectangle.
struct TileTest {
    mean: vec2<f32>,
    // Conic a, b, c and the level.
    conic: vec4<f32>,
}

fn tile_test_of(g: u32) -> TileTest {
    let head = projected[2u * g];
    return TileTest(head.xy, vec4<f32>(projected[2u * g + 1u].xyz, level_of(head.w)));
}

fn meets_tile(gaussian: TileTest, tx: u32, ty: u32) -> bool {
    let mean = gaussian.mean;
    let conic = gaussian.conic;
    let corner = vec2<f32>(f32(tx), f32(ty)) * f32(TILE);
    // Pixel centres of the tile relative to the mean, as a continuous rectangle.
    let lo = corner + vec2<f32>(0.5) - mean;
    let hi = corner + vec2<f32>(f32(TILE) - 0.5) - mean;
    var least = 0.0;
    if any(lo > vec2<f32>(0.0)) || any(hi < vec2<f32>(0.0)) {
        // The unconstrained minimum (the mean) is outside: the minimum is on an edge.
        let a = conic.x;
        let b = conic.y;
        let c = conic.z;
        least = min(
            min(edge_minimum(lo.x, a, b, c, lo.y, hi.y), edge_minimum(hi.x, a, b, c, lo.y, hi.y)),
            min(edge_minimum(lo.y, c, b, a, lo.x, hi.x), edge_minimum(hi.y, c, b, a, lo.x, hi.x)),
        );
    }
    // Rounding of the quadratic's terms, and of the pixel offsets at this distance from 0.
    let reach = max(abs(lo), abs(hi));
    let terms = conic.x * reach.x * reach.x + 2.0 * abs(conic.y) * reach.x * reach.y
        + conic.z * reach.y * reach.y;
    let position = abs(mean.x) + abs(mean.y) + corner.x + corner.y + 2.0 * f32(TILE);
    let margin = 1e-5 * (terms + 16.0 * position) + 1e-3;
    return !(least > conic.w + margin);
}
