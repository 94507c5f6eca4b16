"""Stage 2's check that the target images see a component move (`seen_change`), with a
target state that hides part of the moved matter: a drawer pushed into its cabinet."""

from __future__ import annotations

import numpy as np

from gear.pipeline.stage2.hypotheses import Hypothesis
from gear.pipeline.stage2.parts import MIN_SEEN_CHANGE, seen_change

TOLERANCE = 0.02


def drawer_look(front_y: float):
    """What the closed state's images show: the cabinet's front plane at y = front_y between
    x, z in [0, 1]. A point on it is on the surface; in front of it (y < front_y - tolerance)
    or beside the cabinet it is seen through; behind it (inside the cabinet) it is hidden:
    neither."""

    def look(points: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
        inside = np.all((points[:, [0, 2]] >= 0) & (points[:, [0, 2]] <= 1), axis=1)
        on = inside & (np.abs(points[:, 1] - front_y) < tolerance)
        free = ~inside | (points[:, 1] < front_y - tolerance)
        return on, free

    return look


def open_drawer(rng: np.random.Generator, pull: float) -> np.ndarray:
    """An open drawer's centres: its front at y = -pull and the part of its box pulled out of
    the cabinet (half of the centres; what stays inside is not reconstructed)."""
    front = np.column_stack([rng.uniform(0.1, 0.9, 500), np.full(500, -pull),
                             rng.uniform(0.1, 0.5, 500)])
    box = np.column_stack([rng.uniform(0.1, 0.9, 500), rng.uniform(-pull + 0.05, -0.05, 500),
                           rng.uniform(0.1, 0.5, 500)])
    return np.concatenate([front, box])


def test_a_drawer_whose_box_disappears_into_the_cabinet_is_seen_to_move():
    rng = np.random.default_rng(0)
    pull = 0.4
    points = open_drawer(rng, pull)
    push = Hypothesis("slide", np.eye(3), np.array([0.0, pull, 0.0]))
    score = seen_change(points, push, drawer_look(0.0), TOLERANCE)
    # Half the centres (the box) end inside the cabinet, out of sight: not a contradiction.
    assert score >= 0.95 > MIN_SEEN_CHANGE


def test_matter_moved_wholly_out_of_sight_or_nowhere_is_not_seen_to_move():
    rng = np.random.default_rng(1)
    points = open_drawer(rng, 0.4)
    look = drawer_look(0.0)
    deep = Hypothesis("slide", np.eye(3), np.array([0.0, 0.6, 0.0]))  # all behind the front
    assert seen_change(points, deep, look, TOLERANCE) == 0.0
    astray = Hypothesis("slide", np.eye(3), np.array([0.0, -0.3, 0.0]))  # into empty space
    assert seen_change(points, astray, look, TOLERANCE) < MIN_SEEN_CHANGE


def pulled_drawer_look(pull: float):
    """What the images of a drawer pulled out by `pull` show: its front at y = -pull over x in
    [0.1, 0.9], z in [0.1, 0.5]; behind the front, inside the drawer, they see down through its
    open top to z = 0.3 (seen through above, hidden below); beside the drawer, empty space."""

    def look(points: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
        x, y, z = points.T
        footprint = (x >= 0.1) & (x <= 0.9) & (z >= 0.1) & (z <= 0.5)
        on = footprint & (np.abs(y + pull) < tolerance)
        behind = footprint & (y > -pull + tolerance)
        free = ~footprint | (y < -pull - tolerance) | (behind & (z > 0.3))
        return on, free

    return look


def test_a_pulled_drawer_whose_old_place_is_half_hidden_is_seen_to_move():
    """The closed front's place lies inside the pulled drawer: the images see half of it
    through the open top, empty, and nothing of the rest. Hidden is not "still there"."""
    rng = np.random.default_rng(2)
    closed_front = np.column_stack([rng.uniform(0.1, 0.9, 800), np.zeros(800),
                                    rng.uniform(0.1, 0.5, 800)])
    pull = 0.3
    out = Hypothesis("slide", np.eye(3), np.array([0.0, -pull, 0.0]))
    assert seen_change(closed_front, out, pulled_drawer_look(pull), TOLERANCE) >= 0.95


def test_matter_mostly_hidden_where_it_was_is_not_seen_to_move():
    """Where the images see under half of a component's old place, only what they see empty
    counts, over the whole: an interior that one state reveals and the other hides behind its
    closed door scores low even when its motion lands it on matter."""
    rng = np.random.default_rng(3)
    interior = np.column_stack([rng.uniform(0.1, 0.9, 800), rng.uniform(0.2, 0.8, 800),
                                rng.uniform(0.1, 0.5, 800)])

    def closed_door(points: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
        # Matter far in front (y < -1); the interior hidden behind the door but for a gap
        # along x > 0.75, seen empty.
        on = points[:, 1] < -1.0
        free = (points[:, 1] >= 0.0) & (points[:, 0] > 0.75)
        return on, free

    onto_matter = Hypothesis("slide", np.eye(3), np.array([0.0, -2.0, 0.0]))
    assert seen_change(interior, onto_matter, closed_door, TOLERANCE) < 0.3
