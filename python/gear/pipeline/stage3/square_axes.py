"""Axes square to the body: boxes hinge and slide along their edges (a cabinet's doors about
lines parallel to its sides, its drawers along them), but the motion steps train a free rigid
motion whose axis nothing holds in the directions the images barely see: a strip along the
hinge that trained with the wrong part pulls it a degree or a few off. At the end of stage 3
each hinge or slide whose axis lies within SQUARE_TOLERANCE_DEG of a direction of the body's
frame (the normals of two square faces of the static part, when it has them, else the upright
the cameras were held about and the normal of a face square to it) is tried along
that direction, its angle and translation settled with the axis held; it is kept unless the
images see it clearly worse than the motion trained (docs/method.md, "Axes square to the
body")."""

from __future__ import annotations

import copy
import math

import numpy as np
import torch

from gear.articulation import PartMotion
from gear.camera import capture_up
from gear.kinematics import (
    dq_from_rt,
    quat_axis_angle,
    quat_from_axis_angle,
    quat_to_matrix,
)
from gear.pipeline.stage2.frame import MIN_CENTRES, body_frame, upright_frame
from gear.pipeline.stage3.joint_types import image_loss, scoring_loss
from gear.pipeline.stage3.joints import SurfaceCentres, part_motion
from gear.pipeline.stage3.shared import RefineState

# An axis is tried along a direction of the frame that lies within this of it: a real sink
# cabinet's two doors trained 7.5 and 5.0 degrees off square, and the images saw them squared
# only 1.8 % and 0.1 % worse; a real pair of glasses' temple, a flat bar whose turn leaves its
# axis loosely held, trained 10.5 degrees off the upright, and squared the images saw it
# 0.05 % better. A door truly turning nearly this far off square keeps its axis (the images
# see it squared far worse)...
SQUARE_TOLERANCE_DEG = 15.0
# ... and at least this far from it: the frame itself lay 0.06-0.72 degrees off the true axes
# of seven fast models (cabinets, fridges, an oven counter; 0.25 on average over RANSAC
# seeds), so a smaller move can make the axis worse as easily as better (the built-in
# fridge's door, trained 0.01-0.58 degrees off on two machines).
MIN_SQUARE_DEG = 0.5
# The squared motion is kept unless its image loss exceeds the trained motion's by more than
# this share. The trained motion fits the labels it trained with: a real oven counter's door,
# its axis 1.0 degree off and squared to within 0.16 of the truth, scored 3.0 % worse after
# settling; a door turning 4.5 degrees off square, squared, 5-31 % worse as it opens 50-110
# degrees. Below this share the body's frame decides.
SQUARE_MARGIN = 0.05
# Loss evaluations (renders of the scoring views and their backward) that settle a squared
# part's angle and pivot.
SETTLE_EVALUATIONS = 20



def squared_axis(axis: np.ndarray, frame: np.ndarray) -> np.ndarray | None:
    """The direction of `frame` (sign-aligned with `axis`) within SQUARE_TOLERANCE_DEG of the
    unit `axis`, or None."""
    nearest = frame[int(np.argmax(np.abs(frame @ axis)))]
    dot = float(axis @ nearest)
    if math.degrees(math.acos(min(1.0, abs(dot)))) > SQUARE_TOLERANCE_DEG:
        return None
    return nearest * math.copysign(1.0, dot)


def squared_motion(points: torch.Tensor, quat: torch.Tensor, trans: torch.Tensor,
                   prismatic: bool, frame: np.ndarray,
                   ) -> tuple[torch.Tensor, torch.Tensor, float] | None:
    """(quaternion, translation, degrees the axis moved) of the motion x -> R(quat) x + trans
    of a part with centres `points` [N, 3] along the nearby direction of `frame`: a slide keeps
    its travel along it; a hinge keeps its angle, turned about it, and lands the centres where
    the motion does, on average (least squares). None when the axis is near no direction, or
    within MIN_SQUARE_DEG of one already."""
    if prismatic:
        length = trans.norm()
        if length <= 1e-12:
            return None
        axis = trans / length
    else:
        if quat[1:].norm() <= 1e-9:
            return None
        axis, angle = quat_axis_angle(quat)
    target = squared_axis(axis.numpy(), frame)
    if target is None:
        return None
    target = torch.as_tensor(target, dtype=points.dtype)
    moved = math.degrees(math.acos(min(1.0, abs(float(axis @ target)))))
    if moved < MIN_SQUARE_DEG:
        return None
    if prismatic:
        return quat.clone(), (trans @ target) * target, moved
    new_quat = quat_from_axis_angle(target, angle)
    landed = points @ quat_to_matrix(quat).T + trans
    new_trans = (landed - points @ quat_to_matrix(new_quat).T).mean(dim=0)
    return new_quat, new_trans, moved


def square_axes(state: RefineState) -> list[dict]:
    """Tries every movable part of `state` along the body's frame (squared_motion, then its
    angle and translation settled with the axis held) and keeps the squared motion where its
    image loss is within SQUARE_MARGIN of the current one's. A held slide is not tried: it
    slid along the body's frame all along (RefineState.hold_slides), and a frame read again
    off the final static part only adds that frame's own error (a real kitchen island's
    trays: 1.2 degrees, which the images did not see).
    Returns a record per part tried: how far its axis moved, both losses and whether it was
    kept."""
    g, motion = state.gaussians, state.motion
    surface = SurfaceCentres(g)
    body = surface.of_part(0).numpy()
    frame = body_frame(body)
    if frame is None:
        cameras = [v.camera for v in state.canonical_views + state.target_views]
        frame = upright_frame(body, capture_up(cameras))
    if frame is None:
        return []
    records = []
    current = None  # the image loss of `motion`, once a part is tried
    for k in state.live_parts():
        if k in state.held_slides:
            continue
        points = surface.of_part(k)
        if len(points) < MIN_CENTRES:
            continue
        prismatic = bool(motion.prismatic[k])
        squared = squared_motion(points, *part_motion(motion, k), prismatic, frame)
        if squared is None:
            continue
        quat, trans, moved = squared
        quat, trans = _settled(state, motion, k, quat, trans, prismatic)
        candidate = with_part(motion, k, (quat, trans), prismatic)
        if current is None:
            current = image_loss(state, motion)
        squared_loss = image_loss(state, candidate)
        kept = squared_loss <= current * (1 + SQUARE_MARGIN)
        records.append({"part": k, "axis_moved_deg": round(moved, 4), "loss": current,
                        "squared_loss": squared_loss, "kept": kept})
        if kept:
            motion.set_part(k, *dq_from_rt(quat, trans), prismatic=prismatic)
            current = squared_loss
    return records


class _AlongAxis:
    """`motion` with part k turned about (or slid along) a fixed axis: its angle and
    translation (a slide: its travel) are the free parameters; `motion()` as PartMotion's."""

    def __init__(self, motion: PartMotion, k: int, quat: torch.Tensor, trans: torch.Tensor,
                 prismatic: bool) -> None:
        qr, qd = motion.motion()
        self.qr, self.qd, self.k, self.prismatic = qr.detach(), qd.detach(), k, prismatic
        if prismatic:
            travel = trans.norm()
            self.axis = trans / travel
            self.params = [torch.nn.Parameter(travel.clone())]
        else:
            self.axis, angle = quat_axis_angle(quat)
            self.params = [torch.nn.Parameter(angle.clone()), torch.nn.Parameter(trans.clone())]

    def part(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(quaternion, translation) of part k."""
        if self.prismatic:
            identity = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=self.axis.dtype)
            return identity, self.params[0] * self.axis
        return quat_from_axis_angle(self.axis, self.params[0]), self.params[1]

    def motion(self, s: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
        assert s == 1.0
        qr_k, qd_k = dq_from_rt(*self.part())
        row = torch.arange(len(self.qr))[:, None] == self.k
        return (torch.where(row, qr_k.to(self.qr), self.qr),
                torch.where(row, qd_k.to(self.qd), self.qd))


def _settled(state: RefineState, motion: PartMotion, k: int, quat: torch.Tensor,
             trans: torch.Tensor, prismatic: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """Part k's (quaternion, translation) about (or along) the axis of `quat` (`trans` for a
    slide), its angle and translation (travel) refitted to the scoring views by L-BFGS
    (deterministic, SETTLE_EVALUATIONS loss evaluations at most): the squared axis gets the
    settled angle and pivot the trained one had."""
    held = _AlongAxis(motion, k, quat, trans, prismatic)
    optimizer = torch.optim.LBFGS(held.params, max_iter=SETTLE_EVALUATIONS,
                                  max_eval=SETTLE_EVALUATIONS, line_search_fn="strong_wolfe")

    def closure() -> torch.Tensor:
        optimizer.zero_grad()
        loss = scoring_loss(state, held)
        loss.backward()
        return loss

    with torch.enable_grad():
        optimizer.step(closure)
    with torch.no_grad():
        settled = tuple(x.detach().clone() for x in held.part())
    if not all(bool(torch.isfinite(x).all()) for x in settled):
        return quat, trans
    return settled


def with_part(motion: PartMotion, k: int, rt: tuple[torch.Tensor, torch.Tensor],
               prismatic: bool) -> PartMotion:
    """A copy of `motion` with part k moved by rt = (quaternion, translation)."""
    out = copy.deepcopy(motion)
    out.set_part(k, *dq_from_rt(*rt), prismatic=prismatic)
    return out
