"""Static points the target images contradict (docs/method.md, "Stage 2", step 5): a canonical
point that stage 2 leaves static must be where the target state has matter, since the static
part does not move. Where the target images see through it instead, and a part's motion puts
it on the target's surface, it belongs to that part.

Such points are the pieces of a part that stage 2 found no place for: dynamic components under
the size floors, or cut off a door by its own motion's landing test. Left static-leaning, the
E-step settles most of them as static: on a real sink cabinet at the fast profile, 42 % of one
door's opaque Gaussians ended static, and the half of them that stayed where the open door had
been showed in every target view as a panel sticking out of the closed cabinet."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from gear import geometry
from gear.articulation import RigidMotion
from gear.pipeline.stage2.voxels import SurfaceTest


def claim_seen_through(
    points: np.ndarray, part_of_point: np.ndarray, motions: Sequence[RigidMotion],
    surface: SurfaceTest, tolerance: float,
) -> tuple[np.ndarray, int]:
    """`part_of_point` [N] (0 = static, k = movable part k, whose motion is `motions[k - 1]`)
    with every static point of `points` [N, 3] that `surface` sees through (within
    `tolerance`) given to a part whose motion lands it on the surface and not seen through;
    to the part with the nearest point when several do. Returns the labels and how many
    points changed part."""
    labels = np.asarray(part_of_point).copy()
    static = np.flatnonzero(labels == 0)
    if len(static) == 0 or not motions:
        return labels, 0
    _, seen_through = surface(points[static], tolerance)
    static = static[seen_through]
    if len(static) == 0:
        return labels, 0
    stray = points[static]
    best = np.zeros(len(static), dtype=labels.dtype)
    nearest = np.full(len(static), np.inf)
    for k, (rot, trans) in enumerate(motions, start=1):
        body = points[labels == k]
        if len(body) == 0:
            continue
        on, through = surface(stray @ np.asarray(rot).T + np.asarray(trans), tolerance)
        distance = geometry.knn(body, 1, stray)[1][:, 0]
        better = on & ~through & (distance < nearest)
        best[better], nearest[better] = k, distance[better]
    labels[static] = best
    return labels, int(np.count_nonzero(best))
