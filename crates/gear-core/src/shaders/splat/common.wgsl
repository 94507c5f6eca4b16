// Shared by the per-frame kernels (project, blend and their backward passes): the frame
// uniform and small numeric helpers. Contract constants (NEAR, FAR, LOW_PASS, MIN_ALPHA,
// MAX_ALPHA, MIN_TRANSMITTANCE, QUAT_EPS), the GPU tile size TILE, and CHANNELS, WITH_DEPTH
// are prepended by the host at pipeline compile time.

struct Frame {
    // Rows of world_to_cam: rotation in xyz, translation in w.
    rot0: vec4<f32>,
    rot1: vec4<f32>,
    rot2: vec4<f32>,
    // fx, fy, cx, cy.
    focal: vec4<f32>,
    // |x/z| and |y/z| limits of the Jacobian clamp.
    limits: vec4<f32>,
    n: u32,
    width: u32,
    height: u32,
    tiles_x: u32,
    tiles_y: u32,
    pad0: u32,
    pad1: u32,
    pad2: u32,
    background: array<vec4<f32>, 16>,
}

@group(0) @binding(15) var<uniform> frame: Frame;

fn is_finite(x: f32) -> bool {
    return (bitcast<u32>(x) & 0x7f800000u) != 0x7f800000u;
}

fn background(c: u32) -> f32 {
    return frame.background[c / 4u][c % 4u];
}

// Exponent of the Gaussian at four pixels offset by (dx, dy) from its mean:
// -½ dᵀ conic d (conic = a, b, c).
fn gaussian_power(dx: vec4<f32>, dy: f32, conic: vec3<f32>) -> vec4<f32> {
    return -0.5 * (conic.x * dx * dx + conic.z * dy * dy) - conic.y * dx * dy;
}

// The pixel row `row` of `tile` that a blend thread (blend.wgsl, blend_backward.wgsl) works on.
struct TileRow {
    // Index of the row's first pixel in the image.
    start: u32,
    // Pixels of the row inside the image (0 for a row below it).
    len: u32,
    // Pixel-centre y, and the x of the centres of its first four pixels.
    cy: f32,
    xs: vec4<f32>,
}

fn tile_row(tile: u32, row: u32) -> TileRow {
    let py = (tile / frame.tiles_x) * TILE + row;
    let x0 = (tile % frame.tiles_x) * TILE;
    return TileRow(
        py * frame.width + x0,
        select(0u, min(TILE, frame.width - x0), py < frame.height),
        f32(py) + 0.5,
        f32(x0) + vec4<f32>(0.5, 1.5, 2.5, 3.5),
    );
}

// Index of a 1D thread in a grid folded into 2D (see gpu::workgroup_grid).
fn thread_index(gid: vec3<u32>, nwg: vec3<u32>, wg_size: u32) -> u32 {
    return gid.x + gid.y * nwg.x * wg_size;
}
