"""Stage 2's refinement of a piece's first turn by ICP (`voxels.refined_turn`): a turn read off
fitted planes or a sweep in whole steps can be 10-20 degrees off, and what it misses of the
piece is then cut off as a part of its own; the refined turn must land the piece where it
went, and a turn that is right already must stay right."""

from __future__ import annotations

import numpy as np

from gear.pipeline.stage2.voxels import Scale, refined_turn, split_static_dynamic
from test_coarse import box_surface, hinge_motion

AXIS = np.array([0.0, 0.0, 1.0])
PIVOT = np.array([0.0, 0.0, 0.3])
ANGLE = 60.0


def lid_scene(n: int = 9000, seed: int = 0):
    """A base block and a lid box on it, the lid turned by ANGLE about a vertical line near one
    end; centres jittered by a third of a voxel. Returns (closed, open)."""
    rng = np.random.default_rng(seed)
    base = box_surface([-0.1, -0.15, 0.0], [0.9, 0.15, 0.3], n // 2, rng)
    lid = box_surface([0.0, -0.12, 0.3], [0.6, 0.12, 0.5], n // 2, rng)
    rot, trans = hinge_motion(AXIS, PIVOT, ANGLE)
    closed = np.concatenate([base, lid])
    opened = np.concatenate([base, lid @ rot.T + trans])
    noise = 0.004
    return (closed + rng.normal(0, noise, closed.shape),
            opened + rng.normal(0, noise, opened.shape))


def lid_piece():
    """The split (canonical: closed) and the closed lid's largest dynamic piece: its cells and
    centres."""
    closed, opened = lid_scene()
    size = Scale.of(np.concatenate([closed, opened])).voxel_size(single_part=False)
    split = split_static_dynamic(closed, opened, size)
    labels = split.grid.point_labels(closed, split.labels[0])
    mask = split.labels[0] == 1
    return split, np.argwhere(mask), closed[labels == 1]


def error_of(points: np.ndarray, rot: np.ndarray, trans: np.ndarray) -> float:
    """Median distance between `points` moved by (rot, trans) and by the true turn."""
    true_rot, true_trans = hinge_motion(AXIS, PIVOT, ANGLE)
    return float(np.median(np.linalg.norm(points @ (rot - true_rot).T + trans - true_trans,
                                          axis=1)))


def test_a_turn_about_a_tilted_axis_is_refined_onto_the_true_turn():
    split, cells, points = lid_piece()
    # An axis 10 degrees off and 5 degrees short: half of the lid lands off target matter.
    tilted = np.array([np.sin(np.radians(10)), 0.0, np.cos(np.radians(10))])
    rot, trans = hinge_motion(tilted, PIVOT, ANGLE - 5)
    start = split.score(cells, "hinge", rot, trans)
    voxel = split.grid.voxel_size
    assert error_of(points, rot, trans) > 4 * voxel and start.landed < 0.6  # the premise
    refined = refined_turn(split, cells, points, start)
    assert error_of(points, refined.rot, refined.trans) < 1.5 * voxel
    assert refined.landed > 0.95
    assert refined.kind == "hinge"


def test_a_right_turn_stays_right():
    split, cells, points = lid_piece()
    rot, trans = hinge_motion(AXIS, PIVOT, ANGLE)
    start = split.score(cells, "hinge", rot, trans)
    refined = refined_turn(split, cells, points, start)
    assert error_of(points, refined.rot, refined.trans) < 0.5 * split.grid.voxel_size
    assert refined.landed >= start.landed
