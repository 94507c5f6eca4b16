// Shared by the per-frame kernels (project, blend and their backward passes): the frame
// uniform and small helpers. Contract constants (NEAR, FAR, LOW_PASS, MIN_ALPHA,
// MAX_ALPHA, MIN_TRANSMITTANCE, QUAT_EPS), the GPU tile size TILE, and CHANNELS, WITH_DEPTH
// are prepended by the host at pipeline compile time. `Frame` has the layout and binding of
// the host's `Frame` (splat/frame.rs); the kernels' tests compare the two.

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
    // First image row of the band this frame covers (height and tiles_y count the band's).
    row0: u32,
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
