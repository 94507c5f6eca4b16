//! The forward pass on the GPU: project, depth sort, tile counts and their scan, pair
//! emission, tile sort, tile ranges, blend. Returns the images and the GPU state the
//! backward pass replays.
//!
//! Sorting N Gaussians by depth first and then only the (tile, Gaussian) pairs by tile id
//! (stable) gives every tile's list in depth order while sorting the many pairs on just the
//! tile bits. The number of pairs is read back between the two submissions to size buffers.

use crate::error::Result;
use crate::gpu::{GpuContext, PooledBuffer};

use super::frame::Frame;
use super::kernels::{
    self, dispatch, groups, storage, uniform, CountParams, EmitParams, KernelParams, PixelVariant,
    RangeParams, WG,
};
use super::scan::encode_exclusive_scan;
use super::sort::{bits_for, encode_index_sort, encode_radix_sort, Pairs};
use super::types::{Camera, Gaussians, RenderOptions, RenderOutput};

/// What the backward pass needs from a forward pass, kept on the GPU.
pub struct ForwardState {
    pub(super) frame: Frame,
    pub(super) frame_buffer: wgpu::Buffer,
    pub(super) variant: PixelVariant,
    /// means, quats, log_scales, opacity_logits, features (as uploaded).
    pub(super) inputs: [PooledBuffer; 5],
    pub(super) projected: PooledBuffer,
    pub(super) tile_values: PooledBuffer,
    pub(super) ranges: PooledBuffer,
    pub(super) pixel_state: PooledBuffer,
    /// Number of (tile, Gaussian) pairs.
    pub pairs: u32,
}

impl ForwardState {
    pub fn len(&self) -> usize {
        self.frame.n as usize
    }

    pub fn is_empty(&self) -> bool {
        self.frame.n == 0
    }

    pub fn channels(&self) -> usize {
        self.variant.channels
    }

    pub fn depth(&self) -> bool {
        self.variant.depth
    }

    pub fn width(&self) -> u32 {
        self.frame.width
    }

    pub fn height(&self) -> u32 {
        self.frame.height
    }
}

/// Renders `gaussians` seen by `camera` on the GPU.
pub fn forward(
    gaussians: &Gaussians,
    camera: &Camera,
    options: &RenderOptions,
) -> Result<(RenderOutput<f32>, ForwardState)> {
    forward_impl(gaussians, camera, options, true, false)
}

/// [`forward`], optionally without subgroup operations even where the adapter has them, and
/// filling the outputs with NaN first (tests: both paths run, unwritten pixels show).
pub(crate) fn forward_impl(
    gaussians: &Gaussians,
    camera: &Camera,
    options: &RenderOptions,
    allow_subgroups: bool,
    poison: bool,
) -> Result<(RenderOutput<f32>, ForwardState)> {
    camera.validate()?;
    gaussians.validate()?;
    options.validate(gaussians.channels)?;
    let ctx = GpuContext::global()?;
    let n = gaussians.len() as u32;
    let frame = Frame::new(camera, gaussians.len(), &options.background);
    let variant = PixelVariant {
        channels: gaussians.channels,
        depth: options.depth,
    };
    let frame_buffer = uniform(ctx, &frame);
    let inputs = [
        ctx.upload(gaussians.means)?,
        ctx.upload(gaussians.quats)?,
        ctx.upload(gaussians.log_scales)?,
        ctx.upload(gaussians.opacity_logits)?,
        ctx.upload(gaussians.features)?,
    ];
    let mut keep = Vec::new();

    // Submission 1: project, depth sort, tile counts in depth order, their scan.
    let projected = ctx.storage::<[f32; 12]>(n as usize)?;
    let rects = ctx.storage::<[u32; 4]>(n as usize)?;
    let depth_keys = ctx.storage::<u32>(n as usize)?;
    let mut encoder = ctx.device.create_command_encoder(&Default::default());
    dispatch(
        ctx,
        &mut encoder,
        &kernels::project(variant),
        &[
            (0, storage(&inputs[0])),
            (1, storage(&inputs[1])),
            (2, storage(&inputs[2])),
            (3, storage(&inputs[3])),
            (4, storage(&projected)),
            (5, storage(&rects)),
            (6, storage(&depth_keys)),
            (7, storage(&inputs[4])),
            (Frame::BINDING, frame_buffer.as_entire_binding()),
        ],
        groups(n, WG),
    );
    let by_depth = encode_index_sort(ctx, &mut encoder, depth_keys, n, 32, &mut keep)?;
    let offsets = ctx.storage::<u32>(n as usize + 1)?;
    let count_params = uniform(ctx, &CountParams { n });
    dispatch(
        ctx,
        &mut encoder,
        &kernels::tile_counts(),
        &[
            (0, storage(&by_depth.values)),
            (1, storage(&rects)),
            (2, storage(&offsets)),
            (CountParams::BINDING, count_params.as_entire_binding()),
            (4, storage(&projected)),
        ],
        groups(n + 1, WG),
    );
    encode_exclusive_scan(ctx, &mut encoder, &offsets, n + 1, &mut keep)?;
    let total = ctx.storage::<u32>(1)?;
    encoder.copy_buffer_to_buffer(&offsets.buffer, u64::from(n) * 4, &total.buffer, 0, 4);
    ctx.queue.submit(Some(encoder.finish()));
    let pairs = ctx.read::<u32>(&total, 1)?[0];

    // Submission 2: emit pairs, sort them by tile, find tile ranges, blend.
    let tile_pairs = Pairs {
        keys: ctx.storage::<u32>(pairs as usize)?,
        values: ctx.storage::<u32>(pairs as usize)?,
    };
    let ranges = ctx.storage::<u32>(2 * frame.tiles() as usize)?;
    let pixels = frame.pixels();
    let image_len = pixels * (variant.channels + 1 + usize::from(variant.depth));
    let image = ctx.storage::<f32>(image_len)?;
    let pixel_state = ctx.storage::<u32>(2 * pixels)?;
    if poison {
        ctx.fill(&image, f32::NAN);
        ctx.fill(&pixel_state, u32::MAX);
    }
    let mut encoder = ctx.device.create_command_encoder(&Default::default());
    let emit_params = uniform(
        ctx,
        &EmitParams {
            n,
            tiles_x: frame.tiles_x,
        },
    );
    dispatch(
        ctx,
        &mut encoder,
        &kernels::emit(),
        &[
            (0, storage(&by_depth.values)),
            (1, storage(&rects)),
            (2, storage(&offsets)),
            (3, storage(&tile_pairs.keys)),
            (4, storage(&tile_pairs.values)),
            (EmitParams::BINDING, emit_params.as_entire_binding()),
            (6, storage(&projected)),
        ],
        groups(n, WG),
    );
    let by_tile = encode_radix_sort(
        ctx,
        &mut encoder,
        tile_pairs,
        pairs,
        bits_for(frame.tiles()),
        &mut keep,
    )?;
    encoder.clear_buffer(&ranges.buffer, 0, Some(ranges.size));
    if pairs > 0 {
        let range_params = uniform(ctx, &RangeParams { pairs });
        dispatch(
            ctx,
            &mut encoder,
            &kernels::tile_ranges(),
            &[
                (0, storage(&by_tile.keys)),
                (1, storage(&ranges)),
                (RangeParams::BINDING, range_params.as_entire_binding()),
            ],
            groups(pairs, WG),
        );
    }
    let subgroups = ctx.info.features.subgroups && allow_subgroups;
    dispatch(
        ctx,
        &mut encoder,
        &kernels::blend(variant, subgroups),
        &[
            (0, storage(&projected)),
            (1, storage(&by_tile.values)),
            (2, storage(&ranges)),
            (3, storage(&inputs[4])),
            (4, storage(&image)),
            (5, storage(&pixel_state)),
            (Frame::BINDING, frame_buffer.as_entire_binding()),
        ],
        groups(frame.tiles(), kernels::blend_tile_group(subgroups)),
    );
    ctx.queue.submit(Some(encoder.finish()));
    let mut values = ctx.read::<f32>(&image, image_len)?;
    drop(keep);

    let depth = variant
        .depth
        .then(|| values.split_off(pixels * (variant.channels + 1)));
    let alpha = values.split_off(pixels * variant.channels);
    let output = RenderOutput {
        features: values,
        alpha,
        depth,
    };
    let state = ForwardState {
        frame,
        frame_buffer,
        variant,
        inputs,
        projected,
        tile_values: by_tile.values,
        ranges,
        pixel_state,
        pairs,
    };
    Ok((output, state))
}
