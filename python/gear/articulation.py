"""Per-part rigid motions (canonical -> target, one learnable dual quaternion per movable part)
and the joints read off them: revolute or prismatic, axis, origin, angle or travel; and the
readings of an ambiguous joint (docs/method.md, "Part motion")."""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from gear.kinematics import (
    dq_from_rt,
    dq_normalize,
    dq_sclerp,
    dq_to_rt,
    quat_angle,
    quat_from_matrix,
    quat_identity,
    quat_to_matrix,
)

#: A rigid motion in numpy, ``(R [3, 3], t [3])``: p -> R p + t, canonical state -> target state.
RigidMotion = tuple[np.ndarray, np.ndarray]

# A rotation smaller than this (degrees) is reported as a pure translation by extract_joint
# when the caller does not say which joint type the part has.
_PRISMATIC_ANGLE_DEG = 1e-3


class PartMotion(torch.nn.Module):
    """One rigid motion per part, canonical -> target. Part 0 (static) is fixed to the identity.

    Learnable: `qr`, `qd` [K-1, 4] for parts 1..K-1 (normalised on use). A part flagged in
    `prismatic` [K] has its rotation forced to the identity, so only its translation learns.
    """

    def __init__(self, num_parts: int, dtype: torch.dtype = torch.float32) -> None:
        super().__init__()
        if num_parts < 1:
            raise ValueError(f"num_parts must be at least 1 (the static part), got {num_parts}")
        self.num_parts = num_parts
        self.qr = torch.nn.Parameter(quat_identity((num_parts - 1,), dtype))
        self.qd = torch.nn.Parameter(torch.zeros(num_parts - 1, 4, dtype=dtype))
        self.register_buffer("prismatic", torch.zeros(num_parts, dtype=torch.bool))

    @classmethod
    def from_rt(
        cls,
        motions: Sequence[RigidMotion],
        dtype: torch.dtype = torch.float32,
    ) -> PartMotion:
        """One part per (R 3x3, t 3) of the movable parts, plus the static part 0."""
        module = cls(len(motions) + 1, dtype)
        for k, (rot, trans) in enumerate(motions, start=1):
            rot = torch.as_tensor(np.asarray(rot, dtype=np.float64)).reshape(3, 3)
            trans = torch.as_tensor(np.asarray(trans, dtype=np.float64)).reshape(3)
            if not (torch.isfinite(rot).all() and torch.isfinite(trans).all()):
                raise ValueError(f"motions[{k - 1}]: non-finite rotation or translation")
            qr, qd = dq_from_rt(quat_from_matrix(rot), trans)
            module.set_part(k, qr, qd, prismatic=False)
        return module

    def motion(self, s: float | torch.Tensor = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
        """Unit dual quaternions (qr, qd) [K, 4] of every part at interpolation s in [0, 1]."""
        ident = quat_identity((self.num_parts - 1,), self.qr.dtype, self.qr.device)
        qr = torch.where(self.prismatic[1:, None], ident, self.qr)
        qr, qd = dq_normalize(qr, self.qd)
        qr = torch.cat([quat_identity((1,), qr.dtype, qr.device), qr], dim=0)
        qd = torch.cat([torch.zeros_like(qd[:1]), qd], dim=0)
        if not torch.is_tensor(s) and s == 1:
            return qr, qd
        return dq_sclerp(qr, qd, s)

    def _check_movable(self, k: int) -> None:
        if not 1 <= k < self.num_parts:
            raise ValueError(f"part {k}: movable parts are 1..{self.num_parts - 1}")

    @torch.no_grad()
    def set_part(self, k: int, qr: torch.Tensor, qd: torch.Tensor, prismatic: bool) -> None:
        """Overwrites part k's motion and joint type (a prismatic part keeps only translation)."""
        self._check_movable(k)
        qr, qd = dq_normalize(qr.to(self.qr), qd.to(self.qd))
        if prismatic:
            _, t = dq_to_rt(qr, qd)
            qr, qd = dq_from_rt(quat_identity((), self.qr.dtype, self.qr.device), t)
        self.qr[k - 1] = qr
        self.qd[k - 1] = qd
        self.prismatic[k] = prismatic

    def set_prismatic(self, k: int) -> None:
        """Turns part k into a slide: rotation := identity, its current translation kept."""
        qr, qd = self.motion()
        self.set_part(k, qr[k].detach(), qd[k].detach(), prismatic=True)

    def joints(self, center: np.ndarray | torch.Tensor) -> list[dict]:
        """extract_joint for every movable part (canonical -> target); the type of a part not
        flagged prismatic is inferred from its rotation."""
        qr, qd = self.motion()
        return [
            extract_joint(qr[k], qd[k], center, prismatic=True if self.prismatic[k] else None)
            for k in range(1, self.num_parts)
        ]


# ---------------------------------------------------------------- joints


def extract_joint(
    qr: torch.Tensor,
    qd: torch.Tensor,
    center: np.ndarray | torch.Tensor,
    prismatic: bool | None = None,
) -> dict:
    """The joint of one part's motion, in the joints.json entry format (without "part").

    Revolute: axis from qr (sign chosen so the angle lies in [0, 180]), angle 2 atan2(|v|, w),
    origin = the least-squares solution of (I - R) p = t moved along the axis to the point
    nearest `center`. Prismatic: axis = translation direction, distance = its length, origin =
    `center`. `prismatic=None` infers the type: a rotation below 1e-3 degrees is a slide.
    For a motion whose canonical state is "end", pass dq_conj(qr, qd) to get start -> end.
    """
    qr64, qd64 = dq_normalize(
        torch.as_tensor(qr).detach().to(torch.float64).cpu(),
        torch.as_tensor(qd).detach().to(torch.float64).cpu(),
    )
    if qr64[0] < 0:
        qr64, qd64 = -qr64, -qd64
    _, t_t = dq_to_rt(qr64, qd64)
    t = t_t.numpy()
    c = np.asarray(torch.as_tensor(center).detach().cpu(), dtype=np.float64).reshape(3)
    vec = qr64[1:].numpy()
    angle = float(quat_angle(qr64))
    if prismatic is None:
        prismatic = math.degrees(angle) < _PRISMATIC_ANGLE_DEG
    if prismatic:
        dist = float(np.linalg.norm(t))
        # A zero slide has no direction; any unit axis describes it.
        axis = t / dist if dist > 0 else np.array([1.0, 0.0, 0.0])
        return {
            "type": "prismatic",
            "axis": axis.tolist(),
            "origin": c.tolist(),
            "angle_deg": 0.0,
            "distance": dist,
        }
    norm = float(np.linalg.norm(vec))
    # A hinge that has not turned has no axis yet; report a fixed one rather than NaN.
    axis = vec / norm if norm > 0 else np.array([1.0, 0.0, 0.0])
    rot = quat_to_matrix(qr64).numpy()
    # (I - R) has rank 2 (the axis is its null space): lstsq returns the minimum-norm pivot.
    pivot = np.linalg.lstsq(np.eye(3) - rot, t, rcond=None)[0]
    pivot = pivot + np.dot(c - pivot, axis) * axis
    return {
        "type": "revolute",
        "axis": axis.tolist(),
        "origin": pivot.tolist(),
        "angle_deg": math.degrees(angle),
        "distance": 0.0,
    }


# ---------------------------------------------------------------- ambiguous joints


@dataclass
class JointHypothesis:
    """One candidate motion for a part: a name for logs, its joint type and dual quaternion."""

    name: str
    prismatic: bool
    qr: torch.Tensor
    qd: torch.Tensor


def joint_hypotheses(
    motion: PartMotion, k: int, extra: Sequence[RigidMotion] = ()
) -> list[JointHypothesis]:
    """Candidates for part k: its current motion read as a hinge, the slide keeping its
    translation, and each extra (R, t) (e.g. stage 2's hinge and slide guesses), typed
    prismatic when it does not rotate."""
    motion._check_movable(k)
    qr, qd = (x[k].detach().clone() for x in motion.motion())
    slide = dq_from_rt(quat_identity((), qr.dtype, qr.device), dq_to_rt(qr, qd)[1])
    out = [
        JointHypothesis("revolute", False, qr, qd),
        JointHypothesis("prismatic", True, *slide),
    ]
    for i, (rot, trans) in enumerate(extra):
        rot = torch.as_tensor(np.asarray(rot, dtype=np.float64)).reshape(3, 3)
        trans = torch.as_tensor(np.asarray(trans, dtype=np.float64)).reshape(3)
        if not (torch.isfinite(rot).all() and torch.isfinite(trans).all()):
            raise ValueError(f"extra[{i}]: non-finite rotation or translation")
        eqr, eqd = dq_from_rt(quat_from_matrix(rot), trans)
        still = math.degrees(float(quat_angle(eqr))) < _PRISMATIC_ANGLE_DEG
        kind = "prismatic" if still else "revolute"
        out.append(JointHypothesis(f"{kind}-extra{i}", still, eqr.to(qr), eqd.to(qr)))
    return out


def joint_readings(
    motion: PartMotion, k: int, extra: Sequence[RigidMotion] = ()
) -> list[tuple[JointHypothesis, PartMotion]]:
    """Each hypothesis of joint_hypotheses(motion, k, extra) with its own copy of `motion`
    whose part k is set to it: the readings a caller scores (and may tune in place)."""
    readings = []
    for hyp in joint_hypotheses(motion, k, extra):
        candidate = copy.deepcopy(motion)
        candidate.set_part(k, hyp.qr, hyp.qd, hyp.prismatic)
        readings.append((hyp, candidate))
    return readings


def resolve_ambiguous_joint(
    motion: PartMotion,
    k: int,
    readings: Sequence[tuple[JointHypothesis, PartMotion]],
    losses: Sequence[float],
) -> JointHypothesis:
    """Keeps the reading of an ambiguous joint the images prefer.

    `readings` come from joint_readings(motion, k, ...), `losses` are their photometric +
    depth losses in the same order (lower is better), computed by the caller, which may have
    fine-tuned each copy first. The winner's part k, as the caller left it (the reading it
    scored, not the untuned guess), is written into `motion`, and its hypothesis returned.
    Ground truth plays no part.
    """
    if len(readings) != len(losses) or not readings:
        raise ValueError(f"losses: expected one per reading ({len(readings)}), got {len(losses)}")
    best: tuple[float, JointHypothesis, PartMotion] | None = None
    for (hyp, candidate), loss in zip(readings, losses, strict=True):
        value = float(loss)
        if not math.isfinite(value):
            raise ValueError(f"score: non-finite loss {value} for the {hyp.name} hypothesis")
        if best is None or value < best[0]:
            best = (value, hyp, candidate)
    assert best is not None
    _, hyp, winner = best
    qr, qd = winner.motion()
    motion.set_part(k, qr[k].detach(), qd[k].detach(), hyp.prismatic)
    return hyp
