//! Differentiable Gaussian rasterizer: WGSL kernels, host code, and the f64 CPU reference.
//!
//! The maths every implementation follows is the rasterizer contract
//! (`/work/notes/raster_contract.md`); its constants live in [`constants`].

pub mod constants;
pub mod reference;
pub mod types;

pub use types::{
    Camera, GaussianGradients, Gaussians, OutputGradients, RenderOptions, RenderOutput,
};
