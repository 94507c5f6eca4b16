//! View-dependent colour: real spherical harmonics of degree 0..=3 evaluated per Gaussian,
//! `rgb = max(0, sum_k coeffs[k] * Y_k(dir / |dir|) + 0.5)`, and its backward (to the
//! coefficients and, through the normalisation, to the directions).
//!
//! This is its own op, run before the rasterizer, so the rasterizer contract is unchanged and
//! a scene without view-dependent colour (degree 0) never calls it. The basis, its constants
//! and the +0.5 / clamp-at-0 convention are those of 3D Gaussian Splatting (see
//! `docs/raster-contract.md`, "View-dependent colour"). Three executors compute it: the WGSL
//! kernels ([`gpu`]), the native CPU ([`cpu`], rayon in the rasterizer's pool) and the f64
//! [`reference`].
//!
//! A direction shorter than [`MIN_DIR_NORM`] has no defined orientation: it is evaluated as
//! the zero vector (only the degree-0 term remains) and receives a zero gradient, so the
//! output and every gradient stay finite.

mod basis;
pub mod cpu;
pub mod gpu;
pub mod reference;

#[cfg(test)]
mod tests;

use crate::error::{check_finite, invalid, Result};

/// Highest supported degree; (degree + 1)^2 coefficients per colour channel.
pub const MAX_DEGREE: u32 = 3;
/// Directions shorter than this are treated as the zero vector (see the module docs).
pub const MIN_DIR_NORM: f64 = 1e-12;
/// Colour channels (RGB).
pub const CHANNELS: usize = 3;

/// Coefficients per channel of `degree`.
pub fn coefficient_count(degree: u32) -> usize {
    ((degree + 1) * (degree + 1)) as usize
}

/// Gradients of a loss with respect to the op's inputs, shaped like them (flat, row-major):
/// `coeffs` [N, K, 3] and `dirs` [N, 3].
#[derive(Debug, Clone, PartialEq)]
pub struct ShGradients<T> {
    pub coeffs: Vec<T>,
    pub dirs: Vec<T>,
}

/// The op's inputs, flat and row-major: `dirs` [N, 3], `coeffs` [N, K, 3] with
/// K = (degree + 1)^2.
#[derive(Debug, Clone, Copy)]
pub struct ShInput<'a, T> {
    pub dirs: &'a [T],
    pub coeffs: &'a [T],
    pub degree: u32,
}

impl<'a, T: Copy + Into<f64>> ShInput<'a, T> {
    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.dirs.len() / 3
    }

    pub fn is_empty(&self) -> bool {
        self.dirs.is_empty()
    }

    /// Checks the degree, the array lengths and that every value is finite (a non-finite
    /// input is a bug upstream, reported here rather than spread as NaN colours).
    pub fn validate(&self) -> Result<()> {
        if self.degree > MAX_DEGREE {
            return Err(invalid(format!(
                "sh degree must be 0..={MAX_DEGREE}, got {}",
                self.degree
            )));
        }
        if !self.dirs.len().is_multiple_of(3) {
            return Err(invalid(format!(
                "sh dirs must hold N x 3 values, got {}",
                self.dirs.len()
            )));
        }
        let k = coefficient_count(self.degree);
        let expected = self.len() * k * CHANNELS;
        if self.coeffs.len() != expected {
            return Err(invalid(format!(
                "sh coeffs must hold N x {k} x 3 = {expected} values for {} directions at degree {}, got {}",
                self.len(),
                self.degree,
                self.coeffs.len()
            )));
        }
        check_finite("sh dirs", self.dirs)?;
        check_finite("sh coeffs", self.coeffs)
    }

    /// Checks `grad_rgb` [N, 3] against these inputs.
    pub fn validate_grad(&self, grad_rgb: &[T]) -> Result<()> {
        if grad_rgb.len() != self.dirs.len() {
            return Err(invalid(format!(
                "sh grad_rgb must hold N x 3 = {} values, got {}",
                self.dirs.len(),
                grad_rgb.len()
            )));
        }
        check_finite("sh grad_rgb", grad_rgb)
    }
}
