//! A static layer: the render of Gaussians that stay put while others move, kept for one
//! camera. A render of those Gaussians followed by others (stage 3's motion-only steps: the
//! static part held, the moving parts posed) then projects and bins only the others, and
//! blends only the tiles they reach; every other tile takes the layer's pixels. The images,
//! and the gradients of the Gaussians after the layer's, are bit for bit those of a full
//! forward: a tile's pixels depend on its list alone, and a merged list is in the order a full
//! binning gives (by depth, ties by index).

use rayon::ThreadPool;

use super::bins::{bin, bin_over, Bins};
use super::blend::Base;
use super::{finish, global_pool, CpuState};
use crate::error::{GearError, Result};
use crate::splat::types::{Camera, Gaussians, RenderOptions, RenderOutput};

/// The layer of some Gaussians seen by one camera: their tile lists and, per pixel, the
/// blended sum (without background), the final transmittance and the depth.
pub struct StaticLayer {
    camera: Camera,
    depth: bool,
    channels: usize,
    len: usize,
    /// Of the layer's Gaussians' arrays, to tell a render over other Gaussians.
    fingerprint: u64,
    bins: Bins,
    colour: Vec<f32>,
    final_t: Vec<f32>,
    /// Zeros without depth.
    depth_image: Vec<f32>,
}

impl StaticLayer {
    /// The layer of `gaussians` seen by `camera` (with depth if renders over it want depth),
    /// made in the process-wide thread pool.
    pub fn new(gaussians: &Gaussians, camera: &Camera, depth: bool) -> Result<Self> {
        Self::new_in(global_pool()?, gaussians, camera, depth)
    }

    /// [`StaticLayer::new`] in the thread pool `pool`.
    pub fn new_in(
        pool: &ThreadPool,
        gaussians: &Gaussians,
        camera: &Camera,
        depth: bool,
    ) -> Result<Self> {
        camera.validate()?;
        gaussians.validate()?;
        // Over -0 every stored value is the blended sum itself (x + -0 = x for every x), so
        // adding a background later rounds as the blend's own store does.
        let options = RenderOptions {
            depth,
            background: vec![-0.0; gaussians.channels],
        };
        let (output, state) =
            pool.install(|| finish(bin(gaussians, camera), camera, &options, None, 0));
        let mut bins = state.bins;
        bins.drop_projections();
        Ok(StaticLayer {
            camera: *camera,
            depth,
            channels: gaussians.channels,
            len: gaussians.len(),
            fingerprint: fingerprint(gaussians, gaussians.len()),
            bins,
            colour: output.features,
            final_t: state.pixels.final_t,
            depth_image: output.depth.unwrap_or_else(|| vec![0.0; camera.pixels()]),
        })
    }

    /// Gaussians in the layer.
    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    pub fn camera(&self) -> &Camera {
        &self.camera
    }

    pub fn depth(&self) -> bool {
        self.depth
    }

    pub fn channels(&self) -> usize {
        self.channels
    }

    /// Bytes the layer holds.
    pub fn bytes(&self) -> u64 {
        let images = self.colour.len() + self.final_t.len() + self.depth_image.len();
        (self.bins.bytes() + 4 * images) as u64
    }
}

/// Renders `gaussians`, whose first `layer.len()` are the layer's Gaussians unchanged, seen by
/// `camera` (the layer's): the same images as [`super::forward`] bit for bit, and a state whose
/// backward gives the same gradients to the Gaussians after the layer's (the layer's must be
/// held: they get none). In the process-wide thread pool.
pub fn forward_over(
    layer: &StaticLayer,
    gaussians: &Gaussians,
    camera: &Camera,
    options: &RenderOptions,
) -> Result<(RenderOutput<f32>, CpuState)> {
    forward_over_in(global_pool()?, layer, gaussians, camera, options)
}

/// [`forward_over`] in the thread pool `pool`.
pub fn forward_over_in(
    pool: &ThreadPool,
    layer: &StaticLayer,
    gaussians: &Gaussians,
    camera: &Camera,
    options: &RenderOptions,
) -> Result<(RenderOutput<f32>, CpuState)> {
    gaussians.validate()?;
    options.validate(gaussians.channels)?;
    check_over(layer, gaussians, camera, options)?;
    pool.install(|| {
        let (bins, blend) = bin_over(&layer.bins, gaussians, &layer.camera);
        let base = Base {
            colour: &layer.colour,
            final_t: &layer.final_t,
            depth: &layer.depth_image,
            blend: &blend,
        };
        Ok(finish(bins, &layer.camera, options, Some(base), layer.len))
    })
}

/// Errors unless `gaussians` start with the layer's Gaussians and the render matches the
/// layer's camera, channels and depth.
fn check_over(
    layer: &StaticLayer,
    gaussians: &Gaussians,
    camera: &Camera,
    options: &RenderOptions,
) -> Result<()> {
    let invalid = |message: String| Err(GearError::InvalidInput(message));
    if *camera != layer.camera {
        return invalid("static layer: made for another camera".into());
    }
    if gaussians.channels != layer.channels {
        return invalid(format!(
            "static layer: made with {} feature channels, rendered with {}",
            layer.channels, gaussians.channels
        ));
    }
    if options.depth != layer.depth {
        return invalid(format!(
            "static layer: made with depth {}, rendered with depth {}",
            layer.depth, options.depth
        ));
    }
    if gaussians.len() < layer.len || fingerprint(gaussians, layer.len) != layer.fingerprint {
        return invalid(format!(
            "static layer: the first {} of the {} Gaussians rendered are not the layer's",
            layer.len,
            gaussians.len()
        ));
    }
    Ok(())
}

/// A 64-bit digest of the first `n` Gaussians' arrays (every bit of every value), to tell
/// them from others; four independent lanes keep it at memory speed.
fn fingerprint(gaussians: &Gaussians, n: usize) -> u64 {
    const MIX: u64 = 0x9E37_79B9_7F4A_7C15;
    let channels = gaussians.channels;
    let arrays: [&[u32]; 5] = [
        bytemuck::cast_slice(&gaussians.means[..n]),
        bytemuck::cast_slice(&gaussians.quats[..n]),
        bytemuck::cast_slice(&gaussians.log_scales[..n]),
        bytemuck::cast_slice(&gaussians.opacity_logits[..n]),
        bytemuck::cast_slice(&gaussians.features[..n * channels]),
    ];
    let mut lanes = [1u64, 2, 3, 4];
    for words in arrays {
        let mut quads = words.chunks_exact(4);
        for quad in &mut quads {
            for (lane, &w) in lanes.iter_mut().zip(quad) {
                *lane = (*lane ^ u64::from(w)).wrapping_mul(MIX).rotate_left(31);
            }
        }
        for (lane, &w) in lanes.iter_mut().zip(quads.remainder()) {
            *lane = (*lane ^ u64::from(w) ^ 0xFF)
                .wrapping_mul(MIX)
                .rotate_left(31);
        }
        lanes[0] ^= words.len() as u64;
    }
    lanes.iter().fold(n as u64, |h, &lane| {
        (h ^ lane).wrapping_mul(MIX).rotate_left(27)
    })
}
