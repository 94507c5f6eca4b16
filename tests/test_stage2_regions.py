"""Stage 2's split of one dynamic piece by the motions its regions need
(`regions.motion_regions`): two doors on one hinge line, turned by different angles, touch
along their shared edge and form one piece; they must come out as two regions, each one
door, while two doors turned alike (one rigid motion) stay one region; and the one motion
of two pieces (`regions.one_motion`), the test by which a piece joins a part."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from gear.pipeline.stage2.hypotheses import Hypothesis
from gear.pipeline.stage2.regions import MERGE_COST, motion_regions, one_motion, refine_rigid
from gear.pipeline.stage2.voxels import Scale, init_motion, split_static_dynamic
from test_coarse import FRONT, box_surface, hinge_motion

NOISE = 0.01  # centre jitter, about a third of the voxel: a quick reconstruction's
FINE_NOISE = 0.004  # a longer-trained reconstruction's, about a seventh of the voxel


def stacked_doors(top_deg: float, bottom_deg: float, n: int = 8000, seed: int = 0,
                  noise: float = NOISE):
    """A cabinet with a top and a bottom door on one left hinge line (axis -z), opened by
    `top_deg` and `bottom_deg`; centres jittered by `noise`. Returns (closed, open, which
    door each open-state centre belongs to: 0 body, 1 top, 2 bottom)."""
    rng = np.random.default_rng(seed)
    axis, pivot = np.array([0.0, 0.0, -1.0]), np.array([0.0, -0.025, 0.0])

    def state(open_: bool) -> tuple[np.ndarray, np.ndarray]:
        body = box_surface([0, 0, 0], [1.2, 1, 1.4], int(0.5 * n), rng, skip=(FRONT,))
        top = box_surface([0, -0.04, 0.7], [1.2, -0.01, 1.4], int(0.25 * n), rng)
        bottom = box_surface([0, -0.04, 0], [1.2, -0.01, 0.7], int(0.25 * n), rng)
        if open_:
            for deg, door in ((top_deg, top), (bottom_deg, bottom)):
                rot, trans = hinge_motion(axis, pivot, deg)
                door[:] = door @ rot.T + trans
        points = np.concatenate([body, top, bottom])
        owner = np.repeat([0, 1, 2], [len(body), len(top), len(bottom)])
        return points + rng.normal(0.0, noise, points.shape), owner

    (closed, _), (opened, owner) = state(False), state(True)
    return closed, opened, owner


def regions_of_the_doors(top_deg: float, bottom_deg: float, noise: float = NOISE):
    """The regions of the open state's largest dynamic piece, each as the count of its
    centres per owner (body, top, bottom)."""
    closed, opened, owner = stacked_doors(top_deg, bottom_deg, noise=noise)
    size = Scale.of(np.concatenate([opened, closed])).voxel_size(single_part=False)
    split = split_static_dynamic(opened, closed, size)
    labels = split.grid.point_labels(opened, split.labels[0])
    mask = split.labels[0] == 1
    points, owners = opened[labels == 1], owner[labels == 1]
    # The premise: both doors are in that one piece.
    assert np.bincount(owners, minlength=3)[1:].min() > 0.3 * len(points)
    regions = motion_regions(split, mask, points, init_motion(split, mask, points))
    cells = split.grid.voxel_of(points)
    return [np.bincount(owners[r[tuple(cells.T)]], minlength=3) for r in regions]


# Real cabinets' stacked doors (cupboard, 9.4 and 4.3 degrees apart) at a fine model's noise
# are not yet cut: against the regions' coarse candidates, the pair's motion refined by ICP
# wins. Refining each region's own motion as well cuts both, but on the real asset suite's
# models it also cut single rigid parts in two (a stapler's lid at the fast profile: 4 -> 5
# stage-2 parts), so the merge cost would first have to be set from the data (docs/method.md,
# "Splitting by the motions of regions"). Near the shared hinge the two motions move centres
# by less than the noise, so some of those go to the other door.
_NOT_YET = pytest.mark.xfail(strict=True, reason="stacked doors a few degrees apart stay one "
                             "region: the merge compares a refined motion with coarse ones")


@pytest.mark.parametrize("top_deg, bottom_deg, noise, purity", [
    (40.0, 20.0, NOISE, 0.95),
    pytest.param(40.7, 31.3, FINE_NOISE, 0.95, marks=_NOT_YET),
    pytest.param(22.6, 18.3, FINE_NOISE, 0.9, marks=_NOT_YET)])
def test_doors_on_one_hinge_turned_apart_are_two_regions(top_deg, bottom_deg, noise, purity):
    regions = regions_of_the_doors(top_deg, bottom_deg, noise)
    assert len(regions) == 2
    for counts in regions:
        # Each region is one door (some centres of the other near the shared hinge).
        assert counts[1:].max() >= purity * counts.sum()
    assert {int(np.argmax(c[1:])) for c in regions} == {0, 1}


@pytest.mark.parametrize("noise", [NOISE, FINE_NOISE])
def test_doors_turned_alike_are_one_region(noise):
    regions = regions_of_the_doors(30.0, 30.0, noise)
    assert len(regions) == 1


def test_refine_rigid_recovers_a_small_offset_of_the_true_motion():
    rng = np.random.default_rng(2)
    points = box_surface([0, 0, 0], [1.0, 0.6, 0.3], 3000, rng)
    rot, trans = hinge_motion(np.array([0.0, 0.0, 1.0]), np.array([0.2, 0.1, 0.0]), 25.0)
    tree = cKDTree(points @ rot.T + trans)
    start_rot, start_trans = hinge_motion(np.array([0.0, 0.0, 1.0]),
                                          np.array([0.2, 0.1, 0.0]), 21.0)
    got_rot, got_trans = refine_rigid(points, start_rot, start_trans + 0.02, tree, 25)
    moved = points @ got_rot.T + got_trans
    truth = points @ rot.T + trans
    assert np.abs(moved - truth).max() < 5e-3
    assert np.linalg.det(got_rot) == pytest.approx(1.0)


def test_refine_rigid_stops_at_a_fixed_point_with_the_bits_of_more_steps():
    # Once a step pairs the same points with the same centres as the step before, every
    # further step repeats it: stopping there must give what any longer run gives, bit for bit.
    rng = np.random.default_rng(4)
    points = box_surface([0, 0, 0], [1.0, 0.6, 0.3], 2000, rng)
    rot, trans = hinge_motion(np.array([0.0, 0.0, 1.0]), np.array([0.2, 0.1, 0.0]), 25.0)
    tree = cKDTree(points @ rot.T + trans + rng.normal(0.0, 0.004, (len(points), 3)))
    start_rot, start_trans = hinge_motion(np.array([0.0, 0.0, 1.0]),
                                          np.array([0.2, 0.1, 0.0]), 22.0)
    short = refine_rigid(points, start_rot, start_trans, tree, 25)
    long = refine_rigid(points, start_rot, start_trans, tree, 200)
    again = refine_rigid(points, *short, tree, 1)
    for got in (long, again):
        assert np.array_equal(got[0], short[0]) and np.array_equal(got[1], short[1])


def door_pieces(top_deg: float, bottom_deg: float):
    """The split of the stacked doors (open state canonical) and each door's centres there."""
    closed, opened, owner = stacked_doors(top_deg, bottom_deg, noise=FINE_NOISE)
    split = split_static_dynamic(opened, closed,
                                 Scale.of(np.concatenate([opened, closed])).voxel_size(False))
    return split, opened[owner == 1], opened[owner == 2]


def closing(deg: float) -> Hypothesis:
    """The turn closing a door opened by `deg` about the doors' hinge line."""
    rot, trans = hinge_motion([0.0, 0.0, -1.0], [0.0, -0.025, 0.0], -deg)
    return Hypothesis("hinge", rot, trans)


def test_one_motion_of_two_pieces_read_apart_lies_between_their_readings():
    """Two doors turned alike are one rigid motion: read 6 degrees too far one way and 6 the
    other (as the pieces of a noisy model can be), one motion of both costs them no more than
    their two readings apart, and it is the true turn."""
    split, top, bottom = door_pieces(30.0, 30.0)
    extra, joint = one_motion(split, [(top, closing(36.0)), (bottom, closing(24.0))])
    assert extra <= MERGE_COST
    truth = closing(30.0)
    both = np.concatenate([top, bottom])
    apart = np.linalg.norm(both @ (joint.rot - truth.rot).T + (joint.trans - truth.trans), axis=1)
    assert apart.max() < 2 * FINE_NOISE + 0.25 * split.grid.voxel_size


def test_one_motion_of_two_doors_turned_apart_costs_more():
    split, top, bottom = door_pieces(40.0, 10.0)
    extra, _ = one_motion(split, [(top, closing(40.0)), (bottom, closing(10.0))])
    assert extra > MERGE_COST
