//! Bindings of the k nearest neighbours (gear_core::knn): the one-shot `knn`, and `KnnTree`,
//! a tree over reference points kept for many queries.
//!
//! Arguments are checked here (dtype, shape, layout); values (finite points, k) by gear-core,
//! whose errors become `ValueError`s naming the argument. Queries run without the GIL.

use gear_core::knn::{as_points, NearestTree, Neighbours, Queries};
use numpy::{IntoPyArray, PyArrayDyn};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use crate::args::array;
use crate::errors::guarded;
use crate::geometry::{reshape, POINTS};

type Found<'py> = (Bound<'py, PyArrayDyn<i64>>, Bound<'py, PyArrayDyn<f32>>);

fn count(k: i64) -> PyResult<usize> {
    usize::try_from(k).map_err(|_| PyValueError::new_err(format!("k: must be at least 1, got {k}")))
}

/// `(indices int64 [M, k], distances float32 [M, k])` of found neighbours.
fn found(py: Python<'_>, found: Neighbours) -> PyResult<Found<'_>> {
    let (rows, k) = (found.len(), found.k);
    Ok((
        reshape(found.indices.into_pyarray(py), &[rows, k])?,
        reshape(found.distances.into_pyarray(py), &[rows, k])?,
    ))
}

/// `k` nearest neighbours: `(indices int64 [M, k], distances float32 [M, k])`, nearest first;
/// without `queries`, each point's neighbours among the others.
#[pyfunction]
#[pyo3(signature = (points, k, queries=None))]
fn knn<'py>(
    py: Python<'py>,
    points: &Bound<'py, PyAny>,
    k: i64,
    queries: Option<&Bound<'py, PyAny>>,
) -> PyResult<Found<'py>> {
    let k = count(k)?;
    let points = array::<f32>(points, "points", &POINTS)?;
    let queries = queries
        .map(|q| array::<f32>(q, "queries", &POINTS))
        .transpose()?;
    let refs = as_points(points.as_slice()?);
    let qs = match &queries {
        None => Queries::SelfExcluded,
        Some(q) => Queries::Points(as_points(q.as_slice()?)),
    };
    found(py, guarded(py, move || gear_core::knn::knn(refs, qs, k))?)
}

/// A k-d tree over reference points (float32 [N, 3]) for many `query` calls.
#[pyclass(frozen, name = "KnnTree", module = "gear._core")]
pub struct KnnTree {
    tree: NearestTree,
}

#[pymethods]
impl KnnTree {
    #[new]
    fn new(py: Python<'_>, points: &Bound<'_, PyAny>) -> PyResult<KnnTree> {
        let points = array::<f32>(points, "points", &POINTS)?;
        let refs = as_points(points.as_slice()?);
        let tree = guarded(py, move || NearestTree::new(refs))?;
        Ok(KnnTree { tree })
    }

    fn __len__(&self) -> usize {
        self.tree.len()
    }

    fn __repr__(&self) -> String {
        format!("KnnTree({} points)", self.tree.len())
    }

    /// The `k` nearest reference points of each of `queries` (float32 [M, 3]):
    /// `(indices int64 [M, k], distances float32 [M, k])`, nearest first.
    fn query<'py>(
        &self,
        py: Python<'py>,
        queries: &Bound<'py, PyAny>,
        k: i64,
    ) -> PyResult<Found<'py>> {
        let k = count(k)?;
        let queries = array::<f32>(queries, "queries", &POINTS)?;
        let qs = as_points(queries.as_slice()?);
        let tree = &self.tree;
        found(py, guarded(py, move || tree.query(qs, k))?)
    }
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(knn, m)?)?;
    m.add_class::<KnnTree>()?;
    Ok(())
}
