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
from collections.abc import Callable

import numpy as np
import torch

from gear.articulation import PartMotion
from gear.camera import capture_up
from gear.kinematics import (
    dq_from_rt,
    dq_to_rt,
    quat_axis_angle,
    quat_from_axis_angle,
    quat_to_matrix,
)
from gear.pipeline.stage2.hypotheses import ransac_plane
from gear.pipeline.stage2.initialise import STAGE2_MIN_OPACITY
from gear.pipeline.stage3.joint_types import image_loss, scoring_loss
from gear.pipeline.stage3.shared import RefineState

# The body's faces: RANSAC planes of its opaque centres (an even subsample of at most
# FRAME_POINTS, FRAME_TRIALS seeded triples each), points within FRAME_TOLERANCE of the
# object's size from the plane counting for it.
FRAME_POINTS = 20_000
FRAME_TRIALS = 300
FRAME_TOLERANCE = 0.005
# A face holds at least this share of the body's centres (a box's faces: 10-30 %) and this
# many: the hazy static parts of quick models (300-600 opaque centres) gave frames 0.7-3.3
# degrees off their boxes, about as far as the axes they would square; a fast model's faces
# hold thousands (the oven counter's frame: 0.16 degrees off).
MIN_FACE_SHARE = 0.05
MIN_FACE_CENTRES = 500
# ... and the second face's normal lies within this of square to the first's.
SQUARE_FACES_DEG = 10.0
# A face's opposite: parallel to it within this, and at least this share of the object's size
# away from it (a box's sides, not a ledge beside a face).
OPPOSITE_FACES_DEG = 5.0
OPPOSITE_FACE_GAP = 0.1
# An axis is tried along a direction of the frame that lies within this of it: a real sink
# cabinet's two doors trained 7.5 and 5.0 degrees off square, and the images saw them squared
# only 1.8 % and 0.1 % worse; a door truly turning nearly this far off square keeps its axis
# (the images see it squared far worse)...
SQUARE_TOLERANCE_DEG = 10.0
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
MIN_CENTRES = 10
# Loss evaluations (renders of the scoring views and their backward) that settle a squared
# part's angle and pivot.
SETTLE_EVALUATIONS = 20


def body_frame(points: np.ndarray, seed: int = 0) -> np.ndarray | None:
    """The body's frame [3, 3] (orthonormal rows) from its centres `points` [N, 3]: the
    direction of its largest face, that of its largest face square to the first (within
    SQUARE_FACES_DEG), made square to it, and their cross product (each direction from a face
    and its opposite, _face_direction); None unless both faces hold MIN_FACE_SHARE of the
    centres and MIN_FACE_CENTRES. Faces are fitted to many centres, so their normals are known
    far better than any one Gaussian's (the shortest axes of a real oven counter's Gaussians
    spread 5.5 degrees about its faces, and their modes lay 2-3 degrees off)."""
    pts = _frame_sample(points)
    if len(pts) < MIN_CENTRES:
        return None
    size = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
    rng = np.random.default_rng(seed)
    first = _face_direction(pts, size, rng, None)
    if first is None:
        return None
    second = _face_direction(pts, size, rng, first)
    if second is None:
        return None
    second = second - (second @ first) * first
    second = second / np.linalg.norm(second)
    return np.stack([first, second, np.cross(first, second)])


def upright_frame(points: np.ndarray, up: np.ndarray | None, seed: int = 0) -> np.ndarray | None:
    """The frame [M, 3] (orthonormal rows) of a body with no two square faces, from the
    direction `up` the cameras were held upright about (gear.camera.capture_up): `up`, and
    with the direction of the body's largest face square to it (within SQUARE_FACES_DEG, made
    square; _face_direction) that one and their cross product. None without `up`. A pair of
    glasses is one thin front: no second face, but its temples turn about the upright of the
    capture (their trained axes 1.6 and 0.9 degrees off it at fast)."""
    if up is None:
        return None
    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    pts = _frame_sample(points)
    if len(pts) < MIN_CENTRES:
        return up[None]
    size = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
    face = _face_direction(pts, size, np.random.default_rng(seed), up)
    if face is None:
        return up[None]
    face = face - (face @ up) * up
    face = face / np.linalg.norm(face)
    return np.stack([up, face, np.cross(up, face)])


def _frame_sample(points: np.ndarray) -> np.ndarray:
    """The finite rows of `points` [N, 3] as float64, evenly subsampled to at most
    FRAME_POINTS."""
    pts = np.asarray(points, dtype=np.float64)
    pts = pts[np.isfinite(pts).all(axis=1)]
    return pts[:: max(1, -(-len(pts) // FRAME_POINTS))]


def _face_direction(pts: np.ndarray, size: float, rng: np.random.Generator,
                   square_to: np.ndarray | None) -> np.ndarray | None:
    """The unit normal of the largest face of `pts` (an object `size` across), among faces
    within SQUARE_FACES_DEG of square to `square_to` when given, averaged with that of the
    largest face opposite it (parallel within OPPOSITE_FACES_DEG, OPPOSITE_FACE_GAP of the
    size or more away, as large as a face must be) when there is one. A fast model's opposite
    faces tilt against each other (0.2-2.6 degrees apart on real bodies): over seven fast
    models and six RANSAC seeds the mean of the two normals lay 0.25 degrees off the true
    axes on average, the largest face alone 0.43 (1.02 on a cabinet whose sides lie 1.78
    degrees apart)."""
    tolerance = FRAME_TOLERANCE * size
    least = max(MIN_FACE_CENTRES, MIN_FACE_SHARE * len(pts))
    face = _largest_face(pts, tolerance, least, rng,
                         lambda normal: _square_enough(normal, square_to))
    if face is None:
        return None
    origin, normal = face
    beyond = pts[np.abs((pts - origin) @ normal) >= OPPOSITE_FACE_GAP * size]
    if len(beyond) < least:
        return normal
    opposite = _largest_face(beyond, tolerance, least, rng,
                             lambda other: _parallel_enough(other, normal))
    if opposite is None:
        return normal
    mean = normal + math.copysign(1.0, float(opposite[1] @ normal)) * opposite[1]
    return mean / np.linalg.norm(mean)


def _largest_face(pts: np.ndarray, tolerance: float, least: float, rng: np.random.Generator,
                  accept: Callable[[np.ndarray], bool]) -> tuple[np.ndarray, np.ndarray] | None:
    """(a point, unit normal) of the plane holding the most of `pts` within `tolerance`
    (RANSAC over FRAME_TRIALS triples, refitted to its points by least squares twice), among
    the normals `accept` allows; None when it holds fewer than `least` of them or its refit
    left what `accept` allows."""
    best = ransac_plane(pts, tolerance, FRAME_TRIALS, rng, accept=accept)
    if best is None:
        return None
    origin, normal = best
    for _ in range(2):
        near = pts[np.abs((pts - origin) @ normal) <= tolerance]
        if len(near) < 3:
            return None
        origin = near.mean(axis=0)
        normal = np.linalg.svd(near - origin, full_matrices=False)[2][-1]
    if len(near) < least or not accept(normal):
        return None  # too small, or refitted onto another face (a strip of it)
    return origin, normal / np.linalg.norm(normal)


def _square_enough(normal: np.ndarray, square_to: np.ndarray | None) -> bool:
    """Whether the unit `normal` lies within SQUARE_FACES_DEG of square to `square_to` (True
    without one)."""
    limit = math.sin(math.radians(SQUARE_FACES_DEG))
    return square_to is None or abs(float(normal @ square_to)) <= limit


def _parallel_enough(normal: np.ndarray, other: np.ndarray) -> bool:
    """Whether the unit normals lie within OPPOSITE_FACES_DEG of parallel (either sign)."""
    return abs(float(normal @ other)) >= math.cos(math.radians(OPPOSITE_FACES_DEG))


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
    image loss is within SQUARE_MARGIN of the current one's.
    Returns a record per part tried: how far its axis moved, both losses and whether it was
    kept."""
    g, motion = state.gaussians, state.motion
    ids = g.part_ids()
    opaque = torch.sigmoid(g["opacity"].detach()) > STAGE2_MIN_OPACITY
    body = g["means"].detach()[(ids == 0) & opaque].numpy()
    frame = body_frame(body)
    if frame is None:
        cameras = [v.camera for v in state.canonical_views + state.target_views]
        frame = upright_frame(body, capture_up(cameras))
    if frame is None:
        return []
    means = g["means"].detach().to(torch.float64)
    records = []
    current = None  # the image loss of `motion`, once a part is tried
    for k in state.live_parts():
        points = means[(ids == k) & opaque]
        if len(points) < MIN_CENTRES:
            continue
        prismatic = bool(motion.prismatic[k])
        squared = squared_motion(points, *_part_motion(motion, k), prismatic, frame)
        if squared is None:
            continue
        quat, trans, moved = squared
        quat, trans = _settled(state, motion, k, quat, trans, prismatic)
        candidate = _with_part(motion, k, (quat, trans), prismatic)
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
