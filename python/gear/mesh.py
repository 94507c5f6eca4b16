"""Meshes from depth images: truncated signed distance (TSDF) fusion and marching cubes.

The volume covers only the bounding box of the back-projected valid depth (plus a margin), and the
signed distance is evaluated only in a narrow band around those points: voxels farther than the
truncation distance from every observed surface point can never hold a zero crossing. Each view
updates the band voxels that project onto one of its valid pixels and lie in front of, or less than
`trunc` behind, the observed depth (the usual projective TSDF, averaged over the views; native
threads, gear_core::voxel::tsdf_integrate). Marching
cubes then runs only on cubes whose eight corners were observed, so unobserved space (inside the
object, outside the band) never produces spurious surfaces.

A pixel is valid when its alpha exceeds `alpha_threshold` and its depth is finite and positive;
depth is camera-space z (not ray length), as the rasterizer's expected depth after dividing by
alpha. Other pixels are skipped (they neither add surface nor carve space).
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence

import numpy as np
import trimesh
from scipy import sparse
from scipy.sparse import csgraph
from skimage.measure import marching_cubes

from gear import _core
from gear.camera import Camera
from gear.geometry import dilate

# Dense grids hold a bool band mask plus float32 TSDF and weight (9 bytes per voxel): 2^25 voxels
# is about 300 MB. Larger boxes are coarsened automatically (with a warning).
MAX_VOXELS = 2**25
_MIN_TRUNC_VOXELS = 2.5  # the band must span a few voxels for marching cubes to see a crossing


def _check_inputs(
    depths: Sequence[np.ndarray], alphas: Sequence[np.ndarray], cameras: Sequence[Camera]
) -> None:
    if not (len(depths) == len(alphas) == len(cameras)):
        raise ValueError(
            f"tsdf_fuse: got {len(depths)} depths, {len(alphas)} alphas, {len(cameras)} cameras"
        )
    for i, (d, a, cam) in enumerate(zip(depths, alphas, cameras, strict=True)):
        shape = (cam.height, cam.width)
        if np.shape(d) != shape:
            raise ValueError(f"tsdf_fuse: depths[{i}] has shape {np.shape(d)}, camera is {shape}")
        if np.shape(a) != shape:
            raise ValueError(f"tsdf_fuse: alphas[{i}] has shape {np.shape(a)}, camera is {shape}")


def _valid_mask(depth: np.ndarray, alpha: np.ndarray, alpha_threshold: float) -> np.ndarray:
    d = np.asarray(depth, dtype=np.float32)
    with np.errstate(invalid="ignore"):
        return (np.asarray(alpha) > alpha_threshold) & np.isfinite(d) & (d > 0)


def _observed_points(
    depths: Sequence[np.ndarray], valid: Sequence[np.ndarray], cameras: Sequence[Camera]
) -> np.ndarray:
    """World points of every valid pixel of every view, [N,3] float64."""
    chunks = [
        cam.unproject(np.where(m, np.asarray(d, np.float64), 0.0))
        for d, m, cam in zip(depths, valid, cameras, strict=True)
        if m.any()
    ]
    return np.concatenate(chunks) if chunks else np.zeros((0, 3))


def _grid_size(lo: np.ndarray, hi: np.ndarray, voxel: float) -> np.ndarray:
    return np.floor((hi - lo) / voxel).astype(np.int64) + 1


def _choose_voxel(lo: np.ndarray, hi: np.ndarray, voxel: float, max_voxels: int) -> float:
    """`voxel`, or a coarser size when the box would exceed `max_voxels` (warns)."""
    count = float(np.prod(_grid_size(lo, hi, voxel)))
    if count <= max_voxels:
        return voxel
    coarse = voxel * (count / max_voxels) ** (1.0 / 3.0)
    while np.prod(_grid_size(lo, hi, coarse)) > max_voxels:
        coarse *= 1.05
    warnings.warn(
        f"tsdf_fuse: a {hi - lo} box at voxel {voxel:g} needs {count:.3g} voxels "
        f"(limit {max_voxels:.3g}); using voxel {coarse:.4g} instead",
        stacklevel=3,
    )
    return coarse


def tsdf_fuse(
    depths: Sequence[np.ndarray],
    alphas: Sequence[np.ndarray],
    cameras: Sequence[Camera],
    voxel: float = 0.004,
    trunc: float = 0.02,
    alpha_threshold: float = 0.5,
    max_voxels: int = MAX_VOXELS,
) -> trimesh.Trimesh:
    """Fuse z-depth images into a mesh; returns its largest connected component.

    depths[i], alphas[i]: [H,W] arrays matching cameras[i] (gear.camera.Camera, OpenCV axes).
    Returns an empty Trimesh when no pixel is valid or no surface is found. When the observed
    box needs more than `max_voxels` voxels, the voxel size grows until it fits (with a warning)
    and `trunc` grows to at least 2.5 voxels.
    """
    if not (voxel > 0 and trunc > 0):
        raise ValueError(f"tsdf_fuse: voxel and trunc must be positive, got {voxel}, {trunc}")
    _check_inputs(depths, alphas, cameras)
    valid = [_valid_mask(d, a, alpha_threshold) for d, a in zip(depths, alphas, strict=True)]
    points = _observed_points(depths, valid, cameras)
    if len(points) == 0:
        return trimesh.Trimesh()

    lo0, hi0 = points.min(axis=0), points.max(axis=0)
    voxel = _choose_voxel(lo0 - 2 * trunc, hi0 + 2 * trunc, voxel, max_voxels)
    trunc = max(trunc, _MIN_TRUNC_VOXELS * voxel)
    margin = trunc + 2 * voxel
    lo, hi = lo0 - margin, hi0 + margin
    shape = tuple(_grid_size(lo, hi, voxel).tolist())

    # Narrow band: voxels within `trunc` (Chebyshev, a superset of the Euclidean ball) of an
    # observed point.
    band = np.zeros(shape, dtype=bool)
    idx = np.clip(np.round((points - lo) / voxel).astype(np.int64), 0, np.array(shape) - 1)
    band[idx[:, 0], idx[:, 1], idx[:, 2]] = True
    radius = int(np.ceil(trunc / voxel))
    band = dilate(band, radius)

    flat = np.flatnonzero(band)
    ijk = np.stack(np.unravel_index(flat, shape), axis=1)
    centres = np.ascontiguousarray(lo + ijk * voxel, dtype=np.float32)  # voxel i at lo + i·voxel
    views = [(np.where(m, d, 0).astype(np.float32), cam)
             for d, m, cam in zip(depths, valid, cameras, strict=True) if m.any()]
    tsdf, weight = _core.tsdf_integrate(
        centres, [d for d, _ in views],
        [cam.world_to_cam.astype(np.float32) for _, cam in views],
        [(cam.fx, cam.fy, cam.cx, cam.cy) for _, cam in views], trunc)

    volume = np.ones(shape, np.float32)  # unobserved = outside; masked out below anyway
    observed = np.zeros(shape, bool)
    volume.reshape(-1)[flat] = tsdf
    observed.reshape(-1)[flat] = weight > 0
    return _extract_surface(volume, observed, lo, voxel)


def _extract_surface(
    volume: np.ndarray, observed: np.ndarray, lo: np.ndarray, voxel: float
) -> trimesh.Trimesh:
    """Marching cubes on cubes whose 8 corners are observed; the largest component."""
    if min(volume.shape) < 2:
        return trimesh.Trimesh()
    # skimage visits the cube spanning [x-1, x] x [y-1, y] x [z-1, z] only where mask[x, y, z]
    # is set (its highest corner; checked on a one-voxel volume).
    cube_ok = np.zeros_like(observed)
    corners = observed[:-1, :-1, :-1].copy()
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                corners &= observed[dx : dx + volume.shape[0] - 1, dy : dy + volume.shape[1] - 1,
                                    dz : dz + volume.shape[2] - 1]
    cube_ok[1:, 1:, 1:] = corners
    seen = volume[observed]
    if not cube_ok.any() or seen.min() > 0 or seen.max() < 0:  # no sign change: no surface
        return trimesh.Trimesh()
    try:
        verts, faces, _, _ = marching_cubes(
            volume, level=0.0, spacing=(voxel,) * 3, mask=cube_ok, gradient_direction="descent"
        )
    except (ValueError, RuntimeError):  # no crossing inside the masked cubes
        return trimesh.Trimesh()
    if len(faces) == 0:
        return trimesh.Trimesh()
    faces = _largest_component(faces, len(verts))
    return trimesh.Trimesh(verts + lo, faces, process=True)


def _largest_component(faces: np.ndarray, num_vertices: int) -> np.ndarray:
    """The faces of the largest (by face count) vertex-connected component.

    Marching cubes already shares vertices between neighbouring faces, so components of the
    vertex graph are the mesh's connected pieces (much faster than splitting a Trimesh).
    """
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]])
    graph = sparse.coo_matrix(
        (np.ones(len(edges), np.int8), (edges[:, 0], edges[:, 1])),
        shape=(num_vertices, num_vertices),
    )
    count, labels = csgraph.connected_components(graph, directed=False)
    if count <= 1:
        return faces
    face_labels = labels[faces[:, 0]]
    return faces[face_labels == np.argmax(np.bincount(face_labels))]
