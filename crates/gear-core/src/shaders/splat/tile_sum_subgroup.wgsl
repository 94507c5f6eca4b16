// Row sums of blend_backward.wgsl added up over the subgroup (a whole 8-row tile when the
// subgroup holds at least 8 invocations, else part of it); one invocation per subgroup then
// makes the atomic adds. Needs the SUBGROUP feature.

fn tile_sum(v: f32) -> f32 {
    return subgroupAdd(v);
}

// True for the first active invocation of the subgroup only.
fn adds_tile_sum() -> bool {
    return subgroupExclusiveAdd(1u) == 0u;
}
