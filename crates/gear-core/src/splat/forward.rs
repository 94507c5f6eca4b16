//! The forward pass on the GPU: project, depth sort, then per band of image rows tile counts
//! and their scan, pair emission, tile sort, tile ranges, blend. Returns the images and the
//! GPU state the backward pass replays.
//!
//! Sorting N Gaussians by depth first and then only the (tile, Gaussian) pairs by tile id
//! (stable) gives every tile's list in depth order while sorting the many pairs on just the
//! tile bits. The number of pairs is read back between the two submissions to size buffers.
//!
//! Large images: one storage binding holds at most the adapter's limit (128 MiB on many,
//! lavapipe included), which a 4096 x 4096 image of 3 channels, or 3840 x 2160 with depth,
//! exceeds. The frame is therefore rendered in bands of whole tile rows, each of whose
//! per-pixel buffers and pair lists fit ([`band_rows`]); a band whose pairs do not fit is
//! halved. A band's tile lists are exactly the whole frame's lists of its tiles and its
//! pixel centres keep their place in the image, so the stitched images equal an unsplit
//! render bit for bit. Projection and the depth sort run once for all bands.

use crate::error::{GearError, Result};
use crate::gpu::{GpuContext, PooledBuffer};

use super::frame::Frame;
use super::kernels::{
    self, dispatch, groups, storage, uniform, CountParams, EmitParams, KernelParams, PixelVariant,
    RangeParams, BLEND_COUNTERS, BLEND_COUNTS_BINDING, GPU_TILE, WG,
};
use super::scan::encode_exclusive_scan;
use super::sort::{bits_for, encode_index_sort, encode_radix_sort, Pairs};
use super::types::{Camera, Gaussians, RenderOptions, RenderOutput};

/// One band of image rows as the forward pass left it for the backward pass.
pub(super) struct Band {
    /// The band's frame ([`Frame::band`]) and its uniform.
    pub(super) frame: Frame,
    pub(super) frame_buffer: wgpu::Buffer,
    pub(super) tile_values: PooledBuffer,
    pub(super) ranges: PooledBuffer,
    pub(super) pixel_state: PooledBuffer,
}

/// Work counters of a counting forward pass's blend ([`forward_counted`]), summed over the
/// bands. Why two evaluation counts: the wgpu blend decides per quad (four pixels of a tile
/// row; with subgroups, for all rows of a tile at once) what to evaluate, the CPU executor per
/// row of eight; `row_evaluations` applies the CPU executor's rule to the same walk, so the
/// two executors' counts can be compared.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct BlendCounts {
    /// Gaussian-pixel evaluations the blend made: the pixels inside the image of every quad
    /// it evaluated.
    pub quad_evaluations: u64,
    /// The CPU executor's rule on the same walk: the pixels inside the image of every
    /// (entry, row) whose row still had a pixel blending and which that executor's binning
    /// would mark (blend_counts_on.wgsl).
    pub row_evaluations: u64,
    /// Gaussian-pixel pairs blended.
    pub contributions: u64,
}

impl BlendCounts {
    /// From the counting blend's (low, high) words.
    fn from_words(words: &[u32]) -> Self {
        let word = |i: usize| u64::from(words[2 * i]) | (u64::from(words[2 * i + 1]) << 32);
        BlendCounts {
            quad_evaluations: word(0),
            row_evaluations: word(1),
            contributions: word(2),
        }
    }

    fn add(self, other: Self) -> Self {
        BlendCounts {
            quad_evaluations: self.quad_evaluations + other.quad_evaluations,
            row_evaluations: self.row_evaluations + other.row_evaluations,
            contributions: self.contributions + other.contributions,
        }
    }
}

/// What the backward pass needs from a forward pass, kept on the GPU.
pub struct ForwardState {
    /// The whole image's frame and its uniform (projection and its backward).
    pub(super) frame: Frame,
    pub(super) frame_buffer: wgpu::Buffer,
    pub(super) variant: PixelVariant,
    /// means, quats, log_scales, opacity_logits, features (as uploaded).
    pub(super) inputs: [PooledBuffer; 5],
    pub(super) projected: PooledBuffer,
    /// Top to bottom; one band unless the image exceeds a storage binding.
    pub(super) bands: Vec<Band>,
    /// Number of (tile, Gaussian) pairs, summed over the bands.
    pub pairs: u32,
    /// The blend's work counters, for a counting pass only.
    pub counts: Option<BlendCounts>,
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

    /// Bands of rows the frame was rendered in.
    pub fn bands(&self) -> usize {
        self.bands.len()
    }
}

/// Renders `gaussians` seen by `camera` on the GPU.
pub fn forward(
    gaussians: &Gaussians,
    camera: &Camera,
    options: &RenderOptions,
) -> Result<(RenderOutput<f32>, ForwardState)> {
    forward_impl(gaussians, camera, options, ForwardRun::default())
}

/// [`forward`] with the counting variant of the blend, which also fills
/// [`ForwardState::counts`] (one more read-back per band; for benchmarks and tests).
pub fn forward_counted(
    gaussians: &Gaussians,
    camera: &Camera,
    options: &RenderOptions,
) -> Result<(RenderOutput<f32>, ForwardState)> {
    forward_impl(
        gaussians,
        camera,
        options,
        ForwardRun {
            counting: true,
            ..ForwardRun::default()
        },
    )
}

/// Values per pixel in the largest per-pixel buffer of a band: the image (and, in the
/// backward pass, its gradient) with `channels` features, alpha and depth; the pixel state's
/// two words are never more.
fn words_per_pixel(variant: PixelVariant) -> u64 {
    (variant.channels + 1 + usize::from(variant.depth)) as u64
}

/// Image rows per band (a multiple of the tile size, or the whole height) such that a band's
/// per-pixel buffers of `words` 4-byte values fit in `limit` bytes; an error when not even
/// one row of tiles fits.
fn band_rows(width: u32, height: u32, words: u64, limit: u64) -> Result<u32> {
    let row_bytes = u64::from(width) * words * 4;
    let tile_rows = limit / (row_bytes * u64::from(GPU_TILE));
    if tile_rows == 0 {
        return Err(GearError::InvalidInput(format!(
            "image width {width}: {GPU_TILE} rows of {words} values per pixel exceed this \
             adapter's storage binding limit of {limit} bytes"
        )));
    }
    let rows = tile_rows.saturating_mul(u64::from(GPU_TILE));
    Ok(rows.min(u64::from(height)) as u32)
}

/// How [`forward_impl`] runs, beyond what the caller renders: the switches that tests and the
/// counting variant set. [`ForwardRun::default`] is what [`forward`] does.
#[derive(Clone, Copy, Debug)]
pub(crate) struct ForwardRun {
    /// Use subgroup operations where the adapter has them (false: the per-row path).
    pub allow_subgroups: bool,
    /// Fill the outputs with NaN first, so that unwritten pixels show.
    pub poison: bool,
    /// A smaller storage binding limit than the adapter's (bands on small images).
    pub binding_limit: Option<u64>,
    /// The blend variant that also counts evaluations ([`ForwardState::counts`]).
    pub counting: bool,
}

impl Default for ForwardRun {
    fn default() -> Self {
        Self {
            allow_subgroups: true,
            poison: false,
            binding_limit: None,
            counting: false,
        }
    }
}

impl ForwardRun {
    /// The tests' run: outputs poisoned first, subgroups as `allow_subgroups` says.
    #[cfg(test)]
    pub(crate) fn checked(allow_subgroups: bool) -> Self {
        Self {
            allow_subgroups,
            poison: true,
            ..Self::default()
        }
    }
}

/// [`forward`] run as `run` says.
pub(crate) fn forward_impl(
    gaussians: &Gaussians,
    camera: &Camera,
    options: &RenderOptions,
    run: ForwardRun,
) -> Result<(RenderOutput<f32>, ForwardState)> {
    let ForwardRun {
        allow_subgroups,
        poison,
        binding_limit,
        counting,
    } = run;
    camera.validate()?;
    gaussians.validate()?;
    options.validate(gaussians.channels)?;
    let ctx = GpuContext::global()?;
    let limit = binding_limit.unwrap_or(ctx.info.max_storage_binding_bytes);
    let n = gaussians.len() as u32;
    let frame = Frame::new(camera, gaussians.len(), &options.background);
    let variant = PixelVariant {
        channels: gaussians.channels,
        depth: options.depth,
    };
    let rows = band_rows(frame.width, frame.height, words_per_pixel(variant), limit)?;
    let frame_buffer = uniform(ctx, &frame);
    let inputs = [
        ctx.upload(gaussians.means)?,
        ctx.upload(gaussians.quats)?,
        ctx.upload(gaussians.log_scales)?,
        ctx.upload(gaussians.opacity_logits)?,
        ctx.upload(gaussians.features)?,
    ];
    let mut keep = Vec::new();

    // Submitted with the first band's tile counts: project, depth sort.
    let projected = ctx.storage::<[f32; 8]>(n as usize)?;
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
    let shared = Shared {
        order: &by_depth.values,
        rects: &rects,
        projected: &projected,
        features: &inputs[4],
        n,
        variant,
        subgroups: ctx.info.features.subgroups && allow_subgroups,
        poison,
        counting,
    };

    // Bands to render, as a stack popped top to bottom; a band whose pairs do not fit in a
    // binding is replaced by its two halves.
    let mut pending: Vec<(u32, u32)> = (0..frame.height)
        .step_by(rows as usize)
        .map(|row0| (row0, rows.min(frame.height - row0)))
        .rev()
        .collect();
    let pixels = frame.pixels();
    let mut output = RenderOutput {
        features: Vec::with_capacity(pixels * variant.channels),
        alpha: Vec::with_capacity(pixels),
        depth: variant.depth.then(|| Vec::with_capacity(pixels)),
    };
    let mut bands = Vec::new();
    let mut total_pairs = 0u32;
    let mut counts = counting.then(BlendCounts::default);
    let mut first = Some(encoder);
    while let Some((row0, band_height)) = pending.pop() {
        let band = frame.band(row0, band_height);
        let encoder = first
            .take()
            .unwrap_or_else(|| ctx.device.create_command_encoder(&Default::default()));
        let (offsets, pairs) = count_pairs(ctx, encoder, &shared, &band, &mut keep)?;
        if u64::from(pairs) * 4 > limit {
            if band.tiles_y <= 1 {
                return Err(GearError::InvalidInput(format!(
                    "{pairs} tile-Gaussian pairs in one row of tiles exceed this adapter's \
                     storage binding limit of {limit} bytes"
                )));
            }
            let upper = band.tiles_y.div_ceil(2) * GPU_TILE;
            pending.push((row0 + upper, band_height - upper));
            pending.push((row0, upper));
            continue;
        }
        let (state, band_counts) =
            blend_band(ctx, &shared, band, &offsets, pairs, &mut keep, &mut output)?;
        bands.push(state);
        counts = counts.zip(band_counts).map(|(a, b)| a.add(b));
        total_pairs = total_pairs.saturating_add(pairs);
    }
    drop(keep);
    let state = ForwardState {
        frame,
        frame_buffer,
        variant,
        inputs,
        projected,
        bands,
        pairs: total_pairs,
        counts,
    };
    Ok((output, state))
}

/// What every band of one forward pass reads, and how the pass runs.
struct Shared<'a> {
    /// Gaussian indices in depth order.
    order: &'a PooledBuffer,
    /// Per Gaussian: its tile rectangle in the whole image's grid, and its projection.
    rects: &'a PooledBuffer,
    projected: &'a PooledBuffer,
    features: &'a PooledBuffer,
    n: u32,
    variant: PixelVariant,
    subgroups: bool,
    poison: bool,
    /// Blend with the counting variant.
    counting: bool,
}

/// Submits `encoder` with the band's tile counts in depth order and their exclusive scan
/// appended; returns the scanned offsets and the band's number of pairs (read back).
fn count_pairs(
    ctx: &'static GpuContext,
    mut encoder: wgpu::CommandEncoder,
    shared: &Shared,
    band: &Frame,
    keep: &mut Vec<PooledBuffer>,
) -> Result<(PooledBuffer, u32)> {
    let n = shared.n;
    let offsets = ctx.storage::<u32>(n as usize + 1)?;
    let count_params = uniform(
        ctx,
        &CountParams {
            n,
            tile_y0: band.tile_row0(),
            tile_y1: band.tile_row0() + band.tiles_y,
        },
    );
    dispatch(
        ctx,
        &mut encoder,
        &kernels::tile_counts(),
        &[
            (0, storage(shared.order)),
            (1, storage(shared.rects)),
            (2, storage(&offsets)),
            (CountParams::BINDING, count_params.as_entire_binding()),
            (4, storage(shared.projected)),
        ],
        groups(n + 1, WG),
    );
    encode_exclusive_scan(ctx, &mut encoder, &offsets, n + 1, keep)?;
    let total = ctx.storage::<u32>(1)?;
    encoder.copy_buffer_to_buffer(&offsets.buffer, u64::from(n) * 4, &total.buffer, 0, 4);
    ctx.queue.submit(Some(encoder.finish()));
    let pairs = ctx.read::<u32>(&total, 1)?[0];
    Ok((offsets, pairs))
}

/// Emits the band's pairs at `offsets`, sorts them by tile, finds the tile ranges and blends
/// the band; appends its images (read back) to `output` and returns its state, and its blend
/// counters for a counting pass.
fn blend_band(
    ctx: &'static GpuContext,
    shared: &Shared,
    band: Frame,
    offsets: &PooledBuffer,
    pairs: u32,
    keep: &mut Vec<PooledBuffer>,
    output: &mut RenderOutput<f32>,
) -> Result<(Band, Option<BlendCounts>)> {
    let variant = shared.variant;
    let tile_pairs = Pairs {
        keys: ctx.storage::<u32>(pairs as usize)?,
        values: ctx.storage::<u32>(pairs as usize)?,
    };
    let ranges = ctx.storage::<u32>(2 * band.tiles() as usize)?;
    let pixels = band.pixels();
    let image_len = pixels * words_per_pixel(variant) as usize;
    let image = ctx.storage::<f32>(image_len)?;
    let pixel_state = ctx.storage::<u32>(2 * pixels)?;
    if shared.poison {
        ctx.fill(&image, f32::NAN);
        ctx.fill(&pixel_state, u32::MAX);
    }
    let frame_buffer = uniform(ctx, &band);
    let mut encoder = ctx.device.create_command_encoder(&Default::default());
    let emit_params = uniform(
        ctx,
        &EmitParams {
            n: shared.n,
            tiles_x: band.tiles_x,
            tile_y0: band.tile_row0(),
            tile_y1: band.tile_row0() + band.tiles_y,
        },
    );
    dispatch(
        ctx,
        &mut encoder,
        &kernels::emit(),
        &[
            (0, storage(shared.order)),
            (1, storage(shared.rects)),
            (2, storage(offsets)),
            (3, storage(&tile_pairs.keys)),
            (4, storage(&tile_pairs.values)),
            (EmitParams::BINDING, emit_params.as_entire_binding()),
            (6, storage(shared.projected)),
        ],
        groups(shared.n, WG),
    );
    let by_tile = encode_radix_sort(
        ctx,
        &mut encoder,
        tile_pairs,
        pairs,
        bits_for(band.tiles()),
        keep,
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
    let counters = if shared.counting {
        let buffer = ctx.storage::<u32>(BLEND_COUNTERS)?;
        encoder.clear_buffer(&buffer.buffer, 0, Some(buffer.size));
        Some(buffer)
    } else {
        None
    };
    let mut bindings = vec![
        (0, storage(shared.projected)),
        (1, storage(&by_tile.values)),
        (2, storage(&ranges)),
        (3, storage(shared.features)),
        (4, storage(&image)),
        (5, storage(&pixel_state)),
        (Frame::BINDING, frame_buffer.as_entire_binding()),
    ];
    if let Some(buffer) = &counters {
        bindings.push((BLEND_COUNTS_BINDING, storage(buffer)));
    }
    dispatch(
        ctx,
        &mut encoder,
        &kernels::blend(variant, shared.subgroups, shared.counting),
        &bindings,
        groups(band.tiles(), kernels::blend_tile_group(shared.subgroups)),
    );
    ctx.queue.submit(Some(encoder.finish()));
    let values = ctx.read::<f32>(&image, image_len)?;
    let counts = match &counters {
        Some(buffer) => Some(BlendCounts::from_words(
            &ctx.read::<u32>(buffer, BLEND_COUNTERS)?,
        )),
        None => None,
    };

    // The band's rows are contiguous in every row-major output: append them.
    let (features, rest) = values.split_at(pixels * variant.channels);
    let (alpha, depth) = rest.split_at(pixels);
    output.features.extend_from_slice(features);
    output.alpha.extend_from_slice(alpha);
    if let Some(out) = output.depth.as_mut() {
        out.extend_from_slice(depth);
    }
    let state = Band {
        frame: band,
        frame_buffer,
        tile_values: by_tile.values,
        ranges,
        pixel_state,
    };
    Ok((state, counts))
}
