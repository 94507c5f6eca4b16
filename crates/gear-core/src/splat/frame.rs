//! The per-render uniform shared by the project, blend and backward kernels
//! (`Frame` in shaders/splat/common.wgsl; the kernels' tests check that the layouts match).

use bytemuck::{Pod, Zeroable};

use super::constants::{CLAMP_FACTOR, MAX_CHANNELS};
use super::kernels::{KernelParams, GPU_TILE};
use super::types::Camera;

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
pub struct Frame {
    /// Rows of world_to_cam (rotation xyz, translation w).
    rot: [[f32; 4]; 3],
    /// fx, fy, cx, cy.
    focal: [f32; 4],
    /// |x/z|, |y/z| limits of the Jacobian clamp (then two unused).
    limits: [f32; 4],
    pub n: u32,
    pub width: u32,
    pub height: u32,
    pub tiles_x: u32,
    pub tiles_y: u32,
    /// First image row of the band of rows this frame covers ([`Frame::band`]; 0 for a whole
    /// image): `height` and `tiles_y` count the band's rows and tiles, pixel centres keep
    /// their place in the whole image.
    pub row0: u32,
    pad: [u32; 2],
    background: [[f32; 4]; MAX_CHANNELS / 4],
}

impl KernelParams for Frame {
    const WGSL_NAME: &'static str = "Frame";
    const BINDING: u32 = 15;
}

impl Frame {
    pub fn new(camera: &Camera, n: usize, background: &[f32]) -> Self {
        let w = &camera.world_to_cam;
        let mut bg = [[0.0f32; 4]; MAX_CHANNELS / 4];
        for (c, v) in background.iter().enumerate() {
            bg[c / 4][c % 4] = *v;
        }
        let limit = |size: u32, focal: f32| {
            (CLAMP_FACTOR * 0.5 * f64::from(size) / f64::from(focal)) as f32
        };
        Frame {
            rot: [w[0], w[1], w[2]],
            focal: [camera.fx, camera.fy, camera.cx, camera.cy],
            limits: [
                limit(camera.width, camera.fx),
                limit(camera.height, camera.fy),
                0.0,
                0.0,
            ],
            n: n as u32,
            width: camera.width,
            height: camera.height,
            tiles_x: camera.width.div_ceil(GPU_TILE),
            tiles_y: camera.height.div_ceil(GPU_TILE),
            row0: 0,
            pad: [0; 2],
            background: bg,
        }
    }

    /// The band of `rows` image rows from row `row0` (a multiple of the tile size) of this
    /// whole-image frame. Everything else stays the whole image's, the Jacobian clamp's limits
    /// included, so a band renders exactly the pixels the whole frame would.
    pub fn band(&self, row0: u32, rows: u32) -> Frame {
        debug_assert!(
            self.row0 == 0 && row0.is_multiple_of(GPU_TILE) && row0 + rows <= self.height
        );
        Frame {
            height: rows,
            tiles_y: rows.div_ceil(GPU_TILE),
            row0,
            ..*self
        }
    }

    /// The band's first tile row in the whole image's tile grid.
    pub fn tile_row0(&self) -> u32 {
        self.row0 / GPU_TILE
    }

    pub fn tiles(&self) -> u32 {
        self.tiles_x * self.tiles_y
    }

    pub fn pixels(&self) -> usize {
        self.width as usize * self.height as usize
    }
}
