// Row sums of blend_backward.wgsl added atomically by every row itself (adapters without
// subgroup operations).

fn tile_sum(v: f32) -> f32 {
    return v;
}

fn adds_tile_sum() -> bool {
    return true;
}
