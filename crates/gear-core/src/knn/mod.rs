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
    match queries {
        Queries::Points(q) => NearestTree::new(points)?.query(q, k),
        Queries::SelfExcluded => {
            check_k(k)?;
            check_points(points)?;
            if points.is_empty() {
                return Ok(Neighbours::empty(k));
            }
            check_candidates(k, points.len() - 1, points.len(), ", self excluded")?;
            Ok(search::self_neighbours(&KdTree::build(points), k))
        }
    }
}

/// A k-d tree over reference points, built once for many queries: stage 2's motion search
/// asks one target state's centres for the nearest of a few hundred moved points about 10^5
/// times, where [`knn`] would build the tree each time.
pub struct NearestTree {
    tree: KdTree,
}

impl NearestTree {
    /// The tree over `points`; errors as [`knn`]'s for non-finite or too many points.
    pub fn new(points: &[[f32; 3]]) -> Result<NearestTree> {
        check_points(points)?;
        Ok(NearestTree {
            tree: KdTree::build(points),
        })
    }

    /// Number of reference points.
    pub fn len(&self) -> usize {
        self.tree.len()
    }

    pub fn is_empty(&self) -> bool {
        self.tree.len() == 0
    }

    /// The `k` nearest reference points of each of `queries`, as [`knn`] with
    /// [`Queries::Points`] (same results, same errors).
    pub fn query(&self, queries: &[[f32; 3]], k: usize) -> Result<Neighbours> {
        check_k(k)?;
        check_finite(queries, "queries")?;
        if queries.is_empty() {
            return Ok(Neighbours::empty(k));
        }
        check_candidates(k, self.len(), self.len(), "")?;
        Ok(search::query_neighbours(&self.tree, queries, k))
    }
}

fn check_k(k: usize) -> Result<()> {
    if k == 0 {
        return Err(GearError::InvalidInput(
            "k: must be at least 1, got 0".into(),
        ));
    }
    Ok(())
}

/// Finite coordinates, and few enough points for a u32 index.
fn check_points(points: &[[f32; 3]]) -> Result<()> {
    check_finite(points, "points")?;
    if points.len() >= u32::MAX as usize {
        return Err(GearError::InvalidInput(format!(
            "points: {} points, more than the {} a tree indexes",
            points.len(),
            u32::MAX - 1
        )));
    }
    Ok(())
}

/// At least `k` of the `points` reference points are candidates for each query.
fn check_candidates(k: usize, candidates: usize, points: usize, note: &str) -> Result<()> {
    if candidates < k {
        return Err(GearError::InvalidInput(format!(
            "k: asks for {k} neighbours but only {candidates} reference points are available \
             ({points} points{note})"
        )));
    }
    Ok(())
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
