//! Differentiable Gaussian rasterizer: WGSL kernels and their host code, the native CPU
//! executor ([`cpu`]), and the f64 CPU reference.
//!
//! The maths every implementation follows is the rasterizer contract
//! (`docs/raster-contract.md`); its constants live in [`constants`]. The GPU path is
//! [`forward`] then [`backward`]; [`cpu`] computes the same in f32 with threads; [`reference`]
//! is the same maths on the CPU in f64.

mod backward;
pub mod constants;
pub mod cpu;
mod forward;
mod frame;
mod kernels;
pub mod reference;
mod scan;
mod sort;
pub mod types;

#[cfg(test)]
mod test_rng;
#[cfg(test)]
pub(crate) mod tests;

/// How kernels outside the rasterizer (e.g. [`crate::sh`]) declare and dispatch theirs.
pub(crate) mod kernel_dispatch {
    pub use super::kernels::{dispatch, groups, storage, uniform, KernelParams};
}

pub use backward::{backward, Accumulation};
pub use forward::{forward, forward_counted, BlendCounts, ForwardState};
pub use types::{
    Camera, GaussianGradients, Gaussians, OutputGradients, OwnedGaussians, RenderOptions,
    RenderOutput,
};
