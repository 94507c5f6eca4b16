//! Bindings of voxel grids, components and TSDF integration (gear_core::voxel).
//!
//! Arguments are checked here (dtype, shape, layout); values (finite points, voxel size,
//! key order) are checked by gear-core, whose errors become `ValueError`s naming the argument.
//! The work runs without the GIL on read-only views of the caller's arrays.

use gear_core::knn::as_points;
use gear_core::voxel::{self, check_keys, Connectivity, DepthView, GridSpec};
use numpy::{IntoPyArray, PyArray1, PyArrayDyn, PyArrayMethods, PyUntypedArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use crate::args::{array, Dim};
use crate::errors::guarded;
use crate::splat::camera;

pub(crate) const POINTS: [Dim; 2] = [Dim::Any("N"), Dim::Fixed(3)];
const KEYS: [Dim; 1] = [Dim::Any("M")];
const GRID: [Dim; 3] = [Dim::Any("X"), Dim::Any("Y"), Dim::Any("Z")];

type Array<'py, T> = Bound<'py, PyArrayDyn<T>>;
type Vector<'py, T> = Bound<'py, PyArray1<T>>;

/// `(origin, shape)` of the grid enclosing all `point_sets` at `voxel_size`.
#[pyfunction]
fn grid_enclosing(
    py: Python<'_>,
    point_sets: Vec<Bound<'_, PyAny>>,
    voxel_size: f64,
) -> PyResult<([f64; 3], [usize; 3])> {
    let arrays = point_sets
        .iter()
        .enumerate()
        .map(|(i, s)| array::<f32>(s, &format!("point_sets[{i}]"), &POINTS))
        .collect::<PyResult<Vec<_>>>()?;
    let sets = arrays
        .iter()
        .map(|a| a.as_slice().map(as_points))
        .collect::<Result<Vec<_>, _>>()?;
    let grid = guarded(py, move || GridSpec::enclosing(&sets, voxel_size))?;
    Ok((grid.origin, grid.shape))
}

/// The voxel `[i, j, k]` of each point (int64 [N, 3], possibly outside the grid).
#[pyfunction]
fn voxel_indices<'py>(
    py: Python<'py>,
    points: &Bound<'py, PyAny>,
    origin: [f64; 3],
    voxel_size: f64,
    shape: [usize; 3],
) -> PyResult<Array<'py, i64>> {
    let idx = on_points(
        py,
        points,
        (origin, voxel_size, shape),
        voxel::voxel_indices,
    )?;
    let n = idx.len();
    reshape(idx.into_flattened().into_pyarray(py), &[n, 3])
}

/// Dense occupancy (bool [X, Y, Z]) of the voxels holding `points`; outside points ignored.
#[pyfunction]
fn occupancy_dense<'py>(
    py: Python<'py>,
    points: &Bound<'py, PyAny>,
    origin: [f64; 3],
    voxel_size: f64,
    shape: [usize; 3],
) -> PyResult<Array<'py, bool>> {
    let occ = on_points(
        py,
        points,
        (origin, voxel_size, shape),
        voxel::occupancy_dense,
    )?;
    reshape(occ.into_pyarray(py), &shape)
}

/// Sparse occupancy (sorted distinct int64 keys) of the voxels holding `points`.
#[pyfunction]
fn occupancy_keys<'py>(
    py: Python<'py>,
    points: &Bound<'py, PyAny>,
    origin: [f64; 3],
    voxel_size: f64,
    shape: [usize; 3],
) -> PyResult<Vector<'py, i64>> {
    let keys = on_points(
        py,
        points,
        (origin, voxel_size, shape),
        voxel::occupancy_keys,
    )?;
    Ok(keys.into_pyarray(py))
}

/// `op` in {"and", "or", "sub"} on two sparse occupancies of the same grid `shape`.
#[pyfunction]
fn keys_set_op<'py>(
    py: Python<'py>,
    op: &str,
    a: &Bound<'py, PyAny>,
    b: &Bound<'py, PyAny>,
    shape: [usize; 3],
) -> PyResult<Vector<'py, i64>> {
    let merge = match op {
        "and" => voxel::intersection,
        "or" => voxel::union,
        "sub" => voxel::difference,
        _ => {
            return Err(PyValueError::new_err(format!(
                "op: unknown set operation {op:?}"
            )))
        }
    };
    let (a, b) = (array::<i64>(a, "a", &KEYS)?, array::<i64>(b, "b", &KEYS)?);
    let (ka, kb) = (a.as_slice()?, b.as_slice()?);
    let out = guarded(py, move || {
        check_keys(ka, shape, "a")?;
        check_keys(kb, shape, "b")?;
        Ok(merge(ka, kb))
    })?;
    Ok(out.into_pyarray(py))
}

/// Dense dilation of `occ` (bool [X, Y, Z]) by a cube of side `2 * radius + 1`.
#[pyfunction]
fn dilate_dense<'py>(
    py: Python<'py>,
    occ: &Bound<'py, PyAny>,
    radius: usize,
) -> PyResult<Array<'py, bool>> {
    let (out, shape) = on_dense(py, occ, |cells, shape| {
        voxel::dilate_dense(cells, shape, radius)
    })?;
    reshape(out.into_pyarray(py), &shape)
}

/// Sparse dilation of sorted `keys` in a grid of `shape`.
#[pyfunction]
fn dilate_keys<'py>(
    py: Python<'py>,
    keys: &Bound<'py, PyAny>,
    shape: [usize; 3],
    radius: usize,
) -> PyResult<Vector<'py, i64>> {
    let out = on_keys(py, keys, shape, |k| voxel::dilate_keys(k, shape, radius))?;
    Ok(out.into_pyarray(py))
}

/// Components of a dense occupancy: `(labels int32 [X, Y, Z], sizes int64 [C])`.
#[pyfunction]
fn components_dense<'py>(
    py: Python<'py>,
    occ: &Bound<'py, PyAny>,
    connectivity: i64,
) -> PyResult<(Array<'py, i32>, Vector<'py, i64>)> {
    let conn = Connectivity::from_neighbours(connectivity).map_err(crate::errors::to_py)?;
    let (found, shape) = on_dense(py, occ, |cells, shape| {
        voxel::components_dense(cells, shape, conn)
    })?;
    Ok((
        reshape(found.labels.into_pyarray(py), &shape)?,
        found.sizes.into_pyarray(py),
    ))
}

/// Components of a sparse occupancy: `(labels int32 [M] per key, sizes int64 [C])`.
#[pyfunction]
fn components_keys<'py>(
    py: Python<'py>,
    keys: &Bound<'py, PyAny>,
    shape: [usize; 3],
    connectivity: i64,
) -> PyResult<(Vector<'py, i32>, Vector<'py, i64>)> {
    let conn = Connectivity::from_neighbours(connectivity).map_err(crate::errors::to_py)?;
    let found = on_keys(py, keys, shape, |k| {
        Ok(voxel::components_keys(k, shape, conn))
    })?;
    Ok((found.labels.into_pyarray(py), found.sizes.into_pyarray(py)))
}

/// Runs `op` without the GIL on `points` (checked as float32 [N, 3]) and the grid
/// `(origin, voxel_size, shape)` (checked first).
fn on_points<'py, R: Send>(
    py: Python<'py>,
    points: &Bound<'py, PyAny>,
    (origin, voxel_size, shape): ([f64; 3], f64, [usize; 3]),
    op: impl FnOnce(&GridSpec, &[[f32; 3]]) -> gear_core::Result<R> + Send,
) -> PyResult<R> {
    let grid = GridSpec::new(origin, voxel_size, shape).map_err(crate::errors::to_py)?;
    let points = array::<f32>(points, "points", &POINTS)?;
    let pts = as_points(points.as_slice()?);
    guarded(py, move || op(&grid, pts))
}

/// Runs `op` without the GIL on a dense occupancy `occ` (checked as bool [X, Y, Z]) and its
/// shape; returns the result and the shape.
fn on_dense<'py, R: Send>(
    py: Python<'py>,
    occ: &Bound<'py, PyAny>,
    op: impl FnOnce(&[bool], [usize; 3]) -> R + Send,
) -> PyResult<(R, [usize; 3])> {
    let occ = array::<bool>(occ, "occ", &GRID)?;
    let dims = occ.shape();
    let shape = [dims[0], dims[1], dims[2]];
    let cells = occ.as_slice()?;
    let out = guarded(py, move || Ok(op(cells, shape)))?;
    Ok((out, shape))
}

/// Runs `op` without the GIL on sparse occupancy `keys` (checked as int64 [M], then as sorted
/// distinct keys of a grid of `shape`).
fn on_keys<'py, R: Send>(
    py: Python<'py>,
    keys: &Bound<'py, PyAny>,
    shape: [usize; 3],
    op: impl FnOnce(&[i64]) -> gear_core::Result<R> + Send,
) -> PyResult<R> {
    let keys = array::<i64>(keys, "keys", &KEYS)?;
    let k = keys.as_slice()?;
    guarded(py, move || {
        check_keys(k, shape, "keys")?;
        op(k)
    })
}

/// Gives a flat result array its real shape (a view; no copy).
pub(crate) fn reshape<'py, T: numpy::Element>(
    flat: Bound<'py, PyArray1<T>>,
    shape: &[usize],
) -> PyResult<Array<'py, T>> {
    flat.reshape(shape)
}

/// TSDF integration of z-depth images into voxels: `(distance float32 [N], weight float32
/// [N])` at `centres` [N, 3] (world), the mean truncated signed distance (units of `trunc`, at
/// most 1) over the views that observed each voxel and their count (gear_core::voxel::
/// tsdf_integrate). View i: `depths[i]` [H, W] (0 where unobserved), `world_to_cams[i]` [4, 4],
/// `intrinsics[i]` (fx, fy, cx, cy).
#[pyfunction]
fn tsdf_integrate<'py>(
    py: Python<'py>,
    centres: &Bound<'py, PyAny>,
    depths: Vec<Bound<'py, PyAny>>,
    world_to_cams: Vec<Bound<'py, PyAny>>,
    intrinsics: Vec<(f32, f32, f32, f32)>,
    trunc: f32,
) -> PyResult<(Vector<'py, f32>, Vector<'py, f32>)> {
    if depths.len() != world_to_cams.len() || depths.len() != intrinsics.len() {
        return Err(PyValueError::new_err(format!(
            "tsdf_integrate: {} depths, {} world_to_cams and {} intrinsics",
            depths.len(),
            world_to_cams.len(),
            intrinsics.len()
        )));
    }
    let centres = array::<f32>(centres, "centres", &POINTS)?;
    let depths = depths
        .iter()
        .map(|d| array::<f32>(d, "depths[i]", &[Dim::Any("H"), Dim::Any("W")]))
        .collect::<PyResult<Vec<_>>>()?;
    let size = |n: usize| u32::try_from(n).map_err(|_| PyValueError::new_err("image too large"));
    let mut views = Vec::with_capacity(depths.len());
    for ((depth, w2c), k) in depths.iter().zip(&world_to_cams).zip(intrinsics) {
        let shape = depth.shape();
        views.push(DepthView {
            depth: depth.as_slice()?,
            camera: camera(w2c, k, size(shape[1])?, size(shape[0])?)?,
        });
    }
    let points = as_points(centres.as_slice()?);
    let out = guarded(py, move || voxel::tsdf_integrate(points, &views, trunc))?;
    Ok((out.distance.into_pyarray(py), out.weight.into_pyarray(py)))
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(tsdf_integrate, m)?)?;
    m.add_function(wrap_pyfunction!(grid_enclosing, m)?)?;
    m.add_function(wrap_pyfunction!(voxel_indices, m)?)?;
    m.add_function(wrap_pyfunction!(occupancy_dense, m)?)?;
    m.add_function(wrap_pyfunction!(occupancy_keys, m)?)?;
    m.add_function(wrap_pyfunction!(keys_set_op, m)?)?;
    m.add_function(wrap_pyfunction!(dilate_dense, m)?)?;
    m.add_function(wrap_pyfunction!(dilate_keys, m)?)?;
    m.add_function(wrap_pyfunction!(components_dense, m)?)?;
    m.add_function(wrap_pyfunction!(components_keys, m)?)?;
    Ok(())
}
