// Indices in a dispatch grid folded into 2D when it has more than 65535 workgroups
// (gpu::workgroup_grid); the host prepends this to every rasterizer kernel. Grids are
// folded row-major, and workgroups past the requested count return early.

// Index of the workgroup.
fn workgroup_index(wg: vec3<u32>, nwg: vec3<u32>) -> u32 {
    return wg.x + wg.y * nwg.x;
}

// Index of a 1D thread in workgroups of wg_size threads (the 1D kernels pass WG, their
// workgroup size, which the host prepends from the constant it divides the work by).
fn thread_index(gid: vec3<u32>, nwg: vec3<u32>, wg_size: u32) -> u32 {
    return gid.x + gid.y * nwg.x * wg_size;
}
