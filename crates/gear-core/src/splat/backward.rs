//! The backward pass on the GPU: blend-backward (per tile row, each pixel replayed back to
//! front, row sums added atomically to per-Gaussian screen-space and feature gradients), then
//! project-backward (per Gaussian, no atomics) to means, quats, log_scales and opacity logits.
//! One submission, one readback of the packed gradients.

use crate::error::Result;
use crate::gpu::GpuContext;

use super::forward::ForwardState;
use super::frame::Frame;
use super::kernels::{self, dispatch, groups, storage, KernelParams, WG};
use super::types::{GaussianGradients, OutputGradients};

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
/// backward's cost grows with the channel count.
pub fn backward(
    state: &ForwardState,
    grads: &OutputGradients<f32>,
    accumulation: Accumulation,
    features_grad: bool,
) -> Result<GaussianGradients<f32>> {
    backward_impl(state, grads, accumulation, features_grad, true, false)
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

    let mut packed = Vec::with_capacity(pixels * (channels + 2));
    packed.extend_from_slice(grads.features);
    packed.extend_from_slice(grads.alpha);
    if state.depth() {
        match grads.depth {
            Some(d) => packed.extend_from_slice(d),
            None => packed.resize(packed.len() + pixels, 0.0),
        }
    }
    let image_grads = ctx.upload(&packed)?;
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
    let frame = state.frame_buffer.as_entire_binding();
    dispatch(
        ctx,
        &mut encoder,
        &kernels::blend_backward(state.variant, float_atomics, subgroups, features_grad),
        &[
            (0, storage(&state.projected)),
            (1, storage(&state.tile_values)),
            (2, storage(&state.ranges)),
            (3, storage(&state.inputs[4])),
            (4, storage(&state.pixel_state)),
            (5, storage(&image_grads)),
            (6, storage(&geometry)),
            (7, storage(&gradients)),
            (Frame::BINDING, frame.clone()),
        ],
        state.frame.tiles(),
    );
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
    drop((image_grads, geometry));
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
