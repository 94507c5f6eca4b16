//! The backward pass on the GPU: blend-backward (per tile row, each pixel replayed back to
//! front, row sums added atomically to per-Gaussian screen-space and feature gradients; per
//! band of rows when the forward pass split the image), then project-backward (per Gaussian,
//! no atomics) to means, quats, log_scales and opacity logits. One submission per band, one
//! readback of the packed gradients.

use crate::error::Result;
use crate::gpu::GpuContext;

use super::forward::ForwardState;
use super::frame::Frame;
use super::kernels::{self, dispatch, groups, storage, KernelParams, WG};
use super::types::{check_held, GaussianGradients, OutputGradients};

/// Screen-space accumulators per Gaussian: conic a, b, c, u, v, opacity, z, unused.
const GEOMETRY_STRIDE: usize = 8;
/// Packed gradient values per Gaussian before the features: means 3, quats 4, scales 3, opacity 1.
const GEOMETRY_OUTPUTS: usize = 11;

/// How blend-backward accumulates into shared per-Gaussian gradients.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Accumulation {
    /// Native `atomicAdd` on `atomic<f32>` when the adapter has it, else compare-and-swap.
    Auto,
    /// Always the compare-and-swap loop (to test it on adapters that have float atomics).
    CompareAndSwap,
}

/// Gradients of a loss with respect to the inputs of the forward pass that made `state`.
/// Without `features_grad` the feature gradients are not computed (`features` comes back
/// empty) and the others are unchanged: for callers whose features are constants, as the
/// backward's cost grows with the channel count. The first `held` Gaussians are the caller's
/// constants: their gradients come back as zeros (computed, then zeroed: the kernels do the
/// same work; the CPU executor skips it).
pub fn backward(
    state: &ForwardState,
    grads: &OutputGradients<f32>,
    accumulation: Accumulation,
    features_grad: bool,
    held: usize,
) -> Result<GaussianGradients<f32>> {
    check_held(held, state.len())?;
    let mut gradients = backward_impl(state, grads, accumulation, features_grad, true, false)?;
    gradients.zero_held(held);
    Ok(gradients)
}

/// [`backward`], optionally without subgroup operations even where the adapter has them, and
/// filling the outputs with NaN first (tests: both paths run, unwritten values show).
pub(crate) fn backward_impl(
    state: &ForwardState,
    grads: &OutputGradients<f32>,
    accumulation: Accumulation,
    features_grad: bool,
    allow_subgroups: bool,
    poison: bool,
) -> Result<GaussianGradients<f32>> {
    let pixels = state.frame.pixels();
    let channels = state.channels();
    grads.validate(pixels, channels)?;
    let ctx = GpuContext::global()?;
    let n = state.len();

    let geometry = ctx.storage::<f32>(n * GEOMETRY_STRIDE)?;
    // Without feature gradients the packed output ends before the features.
    let out_channels = if features_grad { channels } else { 0 };
    let total = n * (GEOMETRY_OUTPUTS + out_channels);
    let gradients = ctx.storage::<f32>(total)?;
    if poison {
        ctx.fill(&gradients, f32::NAN);
    }
    let float_atomics = ctx.info.features.float32_atomics && accumulation == Accumulation::Auto;
    let subgroups = ctx.info.features.subgroups && allow_subgroups;
    let kernel = kernels::blend_backward(state.variant, float_atomics, subgroups, features_grad);

    let mut encoder = ctx.device.create_command_encoder(&Default::default());
    encoder.clear_buffer(&geometry.buffer, 0, Some(geometry.size));
    // Features are accumulated; the geometric part is written whole by project-backward.
    if features_grad {
        let feature_offset = (n * GEOMETRY_OUTPUTS * 4) as u64;
        encoder.clear_buffer(
            &gradients.buffer,
            feature_offset,
            Some(gradients.size - feature_offset),
        );
    }
    // Bands add into the same accumulators one after the other, top to bottom. A band's image
    // gradients go back to the buffer pool (where another thread may take them) only once the
    // dispatch that reads them is submitted.
    let width = state.frame.width as usize;
    let mut in_flight = None;
    for band in &state.bands {
        if in_flight.is_some() {
            ctx.queue.submit(Some(encoder.finish()));
            encoder = ctx.device.create_command_encoder(&Default::default());
        }
        let first = band.frame.row0 as usize * width;
        let rows = first..first + band.frame.pixels();
        let mut packed = Vec::with_capacity(rows.len() * (channels + 2));
        packed.extend_from_slice(&grads.features[rows.start * channels..rows.end * channels]);
        packed.extend_from_slice(&grads.alpha[rows.clone()]);
        if state.depth() {
            match grads.depth {
                Some(d) => packed.extend_from_slice(&d[rows]),
                None => packed.resize(packed.len() + band.frame.pixels(), 0.0),
            }
        }
        let image_grads = ctx.upload(&packed)?;
        dispatch(
            ctx,
            &mut encoder,
            &kernel,
            &[
                (0, storage(&state.projected)),
                (1, storage(&band.tile_values)),
                (2, storage(&band.ranges)),
                (3, storage(&state.inputs[4])),
                (4, storage(&band.pixel_state)),
                (5, storage(&image_grads)),
                (6, storage(&geometry)),
                (7, storage(&gradients)),
                (Frame::BINDING, band.frame_buffer.as_entire_binding()),
            ],
            band.frame.tiles(),
        );
        in_flight = Some(image_grads);
    }
    let frame = state.frame_buffer.as_entire_binding();
    dispatch(
        ctx,
        &mut encoder,
        &kernels::project_backward(state.variant),
        &[
            (0, storage(&state.inputs[0])),
            (1, storage(&state.inputs[1])),
            (2, storage(&state.inputs[2])),
            (3, storage(&state.inputs[3])),
            (4, storage(&geometry)),
            (5, storage(&gradients)),
            (7, storage(&state.inputs[4])),
            (Frame::BINDING, frame),
        ],
        groups(n as u32, WG),
    );
    ctx.queue.submit(Some(encoder.finish()));
    let values = ctx.read::<f32>(&gradients, total)?;
    drop((in_flight, geometry));
    Ok(unpack(&values, n, out_channels))
}

/// Splits the packed readback [means 3N | quats 4N | log_scales 3N | opacity N | features CN]
/// (C = 0 when feature gradients were not computed).
fn unpack(values: &[f32], n: usize, channels: usize) -> GaussianGradients<f32> {
    let (means, rest) = values.split_at(3 * n);
    let (quats, rest) = rest.split_at(4 * n);
    let (log_scales, rest) = rest.split_at(3 * n);
    let (opacity_logits, features) = rest.split_at(n);
    debug_assert_eq!(features.len(), n * channels);
    GaussianGradients {
        means: bytemuck::cast_slice(means).to_vec(),
        quats: bytemuck::cast_slice(quats).to_vec(),
        log_scales: bytemuck::cast_slice(log_scales).to_vec(),
        opacity_logits: opacity_logits.to_vec(),
        features: features.to_vec(),
    }
}
