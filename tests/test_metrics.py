"""Metric definitions on hand-computed cases (docs/evaluation.md)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh

from gear.metrics import (
    Joint,
    axis_angle_error,
    chamfer,
    joint_errors,
    line_distance,
    match_parts,
    part_iou,
    psnr,
    rotation_angle_deg,
    rotation_matrix,
    same_motion_groups,
    untie_same_motions,
)


def gt_joint(kind, axis, origin, amount):
    """Stands in for gear.data.GtJoint: the metrics read it by attribute."""
    return SimpleNamespace(
        type=kind, axis=np.asarray(axis, float), origin=np.asarray(origin, float), amount=amount
    )


def revolute(axis, origin, angle):
    return {"type": "revolute", "axis": list(axis), "origin": list(origin), "angle_deg": angle}


def prismatic(axis, distance, origin=(0, 0, 0)):
    return {"type": "prismatic", "axis": list(axis), "origin": list(origin), "distance": distance}


# --- joints ----------------------------------------------------------------------------------

def test_axis_angle_folds_opposite_directions():
    tilt = np.deg2rad(30.0)
    assert axis_angle_error([0, 0, 1], [0, math.sin(tilt), math.cos(tilt)]) == pytest.approx(30.0)
    # The opposite direction is the same line: 150 degrees folds to 30.
    assert axis_angle_error([0, 0, 1], [0, -math.sin(tilt), -math.cos(tilt)]) == pytest.approx(30.0)
    assert axis_angle_error([1, 0, 0], [0, 5, 0]) == pytest.approx(90.0)  # unnormalised input


def test_line_distance_parallel_skew_intersecting():
    # Parallel along z, offset (3, 4) in the xy-plane: distance 5, whatever the origins' z.
    assert line_distance([0, 0, 0], [0, 0, 1], [3, 4, 7], [0, 0, -2]) == pytest.approx(5.0)
    # Skew: x-axis and a line along y through (0, 0, 2): common perpendicular of length 2.
    assert line_distance([5, 0, 0], [1, 0, 0], [0, -3, 2], [0, 1, 0]) == pytest.approx(2.0)
    # Intersecting at (1, 1, 1).
    d = line_distance([0, 0, 0], [1, 1, 1], [1, 1, 0], [0, 0, 1])
    assert d == pytest.approx(0.0, abs=1e-12)
    # Nearly parallel (1e-10 rad) must not blow up: close to the parallel answer.
    d = line_distance([0, 0, 0], [0, 0, 1], [1, 0, 0], [1e-10, 0, 1])
    assert d == pytest.approx(1.0, abs=1e-6)


def test_rotation_helpers_roundtrip():
    r = rotation_matrix([1, 2, 3], 73.0)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0)
    assert rotation_angle_deg(r) == pytest.approx(73.0)
    # Right-handed: +90 about z maps x to y.
    np.testing.assert_allclose(rotation_matrix([0, 0, 1], 90) @ [1, 0, 0], [0, 1, 0], atol=1e-12)


def test_known_axis_offset_and_rotation_error():
    gt = gt_joint("revolute", [0, 0, 1], [0.5, 0, 0], 60.0)
    # Same direction, pivot moved 0.03 perpendicular to the axis (plus a shift along it, which
    # does not move the line), angle 55 instead of 60.
    pred = revolute([0, 0, 1], [0.5, 0.03, 0.9], 55.0)
    e = joint_errors(pred, gt)
    assert e["axis_ang"] == pytest.approx(0.0, abs=1e-6)
    assert e["axis_pos"] == pytest.approx(0.3)  # 0.03 x 10
    assert e["geo_dist"] == pytest.approx(5.0)
    assert e["type_match"]


def test_geo_dist_is_rotation_angle_of_relative_rotation():
    # Axis tilted by 10 degrees, same angle 90: the relative rotation angle from its trace,
    # computed independently here with quaternions: q = (cos45, sin45·a).
    tilt = np.deg2rad(10)
    a1, a2 = np.array([0, 0, 1.0]), np.array([0, math.sin(tilt), math.cos(tilt)])
    q1 = np.r_[math.cos(np.pi / 4), math.sin(np.pi / 4) * a1]
    q2 = np.r_[math.cos(np.pi / 4), math.sin(np.pi / 4) * a2]
    # angle of q1 * conj(q2) = 2 acos(|<q1, q2>|)
    expected = np.rad2deg(2 * math.acos(min(1.0, abs(float(q1 @ q2)))))
    e = joint_errors(revolute(a2, [0, 0, 0], 90.0), gt_joint("revolute", a1, [0, 0, 0], 90.0))
    assert e["axis_ang"] == pytest.approx(10.0)
    assert e["geo_dist"] == pytest.approx(expected, abs=1e-9)
    # A flipped axis with a negated angle is the same motion: no error at all.
    e = joint_errors(revolute(-a1, [0, 0, 0], -90.0), gt_joint("revolute", a1, [0, 0, 0], 90.0))
    assert e["geo_dist"] == pytest.approx(0.0, abs=1e-6)
    assert e["axis_ang"] == pytest.approx(0.0, abs=1e-6)


def test_prismatic_errors():
    gt = gt_joint("prismatic", [1, 0, 0], [9, 9, 9], 0.4)
    e = joint_errors(prismatic([1, 0, 0], 0.37, origin=[0, 5, 0]), gt)
    assert e["axis_pos"] == 0.0  # prismatic axes have no position
    assert e["geo_dist"] == pytest.approx(0.03)
    # Direction off by 90 degrees: |(0, .4, 0) - (.4, 0, 0)| = .4·sqrt2.
    e = joint_errors(prismatic([0, 1, 0], 0.4), gt)
    assert e["axis_ang"] == pytest.approx(90.0)
    assert e["geo_dist"] == pytest.approx(0.4 * math.sqrt(2))


def test_type_mismatch_counts_whole_gt_motion():
    e = joint_errors(prismatic([0, 0, 1], 0.2), gt_joint("revolute", [0, 0, 1], [0, 0, 0], 40.0))
    assert not e["type_match"]
    assert e["geo_dist"] == pytest.approx(40.0)  # R_pred = I
    gt = gt_joint("prismatic", [1, 0, 0], [0, 0, 0], 0.5)
    e = joint_errors(revolute([1, 0, 0], [0, 0, 0], 30), gt)
    assert e["geo_dist"] == pytest.approx(0.5)  # t_pred = 0


def test_bad_joint_input_is_named():
    gt = gt_joint("revolute", [0, 0, 1], [0, 0, 0], 1.0)
    with pytest.raises(ValueError, match=r"pred\.axis"):
        joint_errors(revolute([0, 0, 0], [0, 0, 0], 10), gt)
    with pytest.raises(ValueError, match="type"):
        Joint.from_any({"type": "hinge", "axis": [0, 0, 1]})
    with pytest.raises(ValueError, match="angle_deg"):
        Joint.from_any({"type": "revolute", "axis": [0, 0, 1], "angle_deg": float("nan")})


# --- matching --------------------------------------------------------------------------------

def test_match_finds_permutation():
    gts = [
        gt_joint("revolute", [0, 0, 1], [1, 0, 0], 90.0),
        gt_joint("prismatic", [1, 0, 0], [0, 0, 0], 0.3),
        gt_joint("revolute", [0, 1, 0], [0, 0, 2], 45.0),
    ]
    # Predictions in a shuffled order, each slightly off its true joint.
    preds = [
        revolute([0, 1, 0], [0.01, 0, 2], 44.0),  # -> gt 2
        revolute([0, 0, 1], [1, 0.02, 0], 88.0),  # -> gt 0
        prismatic([1, 0, 0], 0.29),  # -> gt 1
    ]
    m = match_parts(preds, gts)
    assert m.pairs == [(0, 1), (1, 2), (2, 0)]
    assert not m.type_mismatches and not m.count_mismatch
    assert m.errors[0]["geo_dist"] == pytest.approx(2.0)
    assert m.errors[0]["axis_pos"] == pytest.approx(0.2)
    assert m.errors[2]["axis_pos"] == pytest.approx(0.1)


def test_match_prefers_type_consistency_over_smaller_error():
    gts = [gt_joint("revolute", [0, 0, 1], [0, 0, 0], 5.0),
           gt_joint("prismatic", [0, 0, 1], [0, 0, 0], 0.5)]
    # Pairing pred 0 (revolute, 80 deg off) with gt 0 costs more error than crossing the pairs,
    # but crossing would disagree in type twice: the type-consistent assignment must win.
    preds = [revolute([0, 0, 1], [0, 0, 0], 85.0), prismatic([0, 0, 1], 0.5)]
    m = match_parts(preds, gts)
    assert m.pairs == [(0, 0), (1, 1)]
    assert m.type_mismatches == []


def test_type_and_count_mismatches_reported():
    gts = [gt_joint("revolute", [0, 0, 1], [0, 0, 0], 90.0),
           gt_joint("revolute", [1, 0, 0], [0, 0, 0], 30.0)]
    preds = [prismatic([0, 0, 1], 0.1)]
    m = match_parts(preds, gts)
    assert m.count_mismatch
    assert m.pairs == [(0, 0)]  # the closer GT joint by summed error
    assert m.type_mismatches == [(0, 0)]
    assert m.unmatched_gt == [1] and m.unmatched_pred == []
    # Three predictions for one GT joint: the revolute one 10 degrees off wins over a revolute
    # one about the wrong axis (>= 90 degrees of error) and the prismatic one (wrong type).
    extra = match_parts([*preds, revolute([0, 0, 1], [0, 0, 0], 80.0),
                         revolute([0, 1, 0], [0, 0, 0], 1.0)], gts[:1])
    assert extra.pairs == [(0, 1)]
    assert extra.errors[0]["geo_dist"] == pytest.approx(10.0)
    assert extra.unmatched_pred == [0, 2] and extra.type_mismatches == []


def test_predictions_of_one_motion_are_assigned_by_where_the_parts_are():
    """Two drawers of a column pulled by the same travel are one motion: the joint errors
    cannot tell them apart, the parts' centres do. A third joint, and groups whose centres
    are missing, stay as matched."""
    gts = [gt_joint("prismatic", [0, -1, 0], [0, 0, 0.2], 0.25),
           gt_joint("revolute", [0, 0, 1], [0.5, 0, 0], 40.0),
           gt_joint("prismatic", [0, -1, 0], [0, 0, 0.6], 0.25)]
    assert same_motion_groups(gts) == [[0, 2]]
    # The upper drawer's prediction slides 0.249 (closer to both truths than 0.2535), so the
    # joint errors match it to the lower drawer.
    preds = [prismatic([0, -1, 0], 0.2535), revolute([0, 0, 1], [0.5, 0, 0], 40.5),
             prismatic([0, -1, 0], 0.249)]
    m = match_parts(preds, gts)
    assert m.pairs == [(0, 2), (1, 1), (2, 0)]
    gt_centres = {0: np.array([0, -0.1, 0.2]), 1: np.array([0.3, 0, 0.4]),
                  2: np.array([0, -0.1, 0.6])}
    pred_centres = {0: np.array([0, -0.1, 0.21]), 1: np.array([0.3, 0, 0.4]),
                    2: np.array([0, -0.1, 0.59])}
    untied = untie_same_motions(m, preds, gts, pred_centres, gt_centres)
    assert untied.pairs == [(0, 0), (1, 1), (2, 2)]
    assert untied.errors[0]["geo_dist"] == pytest.approx(0.0035)
    assert untied.errors[2]["geo_dist"] == pytest.approx(0.001)
    assert untied.errors[1] == m.errors[1]
    assert untie_same_motions(m, preds, gts, {0: pred_centres[0]}, gt_centres) is m
    # Different travels are different motions: nothing to untie.
    gts[2] = gt_joint("prismatic", [0, -1, 0], [0, 0, 0.6], 0.12)
    assert same_motion_groups(gts) == []


def test_match_with_nothing_predicted():
    m = match_parts([], [gt_joint("revolute", [0, 0, 1], [0, 0, 0], 90.0)])
    assert m.pairs == [] and m.unmatched_gt == [0]


# --- Chamfer ---------------------------------------------------------------------------------

def unit_square(z: float) -> trimesh.Trimesh:
    v = np.array([[0, 0, z], [1, 0, z], [1, 1, z], [0, 1, z]], float)
    return trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], process=False)


def test_chamfer_parallel_squares():
    # Squares offset by d along their normal. Every nearest neighbour lies on the other square,
    # so each squared distance is d² + r², r the in-plane distance to the nearest sample:
    #   CD = 1000·(2d² + E[r²]_ab + E[r²]_ba).
    # For n uniform samples on unit area E[r²] = 1/(πn) = 3.18e-5 (Poisson points), a little
    # more near the square's edges: the sampling floor is 1000·2/(πn) ≈ 0.064, about +20% at
    # the border. We bound it in [0.05, 0.09] and check it against two coincident squares.
    n, d = 10000, 0.1
    floor = chamfer(unit_square(0.0), unit_square(0.0), n=n, seed=3)
    assert 0.05 < floor < 0.09
    cd = chamfer(unit_square(0.0), unit_square(d), n=n, seed=3)
    assert cd == pytest.approx(2000 * d * d + floor, abs=0.01)
    assert 20.05 < cd < 20.09
    # Same seed, same number.
    assert chamfer(unit_square(0.0), unit_square(d), n=n, seed=3) == cd


def test_chamfer_rejects_empty_mesh():
    with pytest.raises(ValueError, match="empty"):
        chamfer(trimesh.Trimesh(), unit_square(0.0))


# --- IoU / PSNR ------------------------------------------------------------------------------

def test_part_iou_hand_counted():
    gt = np.full((4, 4), 255, np.uint8)
    gt[:2, :] = 0  # static: 8 px
    gt[2:, :2] = 1  # part 1: 4 px
    pred = gt.copy()
    pred[2, 2] = 1  # part 1 spills onto background: I=4, U=5
    pred[0, 0] = 1  # and takes one static pixel: static I=7, U=8; part 1 I=4, U=6
    out = part_iou(pred, gt)
    assert out["per_part"] == {0: pytest.approx(7 / 8), 1: pytest.approx(4 / 6)}
    assert out["mean"] == pytest.approx((7 / 8 + 4 / 6) / 2)
    # Pooled over two images: counts add up before dividing.
    pooled = part_iou([pred, gt], [gt, gt])
    assert pooled["per_part"][1] == pytest.approx((4 + 4) / (6 + 4))


def test_psnr_known_values():
    a = np.zeros((8, 8, 3))
    b = a + 0.1  # mse 0.01 -> 20 dB
    assert psnr(a, b) == pytest.approx(20.0)
    mask = np.zeros((8, 8), bool)
    mask[:4] = True
    c = b.copy()
    c[4:] = 1.0  # differences outside the mask are ignored
    assert psnr(a, c, mask=mask) == pytest.approx(20.0)
    assert psnr(a, a) == 100.0  # finite cap, never inf
    with pytest.raises(ValueError, match="shape"):
        psnr(a, a[:4])
