//! k nearest neighbours of 3D points.
//!
//! The reference points go into a balanced k-d tree ([`tree`]); every query walks it nearest
//! child first, pruning boxes farther than its current k-th neighbour ([`search`]). Queries run
//! in parallel (rayon) in a spatially coherent order, so neighbouring queries touch the same
//! leaves while they are still in cache.
//!
//! Coordinates are `f32`, the dtype of Gaussian centres; distances are Euclidean.

mod search;
mod tree;

use crate::error::{GearError, Result};
pub use search::Neighbours;
use tree::KdTree;

/// Which queries to answer.
#[derive(Clone, Copy)]
pub enum Queries<'a> {
    /// Every reference point, each excluding itself (its own index; duplicates still count).
    SelfExcluded,
    /// Other points; all reference points are candidates.
    Points(&'a [[f32; 3]]),
}

/// The `k` nearest reference `points` of each query, sorted nearest first.
///
/// Errors (as [`GearError::InvalidInput`], naming the argument): `k = 0`, a non-finite
/// coordinate, 2^32 - 1 points or more, or fewer candidates than `k` while there is at least
/// one query. No query (an empty `points` with [`Queries::SelfExcluded`], or an empty query
/// set) yields empty results. Meant for small `k` (tens); larger `k` works, each accepted
/// candidate costing a block move of up to `k` entries.
/// Equal distances are ordered arbitrarily but deterministically.
pub fn knn(points: &[[f32; 3]], queries: Queries<'_>, k: usize) -> Result<Neighbours> {
    if k == 0 {
        return Err(GearError::InvalidInput(
            "k: must be at least 1, got 0".into(),
        ));
    }
    check_finite(points, "points")?;
    if points.len() >= u32::MAX as usize {
        return Err(GearError::InvalidInput(format!(
            "points: {} points, more than the {} a tree indexes",
            points.len(),
            u32::MAX - 1
        )));
    }
    let (query_count, candidates, note) = match queries {
        Queries::SelfExcluded => (
            points.len(),
            points.len().saturating_sub(1),
            ", self excluded",
        ),
        Queries::Points(q) => {
            check_finite(q, "queries")?;
            (q.len(), points.len(), "")
        }
    };
    if query_count == 0 {
        return Ok(Neighbours::empty(k));
    }
    if candidates < k {
        return Err(GearError::InvalidInput(format!(
            "k: asks for {k} neighbours but only {candidates} reference points are available \
             ({} points{note})",
            points.len()
        )));
    }
    let tree = KdTree::build(points);
    Ok(match queries {
        Queries::SelfExcluded => search::self_neighbours(&tree, k),
        Queries::Points(q) => search::query_neighbours(&tree, q, k),
    })
}

/// Rejects NaN/Inf coordinates with the argument name and the first offending row.
pub(crate) fn check_finite(points: &[[f32; 3]], name: &str) -> Result<()> {
    match points.iter().position(|p| !p.iter().all(|c| c.is_finite())) {
        None => Ok(()),
        Some(row) => Err(GearError::InvalidInput(format!(
            "{name}: row {row} has a non-finite coordinate {:?}",
            points[row]
        ))),
    }
}

/// Views a flat `[x0, y0, z0, x1, ...]` buffer as points; its length must be a multiple of 3.
pub fn as_points(flat: &[f32]) -> &[[f32; 3]] {
    bytemuck::cast_slice(flat)
}
