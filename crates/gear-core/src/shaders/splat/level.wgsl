// The 1/255 level of a Gaussian of opacity o: alpha = o·exp(-½ dᵀ conic d) falls below
// MIN_ALPHA exactly where dᵀ conic d > level = 2 ln(o / MIN_ALPHA). Recomputed from the opacity
// wherever it is needed (projection, the tile test, the blend kernels' row test) rather than
// stored: the same expression on the same input gives the same value in every kernel.

fn level_of(opacity: f32) -> f32 {
    return 2.0 * max(log(opacity / MIN_ALPHA), 0.0);
}
