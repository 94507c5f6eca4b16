// How blend.wgsl and blend_backward.wgsl share work between the rows of a tile (one tile per
// workgroup), with subgroup operations (SUBGROUP feature): one invocation per subgroup (all
// eight rows when the subgroup holds at least eight invocations, else part of them) loads
// each Gaussian and broadcasts it, the rows stop together, and the backward's row sums are
// added up over the subgroup before one invocation makes the atomic adds.

// True for the first active invocation of the subgroup only (call in uniform control flow).
fn leads_tile() -> bool {
    return subgroupExclusiveAdd(1u) == 0u;
}

// Whether v holds for every row of the subgroup.
fn tile_all(v: bool) -> bool {
    return subgroupAll(v);
}

// Whether v holds for some row of the subgroup: a condition the whole subgroup branches on
// together (a branch that differs between rows would be masked, not skipped).
fn tile_any(v: bool) -> bool {
    return subgroupAny(v);
}

fn tile_sum(v: f32) -> f32 {
    return subgroupAdd(v);
}

fn from_leader_f32(v: f32) -> f32 {
    return subgroupBroadcastFirst(v);
}

fn from_leader_vec4(v: vec4<f32>) -> vec4<f32> {
    return subgroupBroadcastFirst(v);
}
