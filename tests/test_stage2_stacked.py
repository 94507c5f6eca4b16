"""Stage 2's hand-off of doors that may be stacked on one hinge line
(pipeline.stage2.stacked): a hinged part tall along its axis enters stage 3 cut in two across
the axis at its median, with the same motion; short or thin parts, parts hardly turned and
one slab (its halves' faces parallel in both states) are left whole."""

import numpy as np
import pytest

from gear.metrics import rotation_matrix
from gear.pipeline.stage2.parts import seed_logits
from gear.pipeline.stage2.stacked import (
    MIN_HALVES_TILT_DEG,
    MIN_TURN_DEG,
    split_stacked,
    stacked_cut,
)

# Stage 2's voxel for these slabs (a part is one body at it: 2000 centres over 0.5 x 1.7).
VOXEL = 0.05


def slab(width: float, height: float, n: int = 2000, seed: int = 0) -> np.ndarray:
    """Centres of a door-like slab: `width` along x, `height` along z, 0.02 thick."""
    rng = np.random.default_rng(seed)
    return rng.uniform([0.0, 0.0, 0.0], [width, 0.02, height], size=(n, 3))


def turn(deg: float, axis=(0.0, 0.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of a turn by `deg` about a line along `axis` through the origin (the hinge)."""
    return rotation_matrix(np.asarray(axis), deg), np.zeros(3)


def stacked_pair(lower_deg: float, upper_deg: float, n: int = 2000) -> np.ndarray:
    """Centres of two doors 0.5 wide and 0.85 tall stacked on one hinge line (z through the
    origin), the lower turned by `lower_deg` and the upper by `upper_deg`."""
    lower = slab(0.5, 0.85, n // 2) @ turn(lower_deg)[0].T
    upper = (slab(0.5, 0.85, n // 2, seed=1) + np.array([0.0, 0.0, 0.85])) @ turn(upper_deg)[0].T
    return np.concatenate([lower, upper])


def test_a_tall_turned_slab_is_cut_at_its_median_across_the_axis():
    door = slab(0.5, 1.7)
    beyond = stacked_cut(door, turn(35.0), VOXEL)
    assert beyond is not None
    assert beyond.sum() == len(door) // 2
    # the cut runs across the hinge axis (z): every centre beyond lies above every other
    assert door[beyond, 2].min() >= door[~beyond, 2].max()


@pytest.mark.parametrize("shape, motion", [
    ((0.5, 0.6), turn(35.0)),  # about as wide as tall: one door
    ((1.2, 0.3), turn(60.0)),  # a lid, long across its hinge
    ((0.5, 1.7), turn(0.5 * MIN_TURN_DEG)),  # hardly turned
    ((0.5, 1.7), turn(35.0, axis=(1.0, 0.0, 0.0))),  # the hinge along its width
])
def test_short_or_barely_turned_parts_stay_whole(shape, motion):
    assert stacked_cut(slab(*shape), motion, VOXEL) is None


def test_a_stray_chunk_across_the_cabinet_does_not_hide_a_tall_door():
    door = slab(0.5, 1.7)
    # 13 % of the part 1.4 across, as a real upper cabinet's pair of doors came from stage 2
    chunk = slab(0.3, 0.4, n=300, seed=3) + np.array([1.4, 0.0, 0.6])
    means = np.concatenate([door, chunk])
    beyond = stacked_cut(means, turn(35.0), VOXEL)
    assert beyond is not None
    # the cut lies at the door's median across its axis: half of the door beyond it
    assert beyond[: len(door)].sum() == len(door) // 2


def test_too_few_gaussians_stay_whole():
    assert stacked_cut(slab(0.5, 1.7, n=60), turn(35.0), VOXEL) is None


def test_split_stacked_seeds_the_new_part_and_keeps_the_rest():
    door = stacked_pair(0.0, 2 * MIN_HALVES_TILT_DEG)
    drawer = slab(0.4, 0.2, seed=1) + np.array([1.0, 0.0, 0.0])
    body = slab(2.0, 2.0, n=500, seed=2) + np.array([0.0, 0.5, 0.0])
    means = np.concatenate([door, drawer, body])
    part_of = np.repeat([1, 2, 0], [len(door), len(drawer), len(body)])
    logits = seed_logits(part_of, 3)
    slide = (np.eye(3), np.array([0.0, -0.3, 0.0]))
    candidates = [[turn(35.0), slide], [slide]]
    out, out_candidates, halves, notes = split_stacked(logits, candidates, means, VOXEL)
    assert out.shape == (len(means), 4) and np.isfinite(out).all()
    assert halves == [(1, 3)]
    assert len(notes) == 1 and "part 1" in notes[0]
    assert len(out_candidates) == 3 and out_candidates[2] == candidates[0]
    owner = out.argmax(axis=1)
    door_owner = owner[: len(door)]
    assert set(door_owner.tolist()) == {1, 3} and (door_owner == 3).sum() == len(door) // 2
    assert door[door_owner == 3, 2].min() >= door[door_owner == 1, 2].max()
    # everyone else keeps their part; each half's seeded logit is a clear winner
    assert np.array_equal(owner[len(door):], part_of[len(door):])
    assert np.array_equal(out[len(door):, :3], logits[len(door):])
    top2 = np.sort(out[: len(door)], axis=1)[:, -2:]
    assert (top2[:, 1] - top2[:, 0] > 1.0).all()


def test_split_stacked_without_candidates_changes_nothing():
    logits = seed_logits(np.zeros(10, dtype=np.int64), 1)
    out, candidates, halves, notes = split_stacked(logits, [], np.zeros((10, 3)), VOXEL)
    assert np.array_equal(out, logits) and candidates == [] and halves == [] and notes == []


def door_and_body(door: np.ndarray) -> tuple[np.ndarray, np.ndarray, list]:
    """Centres of `door` (part 1, hinged) over a body (part 0), their logits and candidates."""
    body = slab(2.0, 2.0, n=500, seed=2) + np.array([0.0, 0.5, 0.0])
    means = np.concatenate([door, body])
    logits = seed_logits(np.repeat([1, 0], [len(door), len(body)]), 2)
    return means, logits, [[turn(35.0)]]


def test_one_slab_is_not_cut():
    """One door, tall along its hinge: its halves' faces are parallel in both states (the
    target's: the door turned back), so it stays one part, and a note says why."""
    door = slab(0.5, 1.7)
    means, logits, candidates = door_and_body(door)
    target = door @ turn(35.0)[0].T
    out, out_candidates, halves, notes = split_stacked(logits, candidates, means, VOXEL, target)
    assert halves == [] and out_candidates == candidates and np.array_equal(out, logits)
    assert len(notes) == 1 and "one slab" in notes[0] and "not cut" in notes[0]


@pytest.mark.parametrize("canonical, target", [
    ((30.0, 36.0), None),  # open in the canonical state: its faces show the pair
    ((0.0, 0.0), (30.0, 36.0)),  # closed there, open in the target state
])
def test_doors_stacked_at_different_angles_are_cut(canonical, target):
    """Two doors on one hinge line turned 6 degrees apart: their faces lie 6 degrees from
    parallel in the state where they are open, canonical or target, and the part is cut."""
    means, logits, candidates = door_and_body(stacked_pair(*canonical))
    target_points = None if target is None else stacked_pair(*target, n=1600)
    out, _, halves, notes = split_stacked(logits, candidates, means, VOXEL, target_points)
    assert halves == [(1, 2)] and out.shape == (len(means), 3)
    assert "tall along its hinge: one half" in notes[0]
