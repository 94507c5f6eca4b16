"""A rod's twist: a round bar much longer than it is thick (a lever, a handle) looks the same
in the images however far it turns about its own length, so the motion steps have nothing to
hold that twist and Adam walks it about; the hinge's axis drifts with it (a real faucet's
lever at the fast profile: axis 10° off, its length landing within 1/100 of itself). At the
end of stage 3 such a hinge keeps only the swing of its length, the least rotation that lands
it, about the pivot that puts its centre where the trained motion does. A round bar that
turns about an axis not square to its length is read as square to it: no image tells the two
apart (docs/method.md, "Rods")."""

from __future__ import annotations

import numpy as np
import torch

from gear.kinematics import (
    dq_from_rt,
    quat_angle,
    quat_from_axis_angle,
    quat_from_matrix,
    quat_to_matrix,
)
from gear.pipeline.stage2.hypotheses import Plane, fit_plane
from gear.pipeline.stage3.joints import SurfaceCentres, part_motion
from gear.pipeline.stage3.shared import RefineState

# A part is a rod when the extent of its opaque centres along its longest direction (stage 2's
# robust principal extents) is at least this many times that along the next: thin enough that
# a twist moves its surface by little (the real faucet's levers: 8-11 at the quick profile,
# 12-14 at fast; a stapler's arm, whose twist the images do see: 4.2-4.5; doors: 1-2.5).
ROD_ASPECT = 6.0
# ... and round: its cross-section is at most this many times wider one way than the other
# (the faucet's levers: 1.0-1.2). A flat bar (a temple of glasses: 6) shows its twist.
MAX_CROSS_SECTION_ASPECT = 2.0
# Only the twist is dropped: the swing must carry at least this share of the turn. A rod
# spinning about its own length (a knob) swings by nothing and keeps its motion.
MIN_SWING_SHARE = 0.8
MIN_CENTRES = 10


def untwist_rods(state: RefineState) -> list[dict]:
    """Replaces each rod-like hinge's motion in `state.motion` by its swing; returns a record
    per part changed: its twist and how far its axis moved (degrees), the largest shift of its
    centres and the principal extents of its shape."""
    g, motion = state.gaussians, state.motion
    surface = SurfaceCentres(g)
    changed = []
    for k in range(1, motion.num_parts):
        points = surface.of_part(k)
        if bool(motion.prismatic[k]) or len(points) < MIN_CENTRES:
            continue
        quat, trans = part_motion(motion, k)
        swing = rod_swing(points, quat, trans)
        if swing is None:
            continue
        swing_quat, swing_trans, record = swing
        motion.set_part(k, *dq_from_rt(swing_quat, swing_trans), prismatic=False)
        changed.append({"part": k, **record})
    return changed


def round_rod(shape: Plane) -> bool:
    """Whether the principal extents of `shape` (fit_plane of a part's centres) make it a
    round rod: ROD_ASPECT times longer than thick, its cross-section within
    MAX_CROSS_SECTION_ASPECT of round."""
    across = np.sort(shape.extents[1:])
    # Written so that a degenerate cluster (every extent 0) is no rod.
    thin = shape.extents[0] > ROD_ASPECT * across[1]
    return bool(thin and across[1] <= MAX_CROSS_SECTION_ASPECT * across[0])


def rod_swing(points: torch.Tensor, quat: torch.Tensor, trans: torch.Tensor,
              ) -> tuple[torch.Tensor, torch.Tensor, dict] | None:
    """(unit quaternion, translation, record) of the swing of the rod `points` [N,3] under
    the motion x -> R(quat) x + trans, or None when the points are no round rod or the turn
    is mostly a twist about their length."""
    shape = fit_plane(points.numpy())
    extents = torch.from_numpy(shape.extents).to(points.dtype)  # along shape.axes' rows
    if not round_rod(shape):
        return None
    centre = torch.from_numpy(shape.centroid).to(points.dtype)
    length = torch.from_numpy(shape.axes[0]).to(points.dtype)
    rot = quat_to_matrix(quat)
    turned = rot @ length
    axis = torch.linalg.cross(length, turned)
    swing_angle = torch.atan2(axis.norm(), length @ turned)
    if axis.norm() < 1e-9 or swing_angle < MIN_SWING_SHARE * quat_angle(quat):
        return None
    axis = axis / axis.norm()
    swing = quat_from_axis_angle(axis, swing_angle)
    swing_rot = quat_to_matrix(swing)
    # The pivot that lands the centre where the trained motion does: (I - R) p = c' - R c,
    # least squares (a turn cannot move the centre along its own axis).
    landed = rot @ centre + trans
    pivot = torch.linalg.lstsq(torch.eye(3, dtype=points.dtype) - swing_rot,
                               (landed - swing_rot @ centre)[:, None]).solution[:, 0]
    old_axis = quat[1:] / quat[1:].norm().clamp(min=1e-12)
    swing_trans = pivot - swing_rot @ pivot
    moved = (points @ (swing_rot - rot).T + swing_trans - trans).norm(dim=1)
    record = {
        "moved_max": float(moved.max()),
        "extents": [round(float(x), 5) for x in extents],
        "twist_deg": float(torch.rad2deg(quat_angle(quat_from_matrix(swing_rot.T @ rot)))),
        "axis_moved_deg": float(torch.rad2deg(torch.arccos((axis @ old_axis).abs().clamp(max=1)))),
    }
    return swing, swing_trans, record
