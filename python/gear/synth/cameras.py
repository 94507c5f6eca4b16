"""Seeded camera placement on a sphere around the object (z up)."""

from __future__ import annotations

import numpy as np

from gear.camera import Camera

FOV_X = np.deg2rad(40.0)
ELEVATION = (np.deg2rad(-10.0), np.deg2rad(65.0))  # mostly from above, a few from below
MARGIN = 1.08  # the bounding sphere fills the view with this much room


def sphere_cameras(
    n: int, rng: np.random.Generator, center: np.ndarray, radius: float, res: int
) -> list[Camera]:
    """`n` square cameras looking at `center` from random directions (uniform in azimuth and
    in sin(elevation) within ELEVATION), far enough that a sphere of `radius` fits the view."""
    distance = MARGIN * radius / np.sin(FOV_X / 2)
    azimuth = rng.uniform(0, 2 * np.pi, n)
    sin_el = rng.uniform(np.sin(ELEVATION[0]), np.sin(ELEVATION[1]), n)
    cos_el = np.sqrt(1 - sin_el**2)
    dirs = np.stack([cos_el * np.cos(azimuth), cos_el * np.sin(azimuth), sin_el], axis=1)
    return [Camera.look_at(center + distance * d, center, [0, 0, 1], FOV_X, res, res) for d in dirs]
