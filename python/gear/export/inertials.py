"""Mass, centre of mass and inertia of a link from the volume of its convex pieces.

The pieces are what the simulator collides, so mass follows the same solid: a hollow cabinet
weighs its walls, not its bounding block. Densities are per cubic scene unit; the built-in scenes
are in metres, where the default gives everyday furniture and appliances plausible masses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import trimesh

from gear.export import defaults

MIN_MASS = 1e-3  # a link without geometry still needs a positive mass to move in a simulator


@dataclass
class Inertial:
    mass: float
    com: np.ndarray  # [3] world, start state
    inertia: np.ndarray  # [3,3] about the centre of mass, world axes
    volume: float


def solid_inertial(pieces: list[trimesh.Trimesh], density: float) -> Inertial:
    """Mass properties of the union of `pieces` at `density` (their overlaps, small for a
    decomposition, count twice)."""
    volumes = np.array([p.volume for p in pieces])
    coms = np.array([p.center_mass for p in pieces])
    volume = float(volumes.sum())
    if not pieces or volume <= 0:
        return point_inertial(np.zeros(3))
    com = (volumes[:, None] * coms).sum(axis=0) / volume
    inertia = np.zeros((3, 3))
    for piece, v, c in zip(pieces, volumes, coms, strict=True):
        piece_inertia = piece.moment_inertia * density / piece.density  # about its own COM
        mass = density * v
        d = c - com  # parallel axis theorem to the link's COM
        inertia += piece_inertia + mass * (float(d @ d) * np.eye(3) - np.outer(d, d))
    return Inertial(density * volume, com, inertia, volume)


def point_inertial(where: np.ndarray) -> Inertial:
    """A tiny mass for a link with no geometry (simulators refuse massless moving bodies)."""
    side = 0.01
    return Inertial(MIN_MASS, np.asarray(where, dtype=np.float64),
                    np.eye(3) * MIN_MASS * side * side / 6, 0.0)


def link_density(volumes: list[float], density: float | None, total_mass: float | None) -> float:
    """The density every link uses: `density`, or `total_mass` spread by volume."""
    if total_mass is None:
        return defaults.DENSITY if density is None else density
    volume = float(sum(volumes))
    if volume <= 0:
        raise ValueError("--mass needs links with volume (every part mesh is empty)")
    return total_mass / volume


def check_positive(what: str, value: float | None) -> None:
    if value is not None and not (math.isfinite(value) and value > 0):
        raise ValueError(f"{what} must be a positive number, got {value}")
