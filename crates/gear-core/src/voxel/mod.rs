//! Voxel grids shared by several point sets: occupancy, set operations, dilation, components;
//! and the TSDF integration of depth images that the meshes are extracted from.
//!
//! A grid is an origin, a voxel size and a shape `[X, Y, Z]`; voxel `(i, j, k)` covers
//! `origin + v * [i, i+1) x [j, j+1) x [k, k+1)`. Occupancy comes in two forms with identical
//! semantics: dense (`bool` per cell, C order) for grids that fit in memory, and sparse (the
//! sorted linear keys `(i * Y + j) * Z + k` of the occupied cells) for any grid whose cell count
//! fits in an `i64`. Every operation exists for both and gives the same answer.

mod components;
mod dilate;
mod grid;
mod runs;
mod sets;
mod tsdf;

pub use components::{components_dense, components_keys, Components, Connectivity};
pub use dilate::{dilate_dense, dilate_keys};
pub use grid::{check_keys, occupancy_dense, occupancy_keys, voxel_indices, GridSpec, MAX_CELLS};
pub use sets::{difference, intersection, union};
pub use tsdf::{tsdf_integrate, DepthView, Tsdf};
