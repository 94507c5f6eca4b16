//! The numbers of the rasterizer contract (docs/raster-contract.md), in one place so the
//! GPU kernels (specialised with them) and the f64 reference cannot drift apart.

/// Gaussians closer than this (camera-space z) are culled.
pub const NEAR: f64 = 0.01;
/// Gaussians farther than this are culled.
pub const FAR: f64 = 1e4;
/// Added to the diagonal of the 2D covariance (anti-aliasing low-pass, in pixels²).
pub const LOW_PASS: f64 = 0.3;
/// Smallest alpha that is blended; also the opacity below which a Gaussian is culled.
pub const MIN_ALPHA: f64 = 1.0 / 255.0;
/// Largest alpha a single Gaussian may have.
pub const MAX_ALPHA: f64 = 0.999;
/// Blending stops before transmittance would fall below this.
pub const MIN_TRANSMITTANCE: f64 = 1e-4;
/// Screen-space frustum slack of the Jacobian clamp: |x/z| <= CLAMP_FACTOR * 0.5 * W / fx.
pub const CLAMP_FACTOR: f64 = 1.3;
/// Quaternions are normalised by max(|q|, QUAT_EPS).
pub const QUAT_EPS: f64 = 1e-12;
/// How much the per-row spans of a Gaussian's 1/255 ellipse are widened (both executors) so
/// that f32 rounding never makes the blend skip a pixel its own alpha test would take: the
/// level by this fraction plus this much (the alpha test's own rounding, through exp and log,
/// is ~1e-6 relative)...
pub const ROW_LEVEL_MARGIN: f64 = 1e-3;
/// ...and the span on a row by this many pixels on each side.
pub const ROW_SPAN_SLACK: f64 = 1e-2;
/// Tiles are TILE x TILE pixels.
pub const TILE: u32 = 16;
/// Largest number of feature channels.
pub const MAX_CHANNELS: usize = 64;
