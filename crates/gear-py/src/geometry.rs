//! Bindings of voxel grids, components and KNN (gear_core::voxel, gear_core::knn).

use pyo3::prelude::*;

pub fn register(_m: &Bound<'_, PyModule>) -> PyResult<()> {
    Ok(())
}
