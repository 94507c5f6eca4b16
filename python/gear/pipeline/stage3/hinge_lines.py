"""Stage 2's hinge lines tried again: stage 2 places a hinge by laying the part's surface on
the target state's, which pins the line down well, but the motion steps then train the part
with the labels of their moment, and where those were wrong early the line can be carried
off and held there (a real sink cabinet's door: stage 2's line 0.01 off the truth, 0.15 off
after stage 3's first M-step, 0.075 at the end). At the end of stage 3 each hinge's trained
turn is tried about stage 2's line, where it passes nearest the part, and kept where the
images see it better (docs/method.md, "Stage 2's hinge lines tried again")."""

from __future__ import annotations

import numpy as np
import torch

from gear.kinematics import dq_from_rt, quat_to_matrix
from gear.pipeline.stage2.frame import MIN_CENTRES
from gear.pipeline.stage2.hypotheses import axis_angle_of, pivot_near
from gear.pipeline.stage3.joint_types import image_loss
from gear.pipeline.stage3.joints import SurfaceCentres, part_motion
from gear.pipeline.stage3.shared import RefineState
from gear.pipeline.stage3.square_axes import with_part

# A stage-2 guess turning by less than this (radians) is a slide: it has no line to offer.
MIN_TURN_RAD = 1e-3


def stage2_turn(state: RefineState, k: int) -> tuple[np.ndarray, np.ndarray] | None:
    """(R, t) of the first turn among stage 2's guesses for part k, or None when it has none
    (a part stage 2 gave only a slide, or no guesses at all)."""
    if not 0 <= k - 1 < len(state.init_motions):
        return None
    for rot, trans in state.init_motions[k - 1]:
        rot = np.asarray(rot, dtype=np.float64).reshape(3, 3)
        if abs(axis_angle_of(rot)[1]) >= MIN_TURN_RAD:
            return rot, np.asarray(trans, dtype=np.float64).reshape(3)
    return None


def recall_hinge_lines(state: RefineState) -> list[dict]:
    """Tries every hinge of `state` turned as trained about stage 2's line for it (the point
    of that line nearest the part's surface centres), keeping it where the image loss is
    lower than the current motion's. Returns a record per hinge tried: how far the line moved
    there, both losses and whether it was kept."""
    motion = state.motion
    surface = SurfaceCentres(state.gaussians)
    records = []
    current = None  # the image loss of `motion`, once a hinge is tried
    for k in state.live_parts():
        points = surface.of_part(k).numpy()
        guess = stage2_turn(state, k)
        if bool(motion.prismatic[k]) or guess is None or len(points) < MIN_CENTRES:
            continue
        quat, trans = part_motion(motion, k)
        rot = quat_to_matrix(quat).numpy()
        centroid = points.mean(axis=0)
        pivot = pivot_near(*guess, centroid)
        moved = float(np.linalg.norm(pivot - pivot_near(rot, trans.numpy(), centroid)))
        recalled = (quat, torch.as_tensor(pivot - rot @ pivot))
        if current is None:
            current = image_loss(state, motion)
        recalled_loss = image_loss(state, with_part(motion, k, recalled, prismatic=False))
        record = {"part": k, "pivot_moved": round(moved, 5), "loss": current,
                  "recalled_loss": recalled_loss, "kept": recalled_loss < current}
        records.append(record)
        if record["kept"]:
            motion.set_part(k, *dq_from_rt(*recalled), prismatic=False)
            current = recalled_loss
    return records
