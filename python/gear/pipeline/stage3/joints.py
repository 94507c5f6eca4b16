"""Reading joints off stage 3's part motions: joints.json entries, start -> end."""

from __future__ import annotations

import numpy as np
import torch

from gear.articulation import PartMotion, extract_joint
from gear.kinematics import dq_conj, dq_to_rt
from gear.pipeline.stage2.initialise import STAGE2_MIN_OPACITY
from gear.splats import Gaussians


def opaque(g: Gaussians) -> torch.Tensor:
    """Which Gaussians are surface, not haze: opacity above STAGE2_MIN_OPACITY, the bar stage 2
    reads shapes with (bool [N])."""
    return torch.sigmoid(g["opacity"].detach()) > STAGE2_MIN_OPACITY


def solid_means(g: Gaussians, among: torch.Tensor | None = None) -> torch.Tensor:
    """Centres of the opaque Gaussians (of those in the bool mask `among`, if given; all of
    them when fewer than 4 are opaque)."""
    means = g["means"].detach()
    solid = opaque(g)
    if among is not None:
        means, solid = means[among], solid[among]
    return means[solid] if int(solid.sum()) >= 4 else means


def part_motion(motion: PartMotion, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(unit quaternion, translation) of part k of `motion`, in float64."""
    qr, qd = motion.motion()
    quat, trans = dq_to_rt(qr[k], qd[k])
    return quat.detach().to(torch.float64), trans.detach().to(torch.float64)


class SurfaceCentres:
    """A model's surface centres, the ones stage 2 reads shapes from (opacity above
    STAGE2_MIN_OPACITY: surface, not haze), in float64, per part of its logits."""

    def __init__(self, g: Gaussians):
        self.means = g["means"].detach().to(torch.float64)
        self.ids = g.part_ids()
        self.opaque = opaque(g)

    def of_part(self, k: int) -> torch.Tensor:
        """Part k's surface centres [M, 3]."""
        return self.means[(self.ids == k) & self.opaque]

    def all(self) -> torch.Tensor:
        """Every part's surface centres [M, 3]."""
        return self.means[self.opaque]


def object_center(g: Gaussians) -> np.ndarray:
    """Centre of the opaque Gaussians (joint origins are reported nearest to it)."""
    return solid_means(g).mean(dim=0).numpy().astype(np.float64)


def object_radius(g: Gaussians, center: np.ndarray) -> float:
    """How far the opaque Gaussians reach from `center` (99th percentile of their distances,
    so that a few floaters do not count)."""
    pts = solid_means(g)
    if len(pts) == 0:
        return 0.0
    dist = (pts - torch.as_tensor(center, dtype=pts.dtype)).norm(dim=1)
    return float(torch.quantile(dist, 0.99))


def start_to_end_joints(motion: PartMotion, canonical: str, center: np.ndarray) -> list[dict]:
    """joints.json entries: each movable part's motion expressed from start to end."""
    qr, qd = motion.motion(1.0)
    joints = []
    for k in range(1, motion.num_parts):
        a, b = qr[k].detach(), qd[k].detach()
        if canonical == "end":  # the learnt motion is end -> start: invert it
            a, b = dq_conj(a, b)
        entry = extract_joint(a, b, center, prismatic=bool(motion.prismatic[k]))
        joints.append({"part": k, **entry})
    return joints
