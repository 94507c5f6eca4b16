//! `gear._core`: the Python face of gear-core. Checks arguments, converts arrays, releases the
//! GIL around GPU work, and turns every Rust error or panic into a Python exception.

mod args;
mod consistency;
mod errors;
mod geometry;
mod knn;
mod layer;
mod motion;
mod sh;
mod splat;
mod ssim;

use pyo3::prelude::*;
use pyo3::types::PyDict;

use args::{array, Dim};
use errors::guarded;

/// The adapter in use and what it offers (see `python -m gear info`).
#[pyfunction]
fn adapter_info(py: Python<'_>) -> PyResult<Bound<'_, PyDict>> {
    let ctx = guarded(py, gear_core::gpu::GpuContext::global)?;
    let info = &ctx.info;
    let d = PyDict::new(py);
    d.set_item("name", &info.name)?;
    d.set_item("backend", &info.backend)?;
    d.set_item("device_type", &info.device_type)?;
    d.set_item("driver", &info.driver)?;
    d.set_item("float32_atomics", info.features.float32_atomics)?;
    d.set_item("subgroups", info.features.subgroups)?;
    d.set_item("timestamps", info.features.timestamps)?;
    d.set_item("max_storage_binding_bytes", info.max_storage_binding_bytes)?;
    d.set_item("max_workgroups_per_dim", info.max_workgroups_per_dim)?;
    d.set_item(
        "max_storage_buffers_per_stage",
        info.max_storage_buffers_per_stage,
    )?;
    Ok(d)
}

/// Sum of a 1-D float32 array, reduced on the GPU.
#[pyfunction]
fn sum_f32(py: Python<'_>, values: &Bound<'_, PyAny>) -> PyResult<f32> {
    let arr = array::<f32>(values, "values", &[Dim::Any("N")])?;
    let data = arr.as_slice()?.to_vec();
    guarded(py, move || gear_core::reduce::sum_f32(&data))
}

#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    errors::register(m)?;
    m.add_function(wrap_pyfunction!(adapter_info, m)?)?;
    m.add_function(wrap_pyfunction!(sum_f32, m)?)?;
    splat::register(m)?;
    layer::register(m)?;
    geometry::register(m)?;
    knn::register(m)?;
    sh::register(m)?;
    motion::register(m)?;
    consistency::register(m)?;
    ssim::register(m)?;
    Ok(())
}
