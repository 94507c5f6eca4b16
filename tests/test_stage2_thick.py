"""Stage 2's hinge of a thick piece: a lid that is a plane by its aspect but no slab, whose
least-squares normal is not square to its hinge, so that the plane intersections miss the
hinge and the local search of the surface fit must find it."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gear.geometry import NearestTree
from gear.pipeline.stage2.hypotheses import axis_of, fit_plane, refine_turn, rotation_about_line
from gear.pipeline.stage2.voxels import Scale, init_motion, split_static_dynamic
from test_coarse import box_surface

HINGE_AXIS = np.array([0.0, 1.0, 0.0])
HINGE_PIVOT = np.array([0.0, 0.1, 0.1])


def lid_scene(tilt_deg: float, angle_deg: float, n: int = 20000, seed: int = 0):
    """A base box and, on it, a thick lid (0.38 x 0.21 x 0.15) whose cross-section is tilted
    by `tilt_deg` about its length, turned by `angle_deg` about the base's back top edge in the
    second state; each state sampled independently. Returns (start, end, rotation, translation)."""
    rng = np.random.default_rng(seed)
    tilt = Rotation.from_euler("x", tilt_deg, degrees=True).as_matrix()

    def lid():
        shape = box_surface([0, -0.105, -0.075], [0.38, 0.105, 0.075], n, rng)
        return shape @ tilt.T + np.array([0.0, 0.1, 0.18])

    def base():
        return box_surface([0, 0, 0], [0.4, 0.2, 0.1], n, rng)

    rot, trans = rotation_about_line(HINGE_AXIS, HINGE_PIVOT, -np.deg2rad(angle_deg))
    start = np.concatenate([base(), lid()])
    end = np.concatenate([base(), lid() @ rot.T + trans])
    return start, end, rot, trans


def axis_error_deg(rot: np.ndarray) -> float:
    return float(np.degrees(np.arccos(min(1.0, abs(float(axis_of(rot) @ HINGE_AXIS))))))


@pytest.mark.parametrize(("tilt_deg", "angle_deg"), [(10, 40), (20, 40), (10, 90)])
def test_a_thick_lids_hinge_is_searched_from_the_plane_intersections(tilt_deg, angle_deg):
    start, end, rot, trans = lid_scene(tilt_deg, angle_deg)
    voxel = Scale.of(np.concatenate([start, end])).voxel_size(single_part=False)
    split = split_static_dynamic(start, end, voxel)
    labels = split.labels[0]
    points = start[split.grid.point_labels(start, labels) == 1]
    plane = fit_plane(points)
    assert plane.is_plane and not plane.is_flat and not plane.is_rod  # the case in question
    # Without the search (sweep=False), the plane intersections give a hinge well off...
    unrefined = init_motion(split, labels == 1, points, sweep=False)[0]
    assert unrefined.kind == "hinge" and axis_error_deg(unrefined.rot) > 5.0
    # ... with it, the hinge: the axis, and every point of the lid where the truth puts it
    # (within a fifth of a voxel; the lid is 0.38 long).
    hinge = init_motion(split, labels == 1, points)[0]
    assert hinge.kind == "hinge" and hinge.landed > unrefined.landed
    assert axis_error_deg(hinge.rot) < 0.5
    moved = points @ hinge.rot.T + hinge.trans
    assert np.linalg.norm(moved - (points @ rot.T + trans), axis=1).max() < 0.2 * voxel


def test_refine_turn_stays_within_its_tilt_bound():
    """Pulled towards a turn about an axis square to its own (beyond the thick-piece search's
    30-degree tilt bound), the search leans its axis to the bound and no further."""
    rng = np.random.default_rng(3)
    piece = box_surface([0, 0, 0], [0.4, 0.2, 0.15], 4000, rng)
    far_rot, far_trans = rotation_about_line(np.array([1.0, 0, 0]), HINGE_PIVOT, 0.8)
    target = box_surface([0, 0, 0], [0.4, 0.2, 0.15], 4000, rng) @ far_rot.T + far_trans
    tree = NearestTree(target)

    def fit(points, r, t, width=None):
        dist, _ = tree.query(points @ np.asarray(r).T + np.asarray(t), k=1)
        return float(np.exp(-((dist / (width or 0.01)) ** 2)).mean())

    start_rot, start_trans = rotation_about_line(HINGE_AXIS, HINGE_PIVOT, 0.3)
    rot, trans = refine_turn(piece, start_rot, start_trans, 0.4, fit)
    assert fit(piece, rot, trans) > fit(piece, start_rot, start_trans)
    tilt = np.degrees(np.arccos(np.clip(abs(axis_of(rot) @ HINGE_AXIS), -1, 1)))
    assert 25.0 < tilt <= 30.0 + 1e-6
