"""Stage-1 initialisation without depth (splats.init): points on the surface of
the masks' visual hull, coloured by the views that see them in front.

The scene is a sphere of radius R ray-traced analytically (no rasterizer involved): red where
the surface point has x > 0, blue where x < 0, seen by 8 cameras around it."""

from __future__ import annotations

import numpy as np
import pytest

from gear.camera import Camera
from gear.data.scene import View
from gear.splats.init import points_from_masks

R = 0.3
RED, BLUE = np.array([0.9, 0.1, 0.1]), np.array([0.1, 0.1, 0.9])


def _sphere_view(index: int, eye: np.ndarray, res: int) -> View:
    cam = Camera.look_at(eye, np.zeros(3), np.array([0.0, 0.0, 1.0]), 0.7, res, res)
    v, u = np.mgrid[0:res, 0:res] + 0.5
    rays = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], axis=-1)
    rays = rays @ cam.cam_to_world[:3, :3].T
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    origin = cam.center
    # |o + t d| = R: t² + 2 (o.d) t + |o|² - R² = 0, nearest root
    b = rays @ origin
    disc = b * b - (origin @ origin - R * R)
    hit = disc > 0
    t = -b - np.sqrt(np.where(hit, disc, 0.0))
    x = origin[0] + t * rays[..., 0]
    rgb = np.where((x > 0)[..., None], RED, BLUE) * hit[..., None]
    return View(f"start/train/{index:04d}", cam, rgb.astype(np.float32),
                hit.astype(np.float32))


def sphere_views(res: int = 40) -> list[View]:
    views = []
    for i in range(8):
        a = 2 * np.pi * (i + 0.25) / 8
        elevation = 0.5 * np.sin(3 * a)  # a ring that wobbles up and down
        eye = 2.0 * np.array([np.cos(a), np.sin(a), elevation])
        views.append(_sphere_view(i, eye, res))
    return views


def test_hull_points_lie_on_the_surface_not_in_the_volume():
    """Every point is within the hull's surface shell: at most ~1.3 R out (8 silhouettes bound a
    sphere loosely) and never deep inside (a volume sample would reach the centre)."""
    pts, cols = points_from_masks(sphere_views(), 20_000, np.random.default_rng(0))
    radius = np.linalg.norm(pts, axis=1)
    assert len(pts) > 200
    assert radius.max() < 1.3 * R, radius.max()
    assert radius.min() > 0.75 * R, radius.min()
    assert np.median(radius) < 1.15 * R, np.median(radius)
    assert np.isfinite(pts).all() and np.isfinite(cols).all()
    assert pts.dtype == np.float32 and cols.dtype == np.float32 and cols.shape == pts.shape


def test_hull_points_take_the_colour_of_their_own_side():
    """A point is coloured by the views that see it in front (the hull occludes itself): points
    well on the red side (x > R/3) are red, well on the blue side blue. The mean over every
    view that projects a point inside its mask would mix both halves."""
    pts, cols = points_from_masks(sphere_views(), 20_000, np.random.default_rng(1))
    red, blue = pts[:, 0] > R / 3, pts[:, 0] < -R / 3
    assert red.sum() > 50 and blue.sum() > 50
    assert np.mean(cols[red, 0] > cols[red, 2]) > 0.95
    assert np.mean(cols[blue, 2] > cols[blue, 0]) > 0.95
    assert np.abs(cols[red] - RED).mean() < 0.1, cols[red].mean(axis=0)


def test_empty_masks_are_a_clear_error():
    views = sphere_views(16)
    for view in views:
        view.alpha[:] = 0.0
    with pytest.raises(ValueError, match="inside the object masks"):
        points_from_masks(views, 5_000, np.random.default_rng(0))
