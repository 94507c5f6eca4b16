"""Where the Gaussians start (stage 1): points back-projected from depth, or a visual hull of
the masks when a view lacks depth, each an isotropic Gaussian sized by its neighbours
(docs/method.md, "Stage 1")."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from gear.camera import Camera
from gear.config import TrainConfig
from gear.geometry import nearest_neighbours
from gear.splats.gaussians import Gaussians, logit

INIT_OPACITY = 0.1


def initial_gaussians(views: Sequence, config: TrainConfig, seed: int) -> Gaussians:
    """From depth back-projection when every view has depth, else a visual hull of the masks."""
    rng = np.random.default_rng(seed)
    extent = scene_extent([v.camera for v in views])
    if all(v.depth is not None for v in views):
        pts, cols = points_from_depth(
            views, config.init_voxel_fraction * extent, config.init_max_points, rng
        )
    else:
        pts, cols = points_from_masks(views, config.random_init_points, rng)
        if len(pts) > config.init_max_points:
            pick = rng.choice(len(pts), config.init_max_points, replace=False)
            pts, cols = pts[pick], cols[pick]
    return from_points(pts, cols)


def from_points(points: np.ndarray, colors: np.ndarray) -> Gaussians:
    """Isotropic Gaussians at `points`, scale = mean distance to 3 nearest neighbours."""
    pts = torch.as_tensor(np.asarray(points, dtype=np.float32))
    n = len(pts)
    if n < 4:
        raise ValueError(f"initialisation found only {n} points; the scene masks are empty?")
    nbr = torch.as_tensor(nearest_neighbours(points, 3))
    dist = (pts[nbr] - pts[:, None]).norm(dim=-1).mean(dim=1).clamp_min(1e-7)
    rgb = torch.as_tensor(np.asarray(colors, dtype=np.float32)).clamp(0.02, 0.98)
    return Gaussians(
        dict(
            means=pts,
            quats=torch.tensor([1.0, 0.0, 0.0, 0.0]).repeat(n, 1),
            log_scales=torch.log(dist)[:, None].repeat(1, 3),
            opacity=torch.full((n,), float(logit(INIT_OPACITY))),
            colors=torch.log(rgb / (1 - rgb)),
        )
    )


def scene_extent(cameras: Sequence[Camera]) -> float:
    """1.1 x the largest distance of a camera centre from their mean (the 3DGS convention)."""
    centres = np.stack([c.center for c in cameras])
    radius = float(np.linalg.norm(centres - centres.mean(axis=0), axis=1).max())
    return 1.1 * max(radius, 1e-3)


def _voxel_downsample(points: np.ndarray, colors: np.ndarray, voxel: float):
    keys = np.floor(points / voxel).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return points[first], colors[first]


def points_from_depth(
    views: Sequence, voxel: float, max_points: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Back-projects every view's valid depth inside its object mask; voxel-downsampled."""
    pts, cols = [], []
    for view in views:
        if view.depth is None:
            continue
        valid = (view.depth > 0) & (view.alpha > 0.5)
        pts.append(view.camera.unproject(np.where(valid, view.depth, 0.0)))
        cols.append(view.rgb[valid])
    if not pts:
        raise ValueError("points_from_depth: no view has depth")
    points, colors = _voxel_downsample(np.concatenate(pts), np.concatenate(cols), voxel)
    if len(points) > max_points:
        pick = rng.choice(len(points), max_points, replace=False)
        points, colors = points[pick], colors[pick]
    return points.astype(np.float32), colors.astype(np.float32)


def _common_view_box(cameras: Sequence[Camera]) -> tuple[np.ndarray, float]:
    """Centre (the point nearest all optical axes) and half-size of the region every camera
    sees; makes no assumption about the up axis or the camera layout."""
    a = np.zeros((3, 3))
    b = np.zeros(3)
    for cam in cameras:
        d = cam.cam_to_world[:3, 2]
        p = np.eye(3) - np.outer(d, d)
        a += p
        b += p @ cam.center
    centre = np.linalg.lstsq(a, b, rcond=None)[0]
    half = min(
        np.linalg.norm(c.center - centre) * np.tan(0.5 * min(c.camera_angle_x, c.camera_angle_y))
        for c in cameras
    )
    return centre, float(half)


def _pixels(view, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # noqa: ANN001
    """(row, col, depth z, in_view) of `points` in `view`'s image."""
    uv, z = view.camera.project(points)
    h, w = view.alpha.shape
    with np.errstate(invalid="ignore"):
        col = np.floor(np.nan_to_num(uv[:, 0], nan=-1.0)).astype(np.int64)
        row = np.floor(np.nan_to_num(uv[:, 1], nan=-1.0)).astype(np.int64)
    ok = (z > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
    return np.where(ok, row, 0), np.where(ok, col, 0), z, ok


def _carve(views: Sequence, points: np.ndarray) -> np.ndarray:
    """Visual hull membership of `points`: seen by at least half of the views (fewer leave a
    point unconstrained, e.g. a corner of the search box) and inside the object mask in at
    least 90 % of the views that see it (a little slack for mask noise)."""
    inside = np.zeros(len(points))
    seen = np.zeros(len(points))
    for view in views:
        row, col, _, ok = _pixels(view, points)
        seen += ok
        inside += ok & (view.alpha[row, col] > 0.5)
    return (seen >= 0.5 * len(views)) & (inside >= 0.9 * seen)


def _grid(lo: np.ndarray, hi: np.ndarray, cells: int) -> tuple[np.ndarray, float, tuple]:
    """Cell centres [M,3] of a grid of about `cells` cubic cells covering the box [lo, hi],
    the cell side and the grid shape."""
    size = np.maximum(hi - lo, 1e-9)
    side = float(np.cbrt(np.prod(size) / cells))
    shape = tuple(int(k) for k in np.maximum(np.ceil(size / side), 1))
    axes = [lo[i] + side * (np.arange(shape[i]) + 0.5) for i in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3), side, shape


def _boundary(occupied: np.ndarray) -> np.ndarray:
    """Occupied cells with an empty 6-neighbour (or on the grid's border)."""
    padded = np.pad(occupied, 1)
    core = padded[1:-1, 1:-1, 1:-1]
    full = core.copy()
    for axis in range(3):
        for step in (-1, 1):
            full &= np.roll(padded, step, axis=axis)[1:-1, 1:-1, 1:-1]
    return core & ~full


def _visible_colors(views: Sequence, points: np.ndarray, tolerance: float) -> np.ndarray:
    """Mean colour of each point over the views in which it is the front-most point of its
    pixel (within `tolerance` in depth): the hull occludes itself, so a point takes the colour
    of the side it is on. Points no view sees in front get the mean over every view."""
    total = np.zeros((len(points), 3))
    count = np.zeros(len(points))
    fallback = np.zeros((len(points), 3))
    for view in views:
        row, col, z, ok = _pixels(view, points)
        front = np.full(view.alpha.shape, np.inf)
        np.minimum.at(front, (row[ok], col[ok]), z[ok])
        rgb = view.rgb[row, col]
        fallback[ok] += rgb[ok]
        visible = ok & (z <= front[row, col] + tolerance)
        total[visible] += rgb[visible]
        count[visible] += 1
    none = count == 0
    total[none] = fallback[none]
    count[none] = np.maximum(len(views), 1)
    return total / count[:, None]


def points_from_masks(
    views: Sequence, n_cells: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Points on the surface of the masks' visual hull, for scenes without depth.

    The hull is carved on a grid of about `n_cells` cells over the box of a coarse first
    carving (itself over the region every camera sees, found with no up axis assumed), and
    one point is drawn uniformly in each boundary cell. Points on the hull's surface rather
    than through its volume: a photometric loss sees only the first surface along a ray, so
    Gaussians started inside a solid hull are never pushed out and stage 1 leaves thick blobs
    where the object is thin (docs/method.md, "Stage 1"). Colour = mean
    of the pixels of the views that see the point in front (the hull occluding itself)."""
    centre, half = _common_view_box([v.camera for v in views])
    coarse, side, _ = _grid(centre - half, centre + half, 32**3)
    kept = coarse[_carve(views, coarse)]
    if len(kept) == 0:
        raise ValueError("no point lies inside the object masks of the views; check the alphas")
    cells, side, shape = _grid(kept.min(axis=0) - side, kept.max(axis=0) + side, n_cells)
    occupied = _carve(views, cells).reshape(shape)
    surface = cells[_boundary(occupied).reshape(-1)]
    if len(surface) < 4:
        raise ValueError("no point lies inside the object masks of the views; check the alphas")
    points = surface + rng.uniform(-0.5 * side, 0.5 * side, size=surface.shape)
    colors = _visible_colors(views, points, 1.5 * side)
    return points.astype(np.float32), colors.astype(np.float32)
