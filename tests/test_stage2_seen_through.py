"""Stage 2's claim of static points that the target images see through
(`stage2.seen_through.claim_seen_through`): a drawer pulled out in the canonical state, pushed
in (closed) in the target state, part of its front left static by stage 2."""

from __future__ import annotations

import numpy as np

from gear.pipeline.stage2.seen_through import claim_seen_through
from stage2_surfaces import OneView

TOLERANCE = 0.02
VOXEL = 0.05
PULL = 0.4
PUSH = (np.eye(3), np.array([0.0, PULL, 0.0]))  # canonical (pulled out) -> target (closed)


def closed_look(points: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """The closed state's images, as one view's votes: the cabinet's front plane at y = 0 over
    x, z in [0, 1]. On it: on the surface; in front of it or beside the cabinet: seen through;
    behind it: hidden (neither)."""
    inside = np.all((points[:, [0, 2]] >= 0) & (points[:, [0, 2]] <= 1), axis=1)
    on = inside & (np.abs(points[:, 1]) < tolerance)
    free = ~inside | (points[:, 1] < -tolerance)
    return on.astype(np.int64), free.astype(np.int64)


def claim(points, labels, motions, look=closed_look):
    return claim_seen_through(points, labels, motions, OneView(look), TOLERANCE, VOXEL)


def front(x0: float, x1: float, y: float, n: int, rng: np.random.Generator) -> np.ndarray:
    """`n` centres on a front plane at depth y over x in [x0, x1], z in [0.1, 0.5]."""
    return np.column_stack([rng.uniform(x0, x1, n), np.full(n, y), rng.uniform(0.1, 0.5, n)])


def test_a_pulled_drawers_front_left_static_joins_the_drawer():
    rng = np.random.default_rng(0)
    drawer = front(0.1, 0.5, -PULL, 200, rng)   # found by stage 2: part 1
    stray = front(0.5, 0.9, -PULL, 150, rng)    # the rest of its front, left static
    body = front(0.0, 1.0, 0.0, 300, rng)       # the cabinet's front: static, and on the surface
    hidden = np.column_stack([rng.uniform(0.1, 0.9, 50), rng.uniform(0.1, 0.3, 50),
                              rng.uniform(0.1, 0.5, 50)])  # inside the cabinet: never seen
    points = np.concatenate([drawer, stray, body, hidden])
    labels = np.concatenate([np.ones(200, int), np.zeros(150 + 300 + 50, int)])
    out, claimed = claim(points, labels, [PUSH])
    assert claimed == 150
    np.testing.assert_array_equal(out[:350], 1)
    # Matter the target shows where it is, or hides, stays static.
    np.testing.assert_array_equal(out[350:], 0)
    np.testing.assert_array_equal(labels[200:], 0)  # the input is not modified


def test_a_seen_through_point_no_motion_lands_stays_static():
    rng = np.random.default_rng(1)
    drawer = front(0.1, 0.5, -PULL, 200, rng)
    floater = np.array([[0.5, -0.2, 0.3], [2.0, -0.4, 0.3]])  # pushed: behind the front / beside
    points = np.concatenate([drawer, floater])
    labels = np.concatenate([np.ones(200, int), np.zeros(2, int)])
    out, claimed = claim(points, labels, [PUSH])
    assert claimed == 0
    np.testing.assert_array_equal(out, labels)


def test_a_stray_that_two_parts_land_joins_the_nearest():
    rng = np.random.default_rng(2)
    left = front(0.1, 0.3, -PULL, 100, rng)
    right = front(0.7, 0.9, -PULL, 100, rng)
    strays = np.array([[0.35, -PULL, 0.3], [0.65, -PULL, 0.3]])
    points = np.concatenate([left, right, strays])
    labels = np.concatenate([np.ones(100, int), np.full(100, 2), np.zeros(2, int)])
    out, claimed = claim(points, labels, [PUSH, PUSH])
    assert claimed == 2
    assert out[-2] == 1 and out[-1] == 2


def test_movable_points_and_a_scene_without_parts_are_left_alone():
    rng = np.random.default_rng(3)
    drawer = front(0.1, 0.9, -PULL, 100, rng)
    # A part whose own motion the images contradict keeps its label: only static is claimed.
    astray = (np.eye(3), np.array([0.0, -0.3, 0.0]))
    out, claimed = claim(drawer, np.ones(100, int), [astray])
    assert claimed == 0 and (out == 1).all()
    out, claimed = claim(drawer, np.zeros(100, int), [])
    assert claimed == 0 and (out == 0).all()


def test_a_stray_landed_by_chance_away_from_the_part_stays_static():
    rng = np.random.default_rng(4)
    drawer = front(0.1, 0.3, -PULL, 200, rng)
    stray = np.array([[0.8, -PULL, 0.9]])  # seen through, pushed onto the front: but detached
    points = np.concatenate([drawer, stray])
    labels = np.concatenate([np.ones(200, int), np.zeros(1, int)])
    out, claimed = claim(points, labels, [PUSH])
    assert claimed == 0 and out[-1] == 0


def test_a_point_more_views_show_than_see_through_stays_static():
    rng = np.random.default_rng(5)
    drawer = front(0.1, 0.5, -PULL, 200, rng)
    stray = front(0.5, 0.9, -PULL, 50, rng)
    points = np.concatenate([drawer, stray])
    labels = np.concatenate([np.ones(200, int), np.zeros(50, int)])

    def split_vote(pts, tolerance):
        """Three views: one sees through the strays where they are, two show them there."""
        on, through = closed_look(pts, tolerance)
        where_strays = pts[:, 1] < -tolerance
        return on + 2 * where_strays, through

    out, claimed = claim(points, labels, [PUSH], split_vote)
    assert claimed == 0 and (out[200:] == 0).all()
    out, claimed = claim(points, labels, [PUSH])
    assert claimed == 50
