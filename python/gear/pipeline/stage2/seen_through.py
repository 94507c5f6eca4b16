"""Static points the target images contradict (docs/method.md, "Stage 2", step 5): a canonical
point that stage 2 leaves static must be where the target state has matter, since the static
part does not move. Where the target images see through it instead, and a part's motion puts
it on the target's surface, attached to that part, it belongs to that part.

Such points are the pieces of a part that stage 2 found no place for: dynamic components under
the size floors, or cells cut off a door by its own motion's landing test. Left static-leaning,
the E-step settles most of them as static: on a real sink cabinet at the fast profile, 42 % of
one door's opaque Gaussians ended static, and the half of them that stayed where the open door
had been showed in every target view as a panel sticking out of the closed cabinet."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from gear import geometry
from gear.articulation import RigidMotion
from gear.pipeline.stage2.voxels import SurfaceTest


def claim_seen_through(
    points: np.ndarray, part_of_point: np.ndarray, motions: Sequence[RigidMotion],
    target: SurfaceTest, tolerance: float, voxel_size: float,
) -> tuple[np.ndarray, int]:
    """`part_of_point` [N] (0 = static, k = movable part k, whose motion is `motions[k - 1]`)
    with the static points of `points` [N, 3] that more views of the `target` state see
    through than show on the surface given to a part whose motion puts them where more views
    show them on the surface than see through them (the part with the nearest point when
    several do), if they are attached to that part: in a 26-connected piece, on the grid of
    `voxel_size` grown by one cell, holding some of its points. Returns the labels and how
    many points changed part.

    Both counts are majorities, not single views: one view seeing past a thin static edge, or a
    turn that happens to put a stray on some surface, is not enough; and attachment keeps a
    part from picking up a stray that its motion lands by chance across the object."""
    labels = np.asarray(part_of_point).copy()
    static = np.flatnonzero(labels == 0)
    if len(static) == 0 or not motions:
        return labels, 0
    on, through = target.votes(points[static], tolerance)
    static = static[through > on]
    if len(static) == 0:
        return labels, 0
    stray = points[static]
    bodies = {k: points[labels == k] for k in range(1, len(motions) + 1)}
    best = np.zeros(len(static), dtype=labels.dtype)
    nearest = np.full(len(static), np.inf)
    for k, (rot, trans) in enumerate(motions, start=1):
        if len(bodies[k]) == 0:
            continue
        on, through = target.votes(stray @ np.asarray(rot).T + np.asarray(trans), tolerance)
        distance = geometry.knn(bodies[k], 1, stray)[1][:, 0]
        better = (on > through) & (distance < nearest)
        best[better], nearest[better] = k, distance[better]
    for k in np.unique(best[best > 0]):
        mine = np.flatnonzero(best == k)
        best[mine[~_attached(bodies[k], stray[mine], voxel_size)]] = 0
    labels[static] = best
    return labels, int(np.count_nonzero(best))


def _attached(body: np.ndarray, strays: np.ndarray, voxel_size: float) -> np.ndarray:
    """Which of `strays` lie in a 26-connected piece of the cells of `body` and `strays`
    (grown by one cell) that holds a cell of `body`."""
    of_body, of_strays = geometry.piece_labels([body, strays], voxel_size)
    held = np.unique(of_body)
    return np.isin(of_strays, held[held > 0])
