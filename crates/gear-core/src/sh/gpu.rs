//! The op's WGSL kernels (shaders/sh/), one thread per Gaussian, dispatched like the
//! rasterizer's (parameter uniform, folded grid, pooled buffers).

use bytemuck::{Pod, Zeroable};

use super::{coefficient_count, ShGradients, ShInput, MIN_DIR_NORM};
use crate::error::Result;
use crate::gpu::{GpuContext, ShaderSpec};
use crate::splat::kernel_dispatch::{dispatch, groups, storage, uniform, KernelParams};

/// Threads per workgroup of both kernels (the shaders' `WG`).
pub const WG: u32 = 256;

/// One WGSL source: the folded-grid indices, the kernel's bindings and entry point, then the
/// basis (which reads the `dirs` and `coeffs` the kernel declares).
macro_rules! sh_source {
    ($file:literal) => {
        concat!(
            include_str!("../shaders/splat/grid.wgsl"),
            include_str!(concat!("../shaders/sh/", $file, ".wgsl")),
            include_str!("../shaders/sh/basis.wgsl"),
        )
    };
}

const FORWARD: &str = sh_source!("forward");
const BACKWARD: &str = sh_source!("backward");

/// Gaussians in a dispatch (`ShParams` in forward.wgsl and backward.wgsl).
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
pub struct ShParams {
    pub n: u32,
}

impl KernelParams for ShParams {
    const WGSL_NAME: &'static str = "ShParams";
    const BINDING: u32 = 3;
}

fn specialise(spec: ShaderSpec, degree: u32) -> ShaderSpec {
    spec.with("WG", format!("{WG}u"))
        .with("DEGREE", format!("{degree}u"))
        .with("K", format!("{}u", coefficient_count(degree)))
        .with("MIN_DIR_NORM", format!("{:?}f", MIN_DIR_NORM as f32))
}

pub fn forward_kernel(degree: u32) -> ShaderSpec {
    specialise(ShaderSpec::new("sh_forward", FORWARD, "main"), degree)
}

pub fn backward_kernel(degree: u32) -> ShaderSpec {
    specialise(ShaderSpec::new("sh_backward", BACKWARD, "main"), degree)
}

/// `rgb` [N, 3] of `input`, computed on the GPU.
pub fn forward(input: &ShInput<'_, f32>) -> Result<Vec<f32>> {
    input.validate()?;
    let n = input.len();
    if n == 0 {
        return Ok(Vec::new());
    }
    let ctx = GpuContext::global()?;
    let dirs = ctx.upload(input.dirs)?;
    let coeffs = ctx.upload(input.coeffs)?;
    let rgb = ctx.storage::<f32>(3 * n)?;
    let params = uniform(ctx, &ShParams { n: n as u32 });
    let mut encoder = ctx.device.create_command_encoder(&Default::default());
    dispatch(
        ctx,
        &mut encoder,
        &forward_kernel(input.degree),
        &[
            (0, storage(&dirs)),
            (1, storage(&coeffs)),
            (2, storage(&rgb)),
            (ShParams::BINDING, params.as_entire_binding()),
        ],
        groups(n as u32, WG),
    );
    ctx.queue.submit(Some(encoder.finish()));
    ctx.read(&rgb, 3 * n)
}

/// Gradients of a loss with respect to `input`, given its gradient `grad_rgb` [N, 3],
/// computed on the GPU.
pub fn backward(input: &ShInput<'_, f32>, grad_rgb: &[f32]) -> Result<ShGradients<f32>> {
    input.validate()?;
    input.validate_grad(grad_rgb)?;
    let n = input.len();
    if n == 0 {
        return Ok(ShGradients {
            coeffs: Vec::new(),
            dirs: Vec::new(),
        });
    }
    let ctx = GpuContext::global()?;
    let dirs = ctx.upload(input.dirs)?;
    let coeffs = ctx.upload(input.coeffs)?;
    let upstream = ctx.upload(grad_rgb)?;
    let grad_coeffs = ctx.storage::<f32>(input.coeffs.len())?;
    let grad_dirs = ctx.storage::<f32>(3 * n)?;
    let params = uniform(ctx, &ShParams { n: n as u32 });
    let mut encoder = ctx.device.create_command_encoder(&Default::default());
    dispatch(
        ctx,
        &mut encoder,
        &backward_kernel(input.degree),
        &[
            (0, storage(&dirs)),
            (1, storage(&coeffs)),
            (2, storage(&upstream)),
            (ShParams::BINDING, params.as_entire_binding()),
            (4, storage(&grad_coeffs)),
            (5, storage(&grad_dirs)),
        ],
        groups(n as u32, WG),
    );
    ctx.queue.submit(Some(encoder.finish()));
    Ok(ShGradients {
        coeffs: ctx.read(&grad_coeffs, input.coeffs.len())?,
        dirs: ctx.read(&grad_dirs, 3 * n)?,
    })
}
