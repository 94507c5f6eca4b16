//! The native CPU executor of the rasterizer contract: the same maths as the WGSL kernels
//! (projection, 1/255 tile test, depth-ordered per-tile lists, front-to-back blending with
//! early termination, and the backward to the five input arrays), run with rayon threads and
//! eight-pixel SIMD rows. It only evaluates a Gaussian on a pixel row its 1/255 ellipse spans.
//! The backward borrows nothing from the caller: the forward keeps what it needs (the tile
//! lists with their features, and each Gaussian's prepared projection).
//!
//! The backward uses no atomics and no per-pixel-per-Gaussian buffers: each (tile, Gaussian)
//! pair gets a gradient record summed by the one thread that owns the tile, then each
//! Gaussian's records are reduced in tile order. Gradients are therefore bit-identical for any
//! thread count and from run to run.

mod bins;
mod blend;
mod blend_backward;
pub(crate) mod lanes;
mod layer;
mod lists;
mod pool;
mod project;
mod spares;
pub(crate) mod wide;

#[cfg(test)]
mod tests;

use rayon::prelude::*;
use rayon::ThreadPool;

use self::bins::{bin, Bins};
use self::blend::{blend, Base, PixelState, Scene};
use self::blend_backward::{blend_backward, Replay, GEOMETRY, RECORDS};
use self::lanes::{array, with_avx2, LANES as BLOCK};
use self::project::{project_backward, View};
use self::wide::F8;
use crate::counts::{channels, with_channels};
use crate::error::{GearError, Result};
use crate::splat::types::{
    check_held, Camera, GaussianGradients, Gaussians, OutputGradients, RenderOptions, RenderOutput,
};

pub use self::layer::{forward_over, forward_over_in, StaticLayer};
pub use self::pool::{build_pool, global_pool, thread_count};

/// Side of the executor's square tiles: a row of a tile is one eight-lane SIMD row. 8x8 tiles
/// keep the per-tile lists short (fewer row tests) at the price of more pairs.
pub const TILE: u32 = 8;
const _: () = assert!(TILE as usize == lanes::LANES, "a tile row is one SIMD row");

/// What a forward pass did, for benchmarks.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct RasterStats {
    /// (tile, Gaussian) pairs in the tile lists.
    pub pairs: u64,
    /// Gaussian-pixel evaluations of the forward blend.
    pub evaluations: u64,
    /// Evaluations that were blended into their pixel.
    pub contributions: u64,
    /// Bytes held by the forward state (lists, prepared projections, pixel state).
    pub state_bytes: u64,
}

/// What [`backward`] needs from [`forward`]: the lists, the prepared projections and the pixel
/// state.
pub struct CpuState {
    camera: Camera,
    options: RenderOptions,
    bins: Bins,
    pixels: PixelState,
    /// Leading Gaussians whose gradients this state cannot give (those of a static layer the
    /// forward was drawn over: [`forward_over`]).
    floor: usize,
    pub stats: RasterStats,
}

impl CpuState {
    fn scene(&self) -> Scene<'_> {
        Scene {
            bins: &self.bins,
            channels: self.bins.channels,
            width: self.camera.width,
            height: self.camera.height,
            background: &self.options.background,
            depth: self.options.depth,
            base: None,
        }
    }
}

/// Renders `gaussians` seen by `camera` on the CPU, in the process-wide thread pool.
pub fn forward(
    gaussians: &Gaussians,
    camera: &Camera,
    options: &RenderOptions,
) -> Result<(RenderOutput<f32>, CpuState)> {
    forward_in(global_pool()?, gaussians, camera, options)
}

/// [`forward`] in the thread pool `pool`.
pub fn forward_in(
    pool: &ThreadPool,
    gaussians: &Gaussians,
    camera: &Camera,
    options: &RenderOptions,
) -> Result<(RenderOutput<f32>, CpuState)> {
    camera.validate()?;
    gaussians.validate()?;
    options.validate(gaussians.channels)?;
    pool.install(|| Ok(finish(bin(gaussians, camera), camera, options, None, 0)))
}

/// Blends `bins` (over `base`'s pixels where it has them) into the output images and the
/// state the backward needs; call inside the executor's thread pool.
fn finish(
    bins: Bins,
    camera: &Camera,
    options: &RenderOptions,
    base: Option<Base>,
    floor: usize,
) -> (RenderOutput<f32>, CpuState) {
    let scene = Scene {
        bins: &bins,
        channels: bins.channels,
        width: camera.width,
        height: camera.height,
        background: &options.background,
        depth: options.depth,
        base,
    };
    let (features, alpha, depth, pixels, counts) = blend(&scene);
    let state_bytes = (bins.bytes() + 8 * pixels.final_t.len() + pixels.blended_rows.len()) as u64;
    let stats = RasterStats {
        pairs: bins.pairs() as u64,
        evaluations: counts.evaluations,
        contributions: counts.contributions,
        state_bytes,
    };
    let output = RenderOutput {
        features,
        alpha,
        depth: options.depth.then_some(depth),
    };
    let state = CpuState {
        camera: *camera,
        options: options.clone(),
        bins,
        pixels,
        floor,
        stats,
    };
    (output, state)
}

/// Gradients of a loss with respect to the inputs of the forward pass that made `state`.
/// Without `features_grad` the feature gradients are not computed (`features` comes back
/// empty) and the others are bit-identical to those of a full backward. The first `held`
/// Gaussians are the caller's constants: their gradients come back as zeros, and the
/// backward only replays them for the transmittance the others need (the rest are
/// bit-identical to those of a full backward).
pub fn backward(
    state: &CpuState,
    grads: &OutputGradients<f32>,
    features_grad: bool,
    held: usize,
) -> Result<GaussianGradients<f32>> {
    backward_in(global_pool()?, state, grads, features_grad, held)
}

/// Bytes a [`backward`] of `state` allocates at its peak (pair records and the outputs), with
/// no more Gaussians held than it must.
pub fn backward_bytes(state: &CpuState, features_grad: bool) -> u64 {
    let channels = state.bins.channels;
    let stride = GEOMETRY + if features_grad { channels } else { 0 };
    let n = state.bins.len;
    // Records for the pairs of the Gaussians a backward can give gradients to.
    let pairs = state.bins.pair_count() - state.bins.pair_offsets[state.floor] as usize;
    4 * (pairs * stride + n * (11 + channels) + n) as u64
}

/// [`backward`] in the thread pool `pool`.
pub fn backward_in(
    pool: &ThreadPool,
    state: &CpuState,
    grads: &OutputGradients<f32>,
    features_grad: bool,
    held: usize,
) -> Result<GaussianGradients<f32>> {
    let channels = state.bins.channels;
    grads.validate(state.camera.pixels(), channels)?;
    check_held(held, state.bins.len)?;
    if held < state.floor {
        return Err(GearError::InvalidInput(format!(
            "held: a render over a static layer of {} Gaussians gives them no gradients; hold \
             at least those (got {held})",
            state.floor
        )));
    }
    let replay = Replay {
        state: &state.pixels,
        grads,
        features_grad,
        first_pair: state.bins.pair_offsets[held],
    };
    pool.install(|| {
        let records = blend_backward(&state.scene(), &replay);
        let r = reduce(state, &records, features_grad, held);
        RECORDS.keep(records);
        Ok(r)
    })
}

/// The gradient arrays of a run of Gaussians (a whole number of blocks of eight, but for the
/// last run).
struct GradientChunk<'a> {
    means: &'a mut [[f32; 3]],
    quats: &'a mut [[f32; 4]],
    log_scales: &'a mut [[f32; 3]],
    logits: &'a mut [f32],
    /// Gaussians x `channels`; no channels without feature gradients.
    features: &'a mut [f32],
    channels: usize,
}

/// Sums each Gaussian's pair records in tile order and chains them through the projection;
/// the first `held` Gaussians keep zero gradients.
fn reduce(
    state: &CpuState,
    records: &[f32],
    features_grad: bool,
    held: usize,
) -> GaussianGradients<f32> {
    let bins = &state.bins;
    let n = bins.len;
    let channels = if features_grad { bins.channels } else { 0 };
    let view = View::new(&state.camera);
    let input = Reduction {
        bins,
        records,
        view: &view,
        held,
        first_pair: bins.pair_offsets[held] as usize,
    };
    let mut means = vec![[0.0f32; 3]; n];
    let mut quats = vec![[0.0f32; 4]; n];
    let mut log_scales = vec![[0.0f32; 3]; n];
    let mut logits = vec![0.0f32; n];
    let mut features = vec![0.0f32; n * channels];
    // Runs of whole blocks; a zero-width feature chunk keeps the zip aligned without features.
    let chunk = 32 * BLOCK;
    let feature_chunks: Vec<&mut [f32]> = if channels > 0 {
        features.chunks_mut(chunk * channels).collect()
    } else {
        (0..n.div_ceil(chunk)).map(|_| &mut [][..]).collect()
    };
    means
        .par_chunks_mut(chunk)
        .zip(quats.par_chunks_mut(chunk))
        .zip(log_scales.par_chunks_mut(chunk))
        .zip(logits.par_chunks_mut(chunk))
        .zip(feature_chunks)
        .enumerate()
        .for_each(|(c, ((((means, quats), log_scales), logits), features))| {
            let out = GradientChunk {
                means,
                quats,
                log_scales,
                logits,
                features,
                channels,
            };
            if (c + 1) * chunk > held {
                reduce_chunk(&input, c * chunk, out);
            }
        });
    GaussianGradients {
        means,
        quats,
        log_scales,
        opacity_logits: logits,
        features,
    }
}

/// What every chunk of [`reduce`] reads: the lists, the pair records (from pair `first_pair`
/// on, the first of the Gaussians not held), the camera and how many leading Gaussians are
/// held (no gradients).
struct Reduction<'a> {
    bins: &'a Bins,
    records: &'a [f32],
    view: &'a View,
    held: usize,
    first_pair: usize,
}

with_avx2!(
    /// [`reduce`] of Gaussians `first..` into `out`, but for the held ones.
    fn reduce_chunk(input: &Reduction, first: usize, out: GradientChunk) -> () =
        reduce_chunk_any
);

/// [`reduce_chunk_body`] specialised for the channel count of the feature gradients (0
/// without them).
#[inline(always)]
fn reduce_chunk_any(input: &Reduction, first: usize, out: GradientChunk) {
    with_channels!(out.channels, reduce_chunk_body(input, first, out))
}

/// [`reduce_chunk`] with `C` the channel count if it is a compile-time constant
/// ([`with_channels!`]).
#[inline(always)]
fn reduce_chunk_body<const C: usize>(input: &Reduction, first: usize, out: GradientChunk) {
    let (bins, records, view, held) = (input.bins, input.records, input.view, input.held);
    let channels = channels::<C>(out.channels);
    // Held Gaussians have no gradients: a held Gaussian counts as one without pairs.
    let wanted = |g: usize| g >= held && !bins.pairs_of(g).is_empty();
    let stride = GEOMETRY + channels;
    for (k, logits) in out.logits.chunks_mut(BLOCK).enumerate() {
        let first = first + k * BLOCK;
        let mut screen = [F8::default(); GEOMETRY];
        let mut any = false;
        for (i, g) in (first..first + logits.len()).enumerate() {
            if !wanted(g) {
                continue;
            }
            let pairs = bins.pairs_of(g);
            any = true;
            // A Gaussian's records are contiguous, in tile order: one pass sums every value.
            let row = k * BLOCK + i;
            let features = &mut out.features[row * channels..(row + 1) * channels];
            features.fill(0.0);
            let own = pairs.start - input.first_pair..pairs.end - input.first_pair;
            for record in records[own.start * stride..own.end * stride].chunks_exact(stride) {
                let (geometry, values) = record.split_at(GEOMETRY);
                for (sum, &v) in screen.iter_mut().zip(geometry) {
                    sum.0[i] += v;
                }
                for (sum, &v) in features.iter_mut().zip(values) {
                    *sum += v;
                }
            }
        }
        if !any {
            continue;
        }
        let p = bins.prepared[first / BLOCK].project(view);
        let grads = project_backward(&p, &screen, view);
        for (i, logit) in logits.iter_mut().enumerate() {
            if !wanted(first + i) {
                continue;
            }
            let row = k * BLOCK + i;
            out.means[row] = array(|c| grads.mean[c].0[i]);
            out.quats[row] = array(|c| grads.quat[c].0[i]);
            out.log_scales[row] = array(|c| grads.log_scale[c].0[i]);
            *logit = grads.logit.0[i];
        }
    }
}
