// How blend.wgsl and blend_backward.wgsl share work between the rows of a tile without
// subgroup operations: not at all; every row loads each Gaussian, stops on its own, skips the
// quads it does not need on its own, and makes its own atomic adds.

fn leads_tile() -> bool {
    return true;
}

fn tile_all(v: bool) -> bool {
    return v;
}

fn tile_any(v: bool) -> bool {
    return v;
}

fn tile_sum(v: f32) -> f32 {
    return v;
}

fn from_leader_f32(v: f32) -> f32 {
    return v;
}

fn from_leader_vec4(v: vec4<f32>) -> vec4<f32> {
    return v;
}
