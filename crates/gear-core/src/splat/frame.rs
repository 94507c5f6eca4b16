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
    pad: [u32; 3],
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
            pad: [0; 3],
            background: bg,
        }
    }

    pub fn tiles(&self) -> u32 {
        self.tiles_x * self.tiles_y
    }

    pub fn pixels(&self) -> usize {
        self.width as usize * self.height as usize
    }
}
