"""Axes square to the body: boxes hinge and slide along their edges (a cabinet's doors about
lines parallel to its sides, its drawers along them), but the motion steps train a free rigid
motion whose axis nothing holds in the directions the images barely see: a strip along the
hinge that trained with the wrong part pulls it a degree or a few off. At the end of stage 3
each hinge or slide whose axis lies within SQUARE_TOLERANCE_DEG of a direction of the body's
frame (the dominant directions of the static part's surface normals, when it has two square
ones) is tried along that direction, its turn or travel kept; the images keep it unless they
see it clearly worse than the motion trained (docs/method.md, "Axes square to the body")."""

from __future__ import annotations

import copy
import math

import numpy as np
import torch

from gear.articulation import PartMotion
from gear.kinematics import dq_from_rt, dq_to_rt, quat_from_axis_angle, quat_to_matrix
from gear.pipeline.stage2.initialise import STAGE2_MIN_OPACITY
from gear.pipeline.stage3.joint_types import image_loss
from gear.pipeline.stage3.shared import RefineState

# A normal counts for a direction of the frame when it lies within this of it (either sign).
FRAME_CONE_DEG = 10.0
# A direction of the frame holds at least this share of the static surface's weight (area x
# opacity x flatness): a box's faces hold 0.1-0.5 each; the front of a pair of glasses holds
# 0.95, and its curved rims spread the rest (no second direction: no frame).
MIN_DIRECTION_SHARE = 0.1
# ... and at least this many normals' worth of it (the effective count (sum w)^2 / sum w^2 of
# those within FRAME_CONE_DEG): a quick model's static part, a few hundred hazy Gaussians,
# gave directions 3-7 degrees off its box's faces from 1-66 of them.
MIN_EFFECTIVE_NORMALS = 200.0
# Normals scored as candidate directions: the heaviest ones (deterministic, no sampling).
CANDIDATES = 1000
# An axis is tried along a direction of the frame that lies within this of it.
SQUARE_TOLERANCE_DEG = 5.0
# The squared motion is kept unless its image loss exceeds the trained motion's by more than
# this share: within it the images do not tell the two apart, and the body's frame decides.
SQUARE_MARGIN = 0.01
MIN_CENTRES = 10


def surface_normals(g, mask: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:  # noqa: ANN001
    """Unit normals (each Gaussian's shortest axis) [N, 3] and weights [N] (the area of its two
    longer axes x opacity x flatness 1 - shortest / middle) of the Gaussians of `g` in
    `mask`."""
    scales = torch.exp(g["log_scales"].detach()[mask]).double()
    quats = g["quats"].detach()[mask].double()
    quats = quats / quats.norm(dim=1, keepdim=True).clamp(min=1e-12)
    rot = quat_to_matrix(quats)  # [N, 3, 3], columns are the Gaussian's axes
    sorted_scales, order = scales.sort(dim=1)
    normals = rot.gather(2, order[:, None, :1].expand(-1, 3, 1))[..., 0]
    flatness = (1 - sorted_scales[:, 0] / sorted_scales[:, 1].clamp(min=1e-12)).clamp(0, 1)
    opacity = torch.sigmoid(g["opacity"].detach()[mask].double())
    weights = opacity * sorted_scales[:, 1] * sorted_scales[:, 2] * flatness
    return normals.numpy(), weights.numpy()


def _mode(normals: np.ndarray, weights: np.ndarray, candidates: np.ndarray,
          ) -> tuple[np.ndarray, bool]:
    """The candidate direction holding the most normal weight within FRAME_CONE_DEG, refined
    as the weighted mean of the sign-aligned normals near it; and whether it is a direction of
    the body (MIN_DIRECTION_SHARE, MIN_EFFECTIVE_NORMALS)."""
    cone = math.cos(math.radians(FRAME_CONE_DEG))
    held = (np.abs(candidates @ normals.T) >= cone) @ weights
    direction = candidates[int(np.argmax(held))]
    for degrees in (FRAME_CONE_DEG, FRAME_CONE_DEG / 2):
        dots = normals @ direction
        near = np.abs(dots) >= math.cos(math.radians(degrees))
        mean = (normals[near] * (np.sign(dots[near]) * weights[near])[:, None]).sum(axis=0)
        if np.linalg.norm(mean) <= 1e-12:
            break
        direction = mean / np.linalg.norm(mean)
    near = weights[np.abs(normals @ direction) >= cone]
    effective = near.sum() ** 2 / max(float((near**2).sum()), 1e-300)
    found = near.sum() >= MIN_DIRECTION_SHARE * weights.sum() and effective >= MIN_EFFECTIVE_NORMALS
    return direction, bool(found)


def body_frame(normals: np.ndarray, weights: np.ndarray) -> np.ndarray | None:
    """The body's frame [3, 3] (orthonormal rows) from its surface `normals` [N, 3] and
    `weights` [N]: the strongest direction of the body (_mode), the strongest one square to
    it, and their cross product; None unless both are directions of the body."""
    keep = np.isfinite(normals).all(axis=1) & np.isfinite(weights) & (weights > 0)
    normals, weights = normals[keep], weights[keep]
    if len(normals) < MIN_CENTRES:
        return None
    candidates = normals[np.argsort(-weights, kind="stable")[:CANDIDATES]]
    first, found = _mode(normals, weights, candidates)
    across = candidates - np.outer(candidates @ first, first)
    length = np.linalg.norm(across, axis=1)
    # Candidates within FRAME_CONE_DEG of square to the first direction, projected square.
    square = length >= math.cos(math.radians(FRAME_CONE_DEG))
    if not found or not square.any():
        return None
    second, found = _mode(normals, weights, across[square] / length[square, None])
    second = second - (second @ first) * first
    if not found or np.linalg.norm(second) < 0.5:
        return None
    second = second / np.linalg.norm(second)
    return np.stack([first, second, np.cross(first, second)])


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
    on one already."""
    if prismatic:
        length = trans.norm()
        if length <= 1e-12:
            return None
        axis = trans / length
    else:
        axis = quat[1:] / quat[1:].norm().clamp(min=1e-12)
        if quat[1:].norm() <= 1e-9:
            return None
    target = squared_axis(axis.numpy(), frame)
    if target is None:
        return None
    target = torch.as_tensor(target, dtype=points.dtype)
    moved = math.degrees(math.acos(min(1.0, abs(float(axis @ target)))))
    if moved < 1e-3:
        return None
    if prismatic:
        return quat.clone(), (trans @ target) * target, moved
    angle = 2 * torch.atan2(quat[1:].norm(), quat[0])
    new_quat = quat_from_axis_angle(target, angle)
    landed = points @ quat_to_matrix(quat).T + trans
    new_trans = (landed - points @ quat_to_matrix(new_quat).T).mean(dim=0)
    return new_quat, new_trans, moved


def square_axes(state: RefineState) -> list[dict]:
    """Tries every movable part of `state` along the body's frame (squared_motion) and keeps
    the squared motion where its image loss is within SQUARE_MARGIN of the current one's.
    Returns a record per part tried: how far its axis moved, both losses and whether it was
    kept."""
    g, motion = state.gaussians, state.motion
    ids = g.part_ids()
    opaque = torch.sigmoid(g["opacity"].detach()) > STAGE2_MIN_OPACITY
    frame = body_frame(*surface_normals(g, (ids == 0) & opaque))
    if frame is None:
        return []
    means = g["means"].detach().to(torch.float64)
    records = []
    for k in state.live_parts():
        points = means[(ids == k) & opaque]
        if len(points) < MIN_CENTRES:
            continue
        prismatic = bool(motion.prismatic[k])
        squared = squared_motion(points, *_part_motion(motion, k), prismatic, frame)
        if squared is None:
            continue
        quat, trans, moved = squared
        candidate = _with_part(motion, k, (quat, trans), prismatic)
        before, after = image_loss(state, motion), image_loss(state, candidate)
        kept = after <= before * (1 + SQUARE_MARGIN)
        if kept:
            motion.set_part(k, *dq_from_rt(quat, trans), prismatic=prismatic)
        records.append({"part": k, "axis_moved_deg": round(moved, 4), "loss": before,
                        "squared_loss": after, "kept": kept})
    return records


def _part_motion(motion: PartMotion, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(unit quaternion, translation) of part k of `motion`, in float64."""
    qr, qd = motion.motion()
    quat, trans = dq_to_rt(qr[k], qd[k])
    return quat.detach().to(torch.float64), trans.detach().to(torch.float64)


def _with_part(motion: PartMotion, k: int, rt: tuple[torch.Tensor, torch.Tensor],
               prismatic: bool) -> PartMotion:
    """A copy of `motion` with part k moved by rt = (quaternion, translation)."""
    out = copy.deepcopy(motion)
    out.set_part(k, *dq_from_rt(*rt), prismatic=prismatic)
    return out
