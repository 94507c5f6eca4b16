//! Voxel grids shared by several point sets: occupancy, set operations, dilation, components.
