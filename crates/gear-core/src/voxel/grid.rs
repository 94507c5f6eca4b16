//! The grid shared by several point sets and the mapping from points to voxels.

use rayon::prelude::*;

use crate::error::{GearError, Result};
use crate::knn::check_finite;

/// Largest cell count a grid may have: linear keys must fit in an `i64` with room to spare.
pub const MAX_CELLS: u64 = 1 << 62;

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GridSpec {
    pub origin: [f64; 3],
    pub voxel_size: f64,
    pub shape: [usize; 3],
}

impl GridSpec {
    /// A grid given explicitly; checks the voxel size and the cell-count bound.
    pub fn new(origin: [f64; 3], voxel_size: f64, shape: [usize; 3]) -> Result<GridSpec> {
        check_voxel_size(voxel_size)?;
        if !origin.iter().all(|o| o.is_finite()) {
            return Err(GearError::InvalidInput(format!(
                "origin: must be finite, got {origin:?}"
            )));
        }
        let cells = shape
            .iter()
            .try_fold(1u64, |acc, &n| acc.checked_mul(n as u64))
            .filter(|&c| c <= MAX_CELLS);
        if cells.is_none() {
            return Err(GearError::InvalidInput(format!(
                "shape: {shape:?} has more than 2^62 cells"
            )));
        }
        Ok(GridSpec {
            origin,
            voxel_size,
            shape,
        })
    }

    /// The grid whose origin is the min corner of the union of the sets' bounding boxes and
    /// whose shape just covers their max corner. Empty sets are allowed as long as one is not.
    pub fn enclosing(point_sets: &[&[[f32; 3]]], voxel_size: f64) -> Result<GridSpec> {
        check_voxel_size(voxel_size)?;
        let mut lo = [f32::INFINITY; 3];
        let mut hi = [f32::NEG_INFINITY; 3];
        for (s, points) in point_sets.iter().enumerate() {
            check_finite(points, &format!("point_sets[{s}]"))?;
            for p in *points {
                for a in 0..3 {
                    lo[a] = lo[a].min(p[a]);
                    hi[a] = hi[a].max(p[a]);
                }
            }
        }
        if lo[0] > hi[0] {
            return Err(GearError::InvalidInput(
                "point_sets: no points to voxelise (every set is empty)".into(),
            ));
        }
        let origin = lo.map(f64::from);
        // Same arithmetic as `voxel_of`, so the max corner lands in the last voxel.
        let extent: [f64; 3] =
            std::array::from_fn(|a| ((f64::from(hi[a]) - origin[a]) / voxel_size).floor() + 1.0);
        let cells = extent.iter().product::<f64>();
        if cells > MAX_CELLS as f64 {
            return Err(GearError::InvalidInput(format!(
                "voxel_size: {voxel_size} gives a grid of {extent:?} = {cells:.3e} cells, more \
                 than the 2^62 a grid may index"
            )));
        }
        Ok(GridSpec {
            origin,
            voxel_size,
            shape: extent.map(|e| e as usize),
        })
    }

    pub fn cells(&self) -> u64 {
        self.shape.iter().map(|&n| n as u64).product()
    }

    /// The voxel containing `p`, possibly outside the grid.
    #[inline]
    pub fn voxel_of(&self, p: [f32; 3]) -> [i64; 3] {
        std::array::from_fn(|a| {
            ((f64::from(p[a]) - self.origin[a]) / self.voxel_size).floor() as i64
        })
    }

    /// The linear key of voxel `v`, or `None` outside the grid.
    #[inline]
    pub fn key(&self, v: [i64; 3]) -> Option<i64> {
        let inside = (0..3).all(|a| v[a] >= 0 && (v[a] as u64) < self.shape[a] as u64);
        inside.then(|| (v[0] * self.shape[1] as i64 + v[1]) * self.shape[2] as i64 + v[2])
    }
}

fn check_voxel_size(voxel_size: f64) -> Result<()> {
    if voxel_size.is_finite() && voxel_size > 0.0 {
        Ok(())
    } else {
        Err(GearError::InvalidInput(format!(
            "voxel_size: must be a positive finite number, got {voxel_size}"
        )))
    }
}

/// Fewer points than this are indexed on the calling thread: stage 2 asks for the cells of a
/// few hundred moved points ~10^5 times, where waking the pool costs more than the work.
const PARALLEL_MIN_POINTS: usize = 1 << 14;

/// The voxel of each point (`[i, j, k]`, possibly outside the grid).
pub fn voxel_indices(grid: &GridSpec, points: &[[f32; 3]]) -> Result<Vec<[i64; 3]>> {
    check_finite(points, "points")?;
    if points.len() < PARALLEL_MIN_POINTS {
        return Ok(points.iter().map(|&p| grid.voxel_of(p)).collect());
    }
    Ok(points.par_iter().map(|&p| grid.voxel_of(p)).collect())
}

/// Dense occupancy (`bool` per cell, C order) of the voxels holding `points`; points outside
/// the grid are ignored.
pub fn occupancy_dense(grid: &GridSpec, points: &[[f32; 3]]) -> Result<Vec<bool>> {
    check_finite(points, "points")?;
    let mut occ = vec![false; grid.cells() as usize];
    for &p in points {
        if let Some(key) = grid.key(grid.voxel_of(p)) {
            occ[key as usize] = true;
        }
    }
    Ok(occ)
}

/// Sparse occupancy: sorted, distinct keys of the voxels holding `points`; points outside the
/// grid are ignored.
pub fn occupancy_keys(grid: &GridSpec, points: &[[f32; 3]]) -> Result<Vec<i64>> {
    check_finite(points, "points")?;
    let mut keys: Vec<i64> = points
        .par_iter()
        .filter_map(|&p| grid.key(grid.voxel_of(p)))
        .collect();
    keys.par_sort_unstable();
    keys.dedup();
    Ok(keys)
}

/// Checks that `keys` is a valid sparse occupancy of a grid of `shape`: strictly increasing
/// and inside `[0, cells)`.
pub fn check_keys(keys: &[i64], shape: [usize; 3], name: &str) -> Result<()> {
    let cells = shape.iter().map(|&n| n as u64).product::<u64>();
    if let Some(i) = keys.windows(2).position(|w| w[0] >= w[1]) {
        return Err(GearError::InvalidInput(format!(
            "{name}: keys must be strictly increasing, but key {} ({}) >= key {} ({})",
            i,
            keys[i],
            i + 1,
            keys[i + 1]
        )));
    }
    match (keys.first(), keys.last()) {
        (Some(&lo), Some(&hi)) if lo < 0 || hi as u64 >= cells => Err(GearError::InvalidInput(
            format!("{name}: keys must lie in [0, {cells}) for shape {shape:?}, got [{lo}, {hi}]"),
        )),
        _ => Ok(()),
    }
}
