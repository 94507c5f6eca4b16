//! Inputs and outputs shared by the GPU rasterizer and the f64 CPU reference.

use crate::error::{GearError, Result};

use super::constants::MAX_CHANNELS;

/// A pinhole camera, OpenCV axes (+x right, +y down, +z forward).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
    /// World-to-camera transform, row-major (`world_to_cam[row][col]`).
    pub world_to_cam: [[f32; 4]; 4],
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    pub width: u32,
    pub height: u32,
}

impl Camera {
    /// Pixels in the image.
    pub fn pixels(&self) -> usize {
        self.width as usize * self.height as usize
    }

    /// Rejects cameras the rasterizer cannot use (non-finite values, empty image, fx/fy <= 0).
    pub fn validate(&self) -> Result<()> {
        let finite = self.world_to_cam.iter().flatten().all(|v| v.is_finite())
            && [self.fx, self.fy, self.cx, self.cy]
                .iter()
                .all(|v| v.is_finite());
        if !finite {
            return Err(GearError::InvalidInput(
                "camera: world_to_cam and intrinsics must be finite".into(),
            ));
        }
        if self.fx <= 0.0 || self.fy <= 0.0 {
            return Err(GearError::InvalidInput(format!(
                "camera: focal lengths must be positive, got fx={} fy={}",
                self.fx, self.fy
            )));
        }
        if self.width == 0 || self.height == 0 {
            return Err(GearError::InvalidInput(format!(
                "camera: image size must be positive, got {}x{}",
                self.width, self.height
            )));
        }
        Ok(())
    }
}

/// N Gaussians, borrowed. Non-finite values are allowed: such Gaussians are culled.
#[derive(Debug, Clone, Copy)]
pub struct Gaussians<'a> {
    pub means: &'a [[f32; 3]],
    /// (w, x, y, z), unnormalised.
    pub quats: &'a [[f32; 4]],
    pub log_scales: &'a [[f32; 3]],
    pub opacity_logits: &'a [f32],
    /// N x `channels`, row-major.
    pub features: &'a [f32],
    pub channels: usize,
}

impl<'a> Gaussians<'a> {
    /// Views flat arrays (means 3N, quats 4N, log_scales 3N, opacity N, features N x
    /// `channels`) as Gaussians; errors name the array whose length is not a whole number of
    /// rows.
    pub fn from_flat(
        means: &'a [f32],
        quats: &'a [f32],
        log_scales: &'a [f32],
        opacity_logits: &'a [f32],
        features: &'a [f32],
        channels: usize,
    ) -> Result<Self> {
        for (name, len, width) in [
            ("means", means.len(), 3),
            ("quats", quats.len(), 4),
            ("log_scales", log_scales.len(), 3),
        ] {
            if len % width != 0 {
                return Err(GearError::InvalidInput(format!(
                    "{name}: expected rows of {width} values, got {len} values"
                )));
            }
        }
        let gaussians = Gaussians {
            means: bytemuck::cast_slice(means),
            quats: bytemuck::cast_slice(quats),
            log_scales: bytemuck::cast_slice(log_scales),
            opacity_logits,
            features,
            channels,
        };
        gaussians.validate()?;
        Ok(gaussians)
    }
}

impl Gaussians<'_> {
    pub fn len(&self) -> usize {
        self.means.len()
    }

    pub fn is_empty(&self) -> bool {
        self.means.is_empty()
    }

    /// Checks that every array has N rows and that 1 <= channels <= 64.
    pub fn validate(&self) -> Result<()> {
        let n = self.len();
        if self.channels == 0 || self.channels > MAX_CHANNELS {
            return Err(GearError::InvalidInput(format!(
                "features: channel count must be in 1..={MAX_CHANNELS}, got {}",
                self.channels
            )));
        }
        let rows = [
            ("quats", self.quats.len()),
            ("log_scales", self.log_scales.len()),
            ("opacity_logits", self.opacity_logits.len()),
        ];
        for (name, len) in rows {
            if len != n {
                return Err(GearError::InvalidInput(format!(
                    "{name}: expected {n} rows (as means), got {len}"
                )));
            }
        }
        if self.features.len() != n * self.channels {
            return Err(GearError::InvalidInput(format!(
                "features: expected {n} x {} values, got {}",
                self.channels,
                self.features.len()
            )));
        }
        if n > u32::MAX as usize / 4 {
            return Err(GearError::InvalidInput(format!(
                "means: too many Gaussians ({n})"
            )));
        }
        Ok(())
    }
}

/// N Gaussians owning their arrays (same layout as [`Gaussians`]); [`OwnedGaussians::view`]
/// borrows them. For callers that build scenes or keep a copy of their inputs.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct OwnedGaussians {
    pub means: Vec<[f32; 3]>,
    /// (w, x, y, z), unnormalised.
    pub quats: Vec<[f32; 4]>,
    pub log_scales: Vec<[f32; 3]>,
    pub opacity_logits: Vec<f32>,
    /// N x `channels`, row-major.
    pub features: Vec<f32>,
    pub channels: usize,
}

impl OwnedGaussians {
    /// No Gaussians yet, with `channels` feature channels.
    pub fn new(channels: usize) -> Self {
        Self {
            channels,
            ..Self::default()
        }
    }

    /// Appends one Gaussian (`features` holds its `channels` values).
    pub fn push(
        &mut self,
        mean: [f32; 3],
        quat: [f32; 4],
        log_scales: [f32; 3],
        opacity_logit: f32,
        features: &[f32],
    ) {
        self.means.push(mean);
        self.quats.push(quat);
        self.log_scales.push(log_scales);
        self.opacity_logits.push(opacity_logit);
        self.features.extend_from_slice(features);
    }

    pub fn view(&self) -> Gaussians<'_> {
        Gaussians {
            means: &self.means,
            quats: &self.quats,
            log_scales: &self.log_scales,
            opacity_logits: &self.opacity_logits,
            features: &self.features,
            channels: self.channels,
        }
    }
}

impl From<Gaussians<'_>> for OwnedGaussians {
    fn from(g: Gaussians<'_>) -> Self {
        Self {
            means: g.means.to_vec(),
            quats: g.quats.to_vec(),
            log_scales: g.log_scales.to_vec(),
            opacity_logits: g.opacity_logits.to_vec(),
            features: g.features.to_vec(),
            channels: g.channels,
        }
    }
}

/// What to render besides the feature image.
#[derive(Debug, Clone, PartialEq)]
pub struct RenderOptions {
    /// Also output the accumulated camera-space depth.
    pub depth: bool,
    /// Background, one value per channel, added with weight T_final.
    pub background: Vec<f32>,
}

impl RenderOptions {
    pub fn validate(&self, channels: usize) -> Result<()> {
        if self.background.len() != channels {
            return Err(GearError::InvalidInput(format!(
                "background: expected {channels} values (one per channel), got {}",
                self.background.len()
            )));
        }
        if !self.background.iter().all(|v| v.is_finite()) {
            return Err(GearError::InvalidInput(
                "background: values must be finite".into(),
            ));
        }
        Ok(())
    }
}

/// Rendered images: `features` is H x W x C, `alpha` and `depth` are H x W (row-major).
/// `T` is f32 for the GPU and f64 for the reference.
#[derive(Debug, Clone, PartialEq)]
pub struct RenderOutput<T> {
    pub features: Vec<T>,
    pub alpha: Vec<T>,
    /// Present only when [`RenderOptions::depth`] was set.
    pub depth: Option<Vec<T>>,
}

/// Gradients of a loss with respect to the rendered images (same layouts as [`RenderOutput`]).
#[derive(Debug, Clone, Copy)]
pub struct OutputGradients<'a, T> {
    pub features: &'a [T],
    pub alpha: &'a [T],
    /// Ignored (treated as zero) when `None` or when depth was not rendered.
    pub depth: Option<&'a [T]>,
}

impl<T: Copy + Into<f64>> OutputGradients<'_, T> {
    /// Checks the lengths against an H x W x C render, and that every value is finite (a
    /// non-finite image gradient would spread into every Gaussian it touches).
    pub fn validate(&self, pixels: usize, channels: usize) -> Result<()> {
        let checks = [
            ("grad_features", self.features.len(), pixels * channels),
            ("grad_alpha", self.alpha.len(), pixels),
            ("grad_depth", self.depth.map_or(pixels, <[T]>::len), pixels),
        ];
        for (name, got, want) in checks {
            if got != want {
                return Err(GearError::InvalidInput(format!(
                    "{name}: expected {want} values, got {got}"
                )));
            }
        }
        let arrays = [
            ("grad_features", self.features),
            ("grad_alpha", self.alpha),
            ("grad_depth", self.depth.unwrap_or(&[])),
        ];
        for (name, values) in arrays {
            if !values.iter().all(|&v| v.into().is_finite()) {
                return Err(GearError::InvalidInput(format!(
                    "{name}: values must be finite"
                )));
            }
        }
        Ok(())
    }
}

/// Gradients of a loss with respect to every Gaussian input (same layouts as [`Gaussians`]).
#[derive(Debug, Clone, PartialEq)]
pub struct GaussianGradients<T> {
    pub means: Vec<[T; 3]>,
    pub quats: Vec<[T; 4]>,
    pub log_scales: Vec<[T; 3]>,
    pub opacity_logits: Vec<T>,
    /// N x C, row-major; empty when the GPU backward was asked for no feature gradients.
    pub features: Vec<T>,
}

impl<T: Copy + Default> GaussianGradients<T> {
    /// Zeroes the gradients of the first `held` Gaussians (the caller's constants; `held` at
    /// most N, see [`check_held`]).
    pub fn zero_held(&mut self, held: usize) {
        self.means[..held].fill([T::default(); 3]);
        self.quats[..held].fill([T::default(); 4]);
        self.log_scales[..held].fill([T::default(); 3]);
        self.opacity_logits[..held].fill(T::default());
        let channels = self.features.len() / self.means.len().max(1);
        self.features[..held * channels].fill(T::default());
    }
}

/// Checks that a backward's `held` Gaussians (those whose gradients are not wanted: the first
/// `held`) are no more than the `n` rendered.
pub fn check_held(held: usize, n: usize) -> Result<()> {
    if held > n {
        return Err(GearError::InvalidInput(format!(
            "held: {held} Gaussians held of {n} rendered"
        )));
    }
    Ok(())
}
