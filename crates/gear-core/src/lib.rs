//! gear-core: the engine behind gear.
//!
//! - [`gpu`]: one wgpu device per process (a real GPU, else Mesa's software Vulkan adapter),
//!   a pipeline cache keyed by shader specialisation, a buffer pool and readback helpers.
//! - [`reduce`]: a small GPU reduction, the end-to-end check of the plumbing.
//! - [`splat`]: the differentiable Gaussian rasterizer (WGSL kernels) and its f64 CPU reference.
//! - [`voxel`]: shared voxel grids, dilation and connected components.
//! - [`knn`]: k nearest neighbours in 3D.
//! - [`consistency`]: stage 3's KNN consistency term of the part logits, with its gradient.
//! - [`motion`]: Gaussians moved by a soft blend of rigid part motions, and its backward.
//! - [`sh`]: view-dependent colour from spherical harmonics (degree 0..=3), its own op.
//! - [`ssim`]: structural similarity of two images and its gradient (the photometric loss).
//!
//! Nothing here knows about Python or torch; arrays come in and go out as slices.

pub mod consistency;
mod counts;
pub mod error;
pub mod gpu;
pub mod knn;
pub mod motion;
pub mod reduce;
pub mod sh;
pub mod splat;
pub mod ssim;
pub mod voxel;

pub use error::{GearError, Result};
