"""Hinges landed on the target's own reconstruction: the images leave a turned plate's pose
loose along its own plane (a closed door shifted across the cabinet's front, towards its
neighbour, looks much the same), and the motion steps train it together with Gaussians that
follow it, so a door's angle and pivot can settle a few degrees and centimetres off while
both states' images are rendered well. The target state's stage-1 model was trained on its
images alone, and its surfaces hold what the images pin down: its edges, its thickness. At
the end of stage 3 each hinge is searched locally (axis tilt, pivot, angle) for the turn that
lays its part's centres on that model's (hypotheses.refine_turn, coarse to fine), and kept
when it lands them clearly closer and the images do not see it clearly worse
(docs/method.md, "Hinges landed on the target's reconstruction")."""

from __future__ import annotations

import math

import numpy as np
import torch

from gear.geometry import NearestTree, box_diagonal
from gear.kinematics import dq_from_rt, quat_from_matrix, quat_to_matrix
from gear.pipeline.stage2.frame import MIN_CENTRES
from gear.pipeline.stage2.hypotheses import (
    TurnSearch,
    axis_angle_of,
    fit_plane,
    pivot_near,
    refine_turn,
    surface_fit,
)
from gear.pipeline.stage3.joint_types import image_loss
from gear.pipeline.stage3.joints import SurfaceCentres, part_motion
from gear.pipeline.stage3.rods import round_rod
from gear.pipeline.stage3.shared import RefineState
from gear.pipeline.stage3.square_axes import SQUARE_MARGIN, with_part
from gear.splats import Gaussians

# The local search, in fractions of the object's extent (the diagonal of its centres' box):
# real sink-cabinet doors that stage 3 left 3.6 and 5.4 degrees short, their hinge lines 0.05
# and 0.08 off (of an extent of 2.3), came within 0.4 and 0.8 degrees of the true angles with
# these bounds (the second line within 0.009, the first 0.075), and a stapler's lid, squared
# onto a base frame 2.3 degrees off, within 0.8 degrees. The finest width is about a voxel of
# stage 2's grid: the two states' models agree to about that. Every width is at least twice
# the target's median centre spacing.
LANDING_SEARCH = TurnSearch(tilt_deg=5.0, pivot=1 / 15, angle_deg=10.0,
                            widths=(1 / 50, 1 / 100, 1 / 200))
# The landed turn must lay the part's centres at least this much closer (relative gain of the
# surface fit at the finest width): below it the search follows the two models' noise. At
# fast, the sink cabinet's doors gained 63 % and 76 %, the stapler's lid 18 %; the built-in
# fridge's door, 0.12 degrees off, 9.7 % for a turn 0.23 degrees smaller, and storage7's doors
# 6 % and 8 %; a door of a 40-pixel test model, whose search ran to its tilt bound, 6 %...
MIN_LANDING_GAIN = 0.15
# ... and stop short of the search's tilt and angle bounds (this share of them): a turn that
# runs to the edge of the search is no local correction, but the pull of a hazy model.
AT_BOUND = 0.95
# The images may see the landed turn worse only in proportion to what the fit gains: by at
# most this share of the gain, and never more than SQUARE_MARGIN. At fast, the sink cabinet's
# doors gained 63 % and 76 % for images 3.0 % and 2.1 % worse, and landed within a degree of
# the truth; a real wall cabinet's door, trained 0.45 degrees off, gained 21 % for images
# 4.8 % worse and landed 2.5 degrees off.
IMAGE_COST_PER_GAIN = 0.1


def land_hinges(state: RefineState, target: Gaussians) -> list[dict]:
    """Refines every hinge of `state` by landing its part's opaque canonical centres on the
    opaque centres of `target` (the target state's stage-1 model), and keeps the landed turn
    where the fit gains MIN_LANDING_GAIN, the search stopped short of its bounds and the images
    see it worse than the current motion by no more than IMAGE_COST_PER_GAIN of that gain
    (SQUARE_MARGIN at most). Slides and round rods are left as they are (a slide's travel is
    what the images see best; a rod keeps its swing).
    Returns a record per hinge tried: the fits, how far the axis, pivot and angle moved, both
    losses (when scored) and whether it was kept."""
    g, motion = state.gaussians, state.motion
    surface = SurfaceCentres(g)
    target_centres = SurfaceCentres(target).all().numpy()
    centres = surface.all().numpy()
    if len(target_centres) < MIN_CENTRES or len(centres) == 0:
        return []
    extent = box_diagonal(centres)
    tree = NearestTree(target_centres)
    # No width below twice the target's centre spacing: a sparse model (a short run's) would
    # show nothing landing at all.
    spacing = float(np.median(tree.query(target_centres, k=2)[0][:, 1]))
    floor = max(extent * LANDING_SEARCH.widths[-1], 2 * spacing)

    def fit(points: np.ndarray, rot: np.ndarray, trans: np.ndarray,
            width: float | None = None) -> float:
        return surface_fit(tree, points, rot, trans, max(width or floor, floor))

    records = []
    current = None  # the image loss of `motion`, once a hinge is scored
    for k in state.live_parts():
        points = surface.of_part(k).numpy()
        # A round rod's twist about its length moves its surface as little as the images
        # see of it: it keeps the swing untwist_rods gave it.
        if bool(motion.prismatic[k]) or len(points) < MIN_CENTRES \
                or round_rod(fit_plane(points)):
            continue
        quat, trans = part_motion(motion, k)
        rot, trans = quat_to_matrix(quat).numpy(), trans.numpy()
        landed_rot, landed_trans = refine_turn(points, rot, trans, extent, fit, LANDING_SEARCH)
        if not (np.isfinite(landed_rot).all() and np.isfinite(landed_trans).all()):
            continue
        before, after = fit(points, rot, trans), fit(points, landed_rot, landed_trans)
        record = {"part": k, "fit": round(before, 4), "landed_fit": round(after, 4),
                  **_moved((rot, trans), (landed_rot, landed_trans), points.mean(axis=0)),
                  "kept": False}
        records.append(record)
        # A part none of whose centres lay on the target (fit 0) gains without bound.
        gain = after / before - 1 if before > 0 else math.inf
        if gain < MIN_LANDING_GAIN or _at_bounds(record):
            continue
        landed = (quat_from_matrix(torch.as_tensor(landed_rot)), torch.as_tensor(landed_trans))
        if current is None:
            current = image_loss(state, motion)
        landed_loss = image_loss(state, with_part(motion, k, landed, prismatic=False))
        allowed = min(SQUARE_MARGIN, IMAGE_COST_PER_GAIN * gain)
        record.update(loss=current, landed_loss=landed_loss,
                      kept=landed_loss <= current * (1 + allowed))
        if record["kept"]:
            motion.set_part(k, *dq_from_rt(*landed), prismatic=False)
            current = landed_loss
    return records


def _moved(turn: tuple[np.ndarray, np.ndarray], landed: tuple[np.ndarray, np.ndarray],
           centroid: np.ndarray) -> dict:
    """How far the landed turn moved from `turn` (each (R, t)): its axis and angle (degrees)
    and its axis line where it passes nearest the part's `centroid`."""
    (axis, angle), (new_axis, new_angle) = axis_angle_of(turn[0]), axis_angle_of(landed[0])
    shift = pivot_near(*landed, centroid) - pivot_near(*turn, centroid)
    return {"axis_moved_deg": round(math.degrees(math.acos(min(1.0, abs(axis @ new_axis)))), 4),
            "angle_moved_deg": round(math.degrees(abs(new_angle) - abs(angle)), 4),
            "pivot_moved": round(float(np.linalg.norm(shift)), 5)}


def _at_bounds(moved: dict) -> bool:
    """Whether a landed turn (its `_moved` record) reached AT_BOUND of the search's tilt or
    angle bound."""
    return (moved["axis_moved_deg"] >= AT_BOUND * LANDING_SEARCH.tilt_deg
            or abs(moved["angle_moved_deg"]) >= AT_BOUND * LANDING_SEARCH.angle_deg)
