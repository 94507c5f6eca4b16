"""Room for the joints to move: static collision pieces cut back wherever a moving part's pieces
would sink into them anywhere in the joint's range.

A reconstructed surface is a little thicker than the real one, and a door that is ajar in the
start state may overlap the frame it closes against: left as they are, a simulator's contact
solver would shove the part away from its rest pose. Each overlap is removed with one plane cut
of the static piece (a convex piece stays convex), along the separating axis that removes the
least: the face normals of both pieces, as in the separating axis test.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import trimesh

if TYPE_CHECKING:  # assembly calls this module: a run-time import would be circular
    from gear.export.assembly import Joint

STEP_RAD = math.radians(2.0)  # revolute sampling of the joint range
STEPS_PRISMATIC = 40  # prismatic sampling: the range in this many steps
MIN_KEPT_VOLUME = 1e-9


def joint_samples(joint: Joint) -> np.ndarray:
    """Joint values from the lower to the upper limit, dense enough that a piece moves less
    than a few millimetres between two of them for parts up to a metre or two."""
    span = joint.upper - joint.lower
    steps = math.ceil(span / STEP_RAD) if joint.type == "revolute" else STEPS_PRISMATIC
    return np.linspace(joint.lower, joint.upper, max(2, steps + 1))


def _normals(mesh: trimesh.Trimesh) -> np.ndarray:
    return np.unique(np.round(mesh.face_normals, 9), axis=0)


def _cut_plane(static: trimesh.Trimesh, moving: np.ndarray, moving_normals: np.ndarray,
               clearance: float) -> tuple[np.ndarray, float] | None:
    """(n, d) such that keeping {x: n.x >= d} of `static` clears the convex point set `moving`
    by `clearance`, removing the least depth; None when the two are already that far apart
    along some face normal."""
    a = static.vertices
    best: tuple[float, np.ndarray, float] | None = None
    # Axes of the moving piece: keep the static part beyond its face planes.
    h = (moving @ moving_normals.T).max(axis=0) + clearance
    depth = h - (a @ moving_normals.T).min(axis=0)
    if depth.min() <= 0:
        return None
    k = int(depth.argmin())
    best = (float(depth[k]), moving_normals[k], float(h[k]))
    # Axes of the static piece: pull its own faces back in front of the moving piece.
    normals = _normals(static)
    low = (moving @ normals.T).min(axis=0) - clearance
    depth = (a @ normals.T).max(axis=0) - low
    if depth.min() <= 0:
        return None
    k = int(depth.argmin())
    if depth[k] < best[0]:
        best = (float(depth[k]), -normals[k], float(-low[k]))
    return best[1], best[2]


def _keep(piece: trimesh.Trimesh, normal: np.ndarray, offset: float) -> trimesh.Trimesh | None:
    """The convex `piece` cut to {x: normal.x >= offset} (None when too little is left)."""
    v = piece.vertices
    side = v @ normal - offset
    kept = [v[side >= 0]]
    edges = piece.edges_unique
    s0, s1 = side[edges[:, 0]], side[edges[:, 1]]
    crossing = (s0 < 0) != (s1 < 0)
    if crossing.any():
        t = s0[crossing] / (s0[crossing] - s1[crossing])
        p0, p1 = v[edges[crossing, 0]], v[edges[crossing, 1]]
        kept.append(p0 + t[:, None] * (p1 - p0))
    points = np.concatenate(kept)
    if len(points) < 4:
        return None
    try:
        hull = trimesh.convex.convex_hull(points)
    except Exception:  # qhull refuses a flat remainder
        return None
    return hull if hull.volume > MIN_KEPT_VOLUME else None


def clear_joint_paths(static: list[trimesh.Trimesh],
                      movers: list[tuple[Joint, list[trimesh.Trimesh]]],
                      clearance: float) -> tuple[list[trimesh.Trimesh], int]:
    """The static pieces cut so that no moving piece comes closer than `clearance` to them at
    any sampled joint value (start-state world coordinates); and the number of cuts made."""
    pieces: list[trimesh.Trimesh | None] = list(static)
    cuts = 0
    for joint, moving in movers:
        for value in joint_samples(joint):
            motion = joint.motion(float(value))
            for piece in moving:
                points = piece.vertices @ motion[:3, :3].T + motion[:3, 3]
                normals = _normals(piece) @ motion[:3, :3].T
                lo, hi = points.min(axis=0) - clearance, points.max(axis=0) + clearance
                for i, target in enumerate(pieces):
                    if target is None or np.any(target.bounds[0] > hi) or np.any(
                            target.bounds[1] < lo):
                        continue
                    plane = _cut_plane(target, points, normals, clearance)
                    if plane is not None:
                        pieces[i] = _keep(target, *plane)
                        cuts += 1
    return [p for p in pieces if p is not None], cuts
