//! k nearest neighbours of 3D points.
