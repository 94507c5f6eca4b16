//! Bindings of the CPU executor's static layers (gear_core::splat::cpu::StaticLayer): the
//! render of Gaussians that stay put, kept for one camera, and the forward of more Gaussians
//! drawn over it (bit for bit the full render; its backward is `rasterize_backward` with the
//! layer's Gaussians held).

use gear_core::splat::{cpu, Camera, Gaussians, RenderOptions};
use pyo3::prelude::*;

use crate::errors::guarded;
use crate::splat::{
    camera, forward_args, forward_binding, forward_result, gaussian_arrays, ForwardResult,
    StateKind,
};

/// The render of some Gaussians seen by one camera, for `rasterize_forward_over`.
#[pyclass(frozen, name = "StaticLayer", module = "gear._core")]
pub struct StaticLayer {
    layer: cpu::StaticLayer,
}

#[pymethods]
impl StaticLayer {
    fn __len__(&self) -> usize {
        self.layer.len()
    }

    fn __repr__(&self) -> String {
        let camera = self.layer.camera();
        format!(
            "StaticLayer({} Gaussians, {}x{}, channels={}, depth={})",
            self.layer.len(),
            camera.width,
            camera.height,
            self.layer.channels(),
            self.layer.depth()
        )
    }

    /// Bytes the layer holds (its tile lists and three images).
    #[getter]
    fn nbytes(&self) -> u64 {
        self.layer.bytes()
    }
}

/// The static layer of these Gaussians seen by the camera (the arguments of
/// `rasterize_forward_cpu` but the background), with depth if the renders over it want it.
#[pyfunction]
#[pyo3(signature = (means, quats, log_scales, opacity_logits, features, world_to_cam, intrinsics, width, height, depth))]
#[allow(clippy::too_many_arguments)]
fn static_layer_cpu(
    py: Python<'_>,
    means: &Bound<'_, PyAny>,
    quats: &Bound<'_, PyAny>,
    log_scales: &Bound<'_, PyAny>,
    opacity_logits: &Bound<'_, PyAny>,
    features: &Bound<'_, PyAny>,
    world_to_cam: &Bound<'_, PyAny>,
    intrinsics: (f32, f32, f32, f32),
    width: u32,
    height: u32,
    depth: bool,
) -> PyResult<StaticLayer> {
    let (arrays, channels) = gaussian_arrays(means, quats, log_scales, opacity_logits, features)?;
    let camera = camera(world_to_cam, intrinsics, width, height)?;
    let [m, q, s, o, f] = &arrays;
    let slices = [
        m.as_slice()?,
        q.as_slice()?,
        s.as_slice()?,
        o.as_slice()?,
        f.as_slice()?,
    ];
    let layer = guarded(py, || {
        let [m, q, s, o, f] = slices;
        let gaussians = Gaussians::from_flat(m, q, s, o, f, channels)?;
        cpu::StaticLayer::new(&gaussians, &camera, depth)
    })?;
    Ok(StaticLayer { layer })
}

forward_binding!(
    /// Renders with the CPU executor Gaussians whose first `len(layer)` are the layer's, seen
    /// by the layer's camera: only the others are projected and binned, and only the tiles
    /// they reach are blended. Arguments after `layer` as `rasterize_forward_cpu`'s
    /// (`force_cas` is accepted and ignored); an error if those Gaussians, the camera, the
    /// channel count or the depth setting differ from the layer's.
    rasterize_forward_over(layer: &Bound<'_, StaticLayer>) => {
        let layer = &layer.get().layer;
        move |gaussians: Gaussians<'_>, camera: &Camera, options: &RenderOptions| {
            let (out, state) = cpu::forward_over(layer, &gaussians, camera, options)?;
            Ok((out, StateKind::Cpu(Box::new(state))))
        }
    }
);

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<StaticLayer>()?;
    m.add_function(wrap_pyfunction!(static_layer_cpu, m)?)?;
    m.add_function(wrap_pyfunction!(rasterize_forward_over, m)?)?;
    Ok(())
}
