//! Workgroup grids: WebGPU caps each dimension at 65,535 workgroups, so long 1D launches are
//! folded into 2D. Shaders recover the linear index as `wg.x + wg.y * num_wg.x`.

pub const MAX_WORKGROUPS_PER_DIM: u32 = 65_535;

/// Grid `(x, y, 1)` with `x * y >= workgroups` and both within the per-dimension cap.
pub fn workgroup_grid(workgroups: u32) -> (u32, u32, u32) {
    if workgroups <= MAX_WORKGROUPS_PER_DIM {
        return (workgroups.max(1), 1, 1);
    }
    let y = workgroups.div_ceil(MAX_WORKGROUPS_PER_DIM);
    (workgroups.div_ceil(y), y, 1)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grid_covers_and_respects_cap() {
        for n in [0u32, 1, 65_535, 65_536, 1_000_000, 70_000_000] {
            let (x, y, z) = workgroup_grid(n);
            assert!(x <= MAX_WORKGROUPS_PER_DIM && y <= MAX_WORKGROUPS_PER_DIM && z == 1);
            assert!(u64::from(x) * u64::from(y) >= u64::from(n.max(1)));
        }
    }
}
