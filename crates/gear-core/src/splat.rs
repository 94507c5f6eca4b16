//! Differentiable Gaussian rasterizer: WGSL kernels, host code, and the f64 CPU reference.
