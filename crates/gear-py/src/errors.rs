//! Rust errors and panics become Python exceptions; nothing unwinds across the FFI boundary.

use std::panic::{catch_unwind, AssertUnwindSafe};

use gear_core::GearError;
use pyo3::create_exception;
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;

create_exception!(
    _core,
    GpuUnavailableError,
    PyRuntimeError,
    "No usable GPU adapter; install mesa-vulkan-drivers or a GPU driver."
);
create_exception!(
    _core,
    GpuError,
    PyRuntimeError,
    "The GPU device failed while running work."
);

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add("GpuUnavailableError", py.get_type::<GpuUnavailableError>())?;
    m.add("GpuError", py.get_type::<GpuError>())?;
    Ok(())
}

pub fn to_py(err: GearError) -> PyErr {
    match err {
        GearError::NoAdapter(msg) => GpuUnavailableError::new_err(msg),
        GearError::Gpu(msg) => GpuError::new_err(msg),
        GearError::InvalidInput(msg) => PyValueError::new_err(msg),
    }
}

/// Runs `work` without the GIL; an error maps through [`to_py`], a panic to `RuntimeError`.
pub fn guarded<T: Send>(
    py: Python<'_>,
    work: impl FnOnce() -> gear_core::Result<T> + Send,
) -> PyResult<T> {
    let outcome = py.detach(|| catch_unwind(AssertUnwindSafe(work)));
    match outcome {
        Ok(result) => result.map_err(to_py),
        Err(panic) => {
            let msg = panic
                .downcast_ref::<String>()
                .cloned()
                .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
                .unwrap_or_else(|| "unknown panic".into());
            Err(PyRuntimeError::new_err(format!(
                "internal error in gear._core: {msg}"
            )))
        }
    }
}
