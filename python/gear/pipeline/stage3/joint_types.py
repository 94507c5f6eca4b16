"""Stage 3's joint-type decision: a revolute part that barely turns becomes prismatic, or,
by default, every reading of an ambiguous joint is tuned briefly and scored on the target
images and the best kept (docs/method.md, "Stage 3: joint types")."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
import torch

from gear.articulation import PartMotion, resolve_ambiguous_joint
from gear.kinematics import quat_angle
from gear.pipeline.common import check_finite
from gear.pipeline.stage3.shared import RefineState, motion_optimizer

Motion = tuple[np.ndarray, np.ndarray]  # (R [3,3], t [3])


class JointTypes(RefineState):
    def classify(self) -> None:
        """Revolute joints below ε become prismatic; the motion optimizer is rebuilt. The
        log event lists every scored reading's loss (in scoring order) and, per movable
        part, the joint type and angle that came out."""
        c = self.config
        resolve = c.resolve_ambiguous_joints
        scores: list[float] = []

        def score(candidate: PartMotion) -> float:
            scores.append(self.motion_loss(candidate))
            return scores[-1]

        switched = classify_joints(
            self.motion,
            eps_deg=c.revolute_eps_deg,
            score=score if resolve else None,
            init_motions=self.init_motions if resolve and self.init_motions else None,
            small_hinge_margin=c.small_hinge_margin,
        )
        qr, _ = self.motion.motion()
        angles = [round(math.degrees(float(a)), 3) for a in quat_angle(qr.detach())[1:]]
        types = ["prismatic" if p else "revolute" for p in self.motion.prismatic[1:].tolist()]
        self.events.append({"event": "joint_classification", "prismatic": list(switched),
                            "scores": scores, "types": types, "angles_deg": angles})
        # Any part below ε may have been rewritten (slide or initial hinge): fresh Adam moments.
        self.motion_optimizer = motion_optimizer(self.motion, c, self.extent)

    def motion_loss(self, candidate: PartMotion) -> float:
        """Photometric + depth loss of the hard-assigned model moved by `candidate`, over the
        scoring views on a black background, after `classify_tune_steps` motion-only steps
        on the candidate (tune_motion): how well a joint hypothesis explains the target
        images once it has had the same short chance to settle as every other one. No
        ground truth is involved. `candidate` is the caller's copy and is tuned in place."""
        self.tune_motion(candidate, self.config.classify_tune_steps)
        views = self.scoring_views()
        black = [torch.zeros(3)] * len(views)
        with torch.no_grad():
            terms = self.held_image_terms(candidate, views, black)
        return float(sum(terms.values()))

    def tune_motion(self, candidate: PartMotion, steps: int) -> None:
        """`steps` Adam steps on the motion of `candidate` alone (the Gaussians held, hard
        assignment, as in the M-step), each on the next of the scoring views in turn over a
        black background: deterministic, and the same budget for every joint hypothesis. One
        view per step keeps it cheap; Adam's moments average over the cycle. A fresh
        optimizer with the M-step's learning rates; `self.motion` and its optimizer are
        untouched."""
        if steps <= 0:
            return
        optimizer = motion_optimizer(candidate, self.config, self.extent)
        views = self.scoring_views()
        with torch.enable_grad():
            for step in range(steps):
                terms = self.held_image_terms(candidate, [views[step % len(views)]],
                                              [torch.zeros(3)])
                check_finite(terms, f"{self.name} joint scoring", step)
                optimizer.zero_grad(set_to_none=True)
                sum(terms.values()).backward()
                optimizer.step()


def _small_hinge_penalised(
    score: Callable[[PartMotion], float], k: int, eps: float, margin: float
) -> Callable[[PartMotion], float]:
    """`score`, raised by `margin` x |score| for a reading of part k that is a hinge turning
    less than `eps` radians once scored (the scorer may tune the candidate first)."""

    def penalised(candidate: PartMotion) -> float:
        value = float(score(candidate))
        qr, _ = candidate.motion()
        if not bool(candidate.prismatic[k]) and float(quat_angle(qr[k].detach())) < eps:
            value += margin * abs(value)
        return value

    return penalised


def classify_joints(
    motion: PartMotion,
    eps_deg: float = 10.0,
    score: Callable[[PartMotion], float] | None = None,
    init_motions: Sequence[Sequence[Motion]] | None = None,
    small_hinge_margin: float = 0.0,
) -> list[int]:
    """Turns revolute parts whose rotation is below `eps_deg` into prismatic ones.

    Without `score` this is the paper's rule. With `score` (the photometric + depth loss of a
    candidate PartMotion, see articulation.resolve_ambiguous_joint) a part is ambiguous when it
    turned less than `eps_deg` or when stage 2 left it more than one guess
    (`init_motions[k-1]`: a list of (R, t), e.g. Stage2Result.candidates). An
    ambiguous part's readings — its current motion, its slide and the stage-2 guesses — are
    all scored and the lowest loss wins. This rescues hinges that stalled at a small angle,
    e.g. a door opened 180 degrees. A hinge reading that turns less than `eps_deg` keeps the
    paper's rule as a prior: its loss counts `small_hinge_margin` (relative) higher, so it
    wins only when the images prefer it clearly. A hinge contains the slide (angle 0), so
    tuned by the scorer it can always match the slide; on near-ties it would win by noise.
    Returns the parts made prismatic; the caller rebuilds the optimizer state of `motion`.
    """
    if init_motions is not None and len(init_motions) != motion.num_parts - 1:
        raise ValueError(
            f"init_motions: expected {motion.num_parts - 1} entries, got {len(init_motions)}"
        )
    guesses = [list(e) for e in init_motions] if init_motions is not None else None
    qr, _ = motion.motion()
    angles = quat_angle(qr.detach())
    switched = []
    for k in range(1, motion.num_parts):
        if bool(motion.prismatic[k]):
            continue
        small = float(angles[k]) < math.radians(eps_deg)
        extra = guesses[k - 1] if guesses is not None else []
        if score is None:
            if small:
                motion.set_prismatic(k)
        elif small or len(extra) > 1:
            eps = math.radians(eps_deg)
            resolve_ambiguous_joint(
                motion, k, _small_hinge_penalised(score, k, eps, small_hinge_margin), extra
            )
        if bool(motion.prismatic[k]):
            switched.append(k)
    return switched
