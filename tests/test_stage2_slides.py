"""Stage 2's slides of drawers: a push-in judged by what the target images can see (its box goes
where the closed state reconstructed nothing), two drawers of one column pulled by the
same travel kept as two parts, a slide that covers clearly more of the change than a hinge
landing as well goes first, and a deep drawer pushed in claims the change its front shows."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from gear.pipeline.stage2.hypotheses import DETECT_OVERLAP, Hypothesis
from gear.pipeline.stage2.parts import _first_on_free_matter, change_in_sight, coarse_init
from gear.pipeline.stage2.voxels import near_tie_order, split_static_dynamic
from test_coarse import FRONT, box_surface, hinge_motion

VOXEL = 0.025
PUSH = np.array([0.0, 0.3, 0.0])  # the true motion: the drawer pushed in along +y
DECOY = np.array([0.6, 0.0, 0.0])  # where an identical drawer stands in the target only


def drawer(offset, rng, n=3000):
    """An open-top drawer box (front at y = 0) moved by `offset`."""
    return box_surface([0, 0, 0], [0.4, 0.4, 0.2], n, rng, skip=(5,)) + offset


def push_in_scene(seed=0):
    """Canonical: a drawer alone. Target: the same drawer pushed in by PUSH, of which only the
    front and the bottom were reconstructed (the sides and back are inside the cabinet, hidden),
    and an identical whole drawer at DECOY, onto which a sideways shift lands every cell."""
    rng = np.random.default_rng(seed)
    canon = drawer(np.zeros(3), rng)
    pushed = drawer(PUSH, rng)
    shown = (pushed[:, 1] <= PUSH[1] + 1e-9) | (pushed[:, 2] <= 1e-9)
    target = np.concatenate([pushed[shown], drawer(DECOY, rng)])
    return canon, target


class HiddenInterior:
    """A target SurfaceTest of push_in_scene: a point on the target's matter is seen on the
    surface, a point inside the cabinet (behind the pushed front) is hidden, any other point is
    seen through."""

    def __init__(self, target):
        self.target = target

    def __call__(self, points, tolerance):
        on = cKDTree(self.target).query(points)[0] < tolerance
        inside = (points[:, 1] > PUSH[1] + tolerance) & (points[:, 0] < 0.45)
        return on, ~on & ~inside


def test_push_in_is_chosen_when_the_images_see_its_box_hidden():
    canon, target = push_in_scene()
    split = split_static_dynamic(canon, target, VOXEL)
    mask = split.labels[0] == 1
    assert mask.sum() > 0.9 * (split.labels[0] > 0).sum()  # the drawer is one piece
    # The voxels alone: the decoy lands every cell, the push-in only front and bottom.
    blind = split.best_slide(mask)
    assert np.linalg.norm(blind - DECOY) < 1.5 * VOXEL, blind
    split.on_surface = HiddenInterior(target)
    split.surface_tolerance = 2 * VOXEL
    seen = split.best_slide(mask)
    assert np.linalg.norm(seen - PUSH) < 1.5 * VOXEL, seen


def test_a_deep_drawer_pushed_in_claims_the_change_its_front_shows():
    """A drawer twice as deep as wide pushed in by 0.6: the closed state shows only its front,
    and another part's panel changes elsewhere (the target's change is mostly not the
    drawer's). Counted over all its cells the true slide covers too little of the change to
    claim a part; over the cells the target images can see where it puts them, the front,
    it covers most of it."""
    rng = np.random.default_rng(0)
    push = np.array([0.0, 0.6, 0.0])

    def deep_drawer(offset):
        return box_surface([0, 0, 0], [0.4, 0.8, 0.2], 4000, rng, skip=(5,)) + offset

    pushed = deep_drawer(push)
    panel = box_surface([1.0, 0.0, 0.0], [1.05, 1.5, 1.5], 8000, rng)
    target = np.concatenate([pushed[pushed[:, 1] <= push[1] + 1e-9], panel])

    def in_sight(points, tolerance):
        on = cKDTree(target).query(points)[0] < tolerance
        inside = (points[:, 1] > push[1] + tolerance) & (points[:, 0] < 0.45)
        return on, ~on & ~inside

    split = split_static_dynamic(deep_drawer(np.zeros(3)), target, VOXEL)
    cells = np.argwhere(split.labels[0] > 0)
    slide = split.score(cells, "slide", np.eye(3), push)
    assert slide.trusted and slide.explained < DETECT_OVERLAP, slide
    assert change_in_sight(split, cells, slide) == 0.0  # no images, nothing in sight
    split.on_surface, split.surface_tolerance = in_sight, 2 * VOXEL
    shown = change_in_sight(split, cells, slide)
    assert shown >= 2 * DETECT_OVERLAP, shown
    # Nothing in sight claims nothing.
    split.on_surface = lambda p, t: (np.zeros(len(p), bool),) * 2
    assert change_in_sight(split, cells, slide) == 0.0


def two_drawers_one_column(travel=0.35, n=16000, seed=3):
    """A cabinet with a drawer above another, both pulled out by `travel` along -y."""
    rng = np.random.default_rng(seed)

    def state(pulled):
        body = box_surface([0, 0, 0], [1, 1, 1.2], int(0.5 * n), rng, skip=(FRONT,))
        shift = np.array([0.0, -travel if pulled else 0.0, 0.0])
        low = box_surface([0.05, -0.02, 0.05], [0.95, 0.9, 0.5], int(0.25 * n), rng, skip=(5,))
        high = box_surface([0.05, -0.02, 0.65], [0.95, 0.9, 1.1], int(0.25 * n), rng, skip=(5,))
        return np.concatenate([body, low + shift, high + shift])

    return state(False), state(True)


def test_drawers_of_one_column_with_one_travel_stay_two_parts():
    closed, pulled = two_drawers_one_column()
    result = coarse_init(closed, pulled)
    assert result.num_parts == 3, result.notes
    for rot, trans in result.motions:
        want = np.array([0.0, -0.35, 0.0]) * (1 if result.canonical == "start" else -1)
        assert np.allclose(rot, np.eye(3), atol=1e-6)
        assert np.linalg.norm(trans - want) < 1.5 * result.voxel_size, (trans, result.notes)


def mirrored_fronts(seed=0):
    """Two drawer fronts side by side (x in [-0.5, -0.1] and [0.1, 0.5]), pulled 0.1 out
    (-y) in the canonical state and pushed in (y = 0) in the target, before a static back
    wall. A half turn about the vertical line x = 0, y = -0.05 puts the right front exactly
    where the left one ends: it lands as well as the right front's own slide."""
    rng = np.random.default_rng(seed)

    def front(x0, y, n=2500):
        return box_surface([x0, y - 0.02, 0.0], [x0 + 0.4, y, 0.3], n, rng)

    wall = box_surface([-0.6, 0.3, -0.1], [0.6, 0.32, 0.4], 4000, rng)
    canon = [front(-0.5, -0.1), front(0.1, -0.1)]
    target = np.concatenate([front(-0.5, 0.0), front(0.1, 0.0), wall])
    split = split_static_dynamic(np.concatenate([*canon, wall]), target, VOXEL, 1)
    return split, [split.grid.voxel_of(c) for c in canon]


def test_a_hinge_that_lands_only_on_claimed_matter_goes_behind_the_slide():
    split, (left, right) = mirrored_fronts()
    slide = np.array([0.0, 0.1, 0.0])
    rot, trans = hinge_motion([0, 0, 1], [0.0, -0.05, 0.0], 180.0)
    fold = split.score(right, "hinge", rot, trans)
    pull = split.score(right, "slide", np.eye(3), slide)
    assert fold.landed >= pull.landed - 0.1  # a near-tie on all the target's matter
    hyps = [fold, pull]
    nothing = np.zeros(split.grid.shape, dtype=bool)
    assert _first_on_free_matter(split, nothing, right, hyps) == (hyps, None)
    # The left front, a part already, lands where the fold puts the right one.
    claimed = split.landing_cells(left, Hypothesis("slide", np.eye(3), slide))
    ordered, free = _first_on_free_matter(split, claimed, right, hyps)
    assert ordered == [pull, fold] and free is not None and free < 0.2
    # A hinge that lands on free matter keeps its place.
    other = split.landing_cells(left, Hypothesis("slide", np.eye(3), -slide))
    assert _first_on_free_matter(split, other, right, hyps) == (hyps, None)


def reading(kind: str, landed: float, explained: float) -> Hypothesis:
    return Hypothesis(kind, np.eye(3), np.zeros(3), landed, explained)


@pytest.mark.parametrize("swap", [False, True])
def test_near_tie_order_puts_a_slide_first_only_when_it_covers_clearly_more(swap):
    """The readings stage 2 logged on real objects: a drawer (its slide covering 0.18 more than
    a turn landing about as well) starts as a slide; a door opened 180° (its slide covering 0.07
    more) and a door's fragment (its hinge explaining too little to claim a part) start as
    hinges. The order does not depend on which of the two ranked first."""
    cases = [
        (reading("hinge", 0.95, 0.56), reading("slide", 0.97, 0.74), "slide"),
        (reading("hinge", 0.91, 0.78), reading("slide", 0.99, 0.85), "hinge"),
        (reading("hinge", 0.93, 0.13), reading("slide", 1.00, 0.87), "hinge"),
    ]
    for hinge, slide, first in cases:
        pair = (slide, hinge) if swap else (hinge, slide)
        ordered = near_tie_order(*pair)
        assert [h.kind for h in ordered] == [first, "hinge" if first == "slide" else "slide"]
        assert {id(h) for h in ordered} == {id(hinge), id(slide)}
