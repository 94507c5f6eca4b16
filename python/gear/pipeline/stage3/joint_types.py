"""Stage 3's joint-type decision: a revolute part that barely turns becomes prismatic, or,
by default, every reading of an ambiguous joint is tuned briefly and scored on the target
images and the best kept (docs/method.md, "Stage 3: joint types"). The losses are computed
here and handed to gear.articulation as numbers."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
import torch

from gear.articulation import (
    PartMotion,
    RigidMotion,
    extract_joint,
    joint_readings,
    resolve_ambiguous_joint,
)
from gear.kinematics import quat_angle
from gear.pipeline.common import check_finite
from gear.pipeline.stage3.joints import object_center, object_radius
from gear.pipeline.stage3.shared import RefineState, motion_optimizer

# A hinge's axis passes within this many object radii of the object's centre: a hinge turning
# less than ε about an axis farther out moves its part along an arc of radius far beyond the
# object, which over a small angle is its chord: a slide in disguise, whatever the images'
# slight preference for the curve (a drawer whose motion settled as a 0.6° turn about an axis
# 25 object sizes away scored 4 % below its slide).
HINGE_REACH = 2.0


def classify(state: RefineState) -> None:
    """Revolute joints below ε become prismatic; the motion optimizer of `state` is rebuilt.
    The log event lists every scored reading's loss (in scoring order) and, per movable part,
    the joint type and angle that came out."""
    c = state.config
    resolve = c.resolve_ambiguous_joints
    scores: list[float] = []

    def score(candidate: PartMotion) -> float:
        scores.append(motion_loss(state, candidate))
        return scores[-1]

    center = object_center(state.gaussians)
    switched = classify_joints(
        state.motion,
        eps_deg=c.revolute_eps_deg,
        score=score if resolve else None,
        init_motions=state.init_motions if resolve and state.init_motions else None,
        small_hinge_margin=c.small_hinge_margin,
        hinge_reach=(center, HINGE_REACH * object_radius(state.gaussians, center)),
        # A held slide is a slide: the body's frame gave its line (RefineState.hold_slides).
        parts=[k for k in state.live_parts() if k not in state.held_slides],
    )
    qr, _ = state.motion.motion()
    angles = [round(math.degrees(float(a)), 3) for a in quat_angle(qr.detach())[1:]]
    types = ["prismatic" if p else "revolute" for p in state.motion.prismatic[1:].tolist()]
    state.events.append({"event": "joint_classification", "prismatic": list(switched),
                         "scores": scores, "types": types, "angles_deg": angles})
    # Any part below ε may have been rewritten (slide or initial hinge): fresh Adam moments.
    state.motion_optimizer = motion_optimizer(state.motion, c, state.extent)


def motion_loss(state: RefineState, candidate: PartMotion) -> float:
    """Photometric + depth loss of the hard-assigned model of `state` moved by `candidate`,
    over the scoring views on a black background, after `classify_tune_steps` motion-only
    steps on the candidate (tune_motion): how well a joint hypothesis explains the target
    images once it has had the same short chance to settle as every other one. No ground
    truth is involved. `candidate` is the caller's copy and is tuned in place."""
    tune_motion(state, candidate, state.config.classify_tune_steps)
    return image_loss(state, candidate)


def image_loss(state: RefineState, candidate: PartMotion) -> float:
    """Photometric + depth loss of the hard-assigned model of `state` moved by `candidate` as
    it is, over the scoring views on a black background."""
    with torch.no_grad():
        return float(scoring_loss(state, candidate))


def scoring_loss(state: RefineState, candidate: PartMotion) -> torch.Tensor:
    """image_loss as a tensor, differentiable in `candidate`'s motion where gradients are on."""
    views = state.scoring_views()
    terms = state.held_image_terms(candidate, views, [torch.zeros(3)] * len(views))
    return sum(terms.values())


def tune_motion(state: RefineState, candidate: PartMotion, steps: int) -> None:
    """`steps` Adam steps on the motion of `candidate` alone (the Gaussians held, hard
    assignment, as in the M-step), each on the next of the scoring views in turn over a black
    background: deterministic, and the same budget for every joint hypothesis. One view per
    step keeps it cheap; Adam's moments average over the cycle. A fresh optimizer with the
    M-step's learning rates; the motion of `state` and its optimizer are untouched."""
    if steps <= 0:
        return
    optimizer = motion_optimizer(candidate, state.config, state.extent)
    views = state.scoring_views()
    with torch.enable_grad():
        for step in range(steps):
            terms = state.held_image_terms(candidate, [views[step % len(views)]],
                                           [torch.zeros(3)])
            check_finite(terms, f"{state.name} joint scoring", step)
            optimizer.zero_grad(set_to_none=True)
            sum(terms.values()).backward()
            optimizer.step()


def _epsilon_prior(candidate: PartMotion, k: int, value: float, eps: float, margin: float,
                   turned: bool) -> float:
    """`value` (the loss of a reading of part k, once scored: the scorer may tune the
    candidate first), raised by `margin` x |value| when the reading goes against the paper's
    ε rule: a hinge turning less than `eps` radians, or a slide of a part that has `turned`
    at least `eps` in training. Within the margin (a near-tie) the rule decides."""
    qr, _ = candidate.motion()
    if bool(candidate.prismatic[k]):
        against = turned
    else:
        against = float(quat_angle(qr[k].detach())) < eps
    return value + margin * abs(value) if against else value


def _axis_out_of_reach(qr: torch.Tensor, qd: torch.Tensor,
                       reach: tuple[np.ndarray, float] | None) -> bool:
    """Whether the hinge axis of the motion (qr, qd) passes farther than reach = (centre,
    radius) from centre; False without `reach`."""
    if reach is None:
        return False
    center, radius = reach
    pivot = extract_joint(qr, qd, center, prismatic=False)["origin"]
    return float(np.linalg.norm(np.asarray(pivot) - np.asarray(center))) > radius


def classify_joints(
    motion: PartMotion,
    eps_deg: float = 10.0,
    score: Callable[[PartMotion], float] | None = None,
    init_motions: Sequence[Sequence[RigidMotion]] | None = None,
    small_hinge_margin: float = 0.0,
    hinge_reach: tuple[np.ndarray, float] | None = None,
    parts: Sequence[int] | None = None,
) -> list[int]:
    """Turns revolute parts whose rotation is below `eps_deg` into prismatic ones.

    Without `score` this is the paper's rule. With `score` (the photometric + depth loss of a
    candidate PartMotion, e.g. motion_loss) a part is ambiguous when it turned less than
    `eps_deg` or when stage 2 left it more than one guess (`init_motions[k-1]`: a list of
    (R, t), e.g. Stage2Result.candidates). An ambiguous part's readings — its current motion,
    its slide and the stage-2 guesses — are all scored and the lowest loss wins. This rescues
    hinges that stalled at a small angle, e.g. a door opened 180 degrees. The paper's rule
    stays as a prior on near-ties: a hinge reading that turns less than `eps_deg`, and a slide
    reading of a part that turned at least `eps_deg`, count `small_hinge_margin` (relative)
    higher, so they win only when the images prefer them clearly. A hinge contains the slide
    (angle 0), so tuned by the scorer it can always match the slide; on near-ties it would win
    by noise. A door that turned 38 degrees lost to its slide by 0.7 % of a loss the images
    of a quick model barely resolve (a real fridge); the images, not noise, must overturn
    what training found. With `hinge_reach` (centre, radius), a hinge below `eps_deg` whose
    axis passes farther than radius from centre is typed prismatic by the rule alone, unscored
    (see HINGE_REACH). Only the movable `parts` are decided (default: all; a part merged into
    another has no Gaussians left to judge it by). Returns the parts made prismatic; the
    caller rebuilds the optimizer state of `motion`.
    """
    if init_motions is not None and len(init_motions) != motion.num_parts - 1:
        raise ValueError(
            f"init_motions: expected {motion.num_parts - 1} entries, got {len(init_motions)}"
        )
    guesses = [list(e) for e in init_motions] if init_motions is not None else None
    qr, qd = motion.motion()
    angles = quat_angle(qr.detach())
    eps = math.radians(eps_deg)
    switched = []
    for k in range(1, motion.num_parts) if parts is None else parts:
        if bool(motion.prismatic[k]):
            continue
        small = float(angles[k]) < eps
        extra = guesses[k - 1] if guesses is not None else []
        if score is None or (small and _axis_out_of_reach(qr[k], qd[k], hinge_reach)):
            if small:
                motion.set_prismatic(k)
        elif small or len(extra) > 1:
            readings = joint_readings(motion, k, extra)
            losses = [_epsilon_prior(cand, k, float(score(cand)), eps, small_hinge_margin,
                                     not small)
                      for _, cand in readings]
            resolve_ambiguous_joint(motion, k, readings, losses)
        if bool(motion.prismatic[k]):
            switched.append(k)
    return switched
