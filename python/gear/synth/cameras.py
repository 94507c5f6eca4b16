"""Seeded camera placement on a sphere around the object (z up unless the world is rotated)."""

from __future__ import annotations

import numpy as np

from gear.camera import Camera

FOV_X = np.deg2rad(40.0)
ELEVATION = (np.deg2rad(-10.0), np.deg2rad(65.0))  # mostly from above, a few from below
MARGIN = 1.08  # the bounding sphere fills the view with this much room


def up_rotation(up: np.ndarray) -> np.ndarray:
    """The smallest rotation taking the renderer's up (+z) to the unit vector `up`."""
    z = np.array([0.0, 0.0, 1.0])
    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    axis = np.cross(z, up)
    sin, cos = np.linalg.norm(axis), float(up @ z)
    if sin < 1e-12:  # up is +z (identity) or -z (half a turn about x)
        return np.eye(3) if cos > 0 else np.diag([1.0, -1.0, -1.0])
    k = axis / sin
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + sin * cross + (1 - cos) * cross @ cross


def sphere_cameras(
    n: int,
    rng: np.random.Generator,
    center: np.ndarray,
    radius: float,
    res: int,
    rotation: np.ndarray | None = None,
) -> list[Camera]:
    """`n` square cameras looking at `center` from random directions (uniform in azimuth and
    in sin(elevation) within ELEVATION), far enough that a sphere of `radius` fits the view.
    `rotation` (3x3) turns the directions and the image-up with a rotated world, so the
    cameras see a rotated object exactly as the unrotated one."""
    distance = MARGIN * radius / np.sin(FOV_X / 2)
    azimuth = rng.uniform(0, 2 * np.pi, n)
    sin_el = rng.uniform(np.sin(ELEVATION[0]), np.sin(ELEVATION[1]), n)
    cos_el = np.sqrt(1 - sin_el**2)
    dirs = np.stack([cos_el * np.cos(azimuth), cos_el * np.sin(azimuth), sin_el], axis=1)
    up = np.array([0.0, 0.0, 1.0])
    if rotation is not None:
        dirs, up = dirs @ rotation.T, rotation @ up
    return [Camera.look_at(center + distance * d, center, up, FOV_X, res, res) for d in dirs]
