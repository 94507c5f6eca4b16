"""Stage 3's merging of parts read twice: a movable part whose Gaussians another part's motion,
or staying put, moves onto the target images about as well as its own motion is not a part of
its own (a fragment of a blade or of a lid that stage 2 gave a motion of its own); its
Gaussians join the other part (docs/method.md, "Parts read twice")."""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from gear import geometry
from gear.articulation import PartMotion
from gear.kinematics import dq_to_rt, quat_angle
from gear.pipeline.stage2.parts import IN_LINE_SHARE
from gear.pipeline.stage2.voxels import Scale
from gear.pipeline.stage3.joint_types import image_loss
from gear.pipeline.stage3.joints import object_center, object_radius, solid_means
from gear.pipeline.stage3.shared import RefineState
from gear.splats import Gaussians

# A part merges when another motion costs it at most this share of what its own motion gains
# over staying put (both in the image loss of the target views).
MERGE_SHARE = 0.1
# Halves of one part that stage 2 cut along its hinge (stage2.stacked) join only when one's
# motion costs the other at most this share of its gain. Both start from one motion and see the
# same images, so one door's halves end within noise of each other (cabinet_upper at fast:
# 0.06 %), while two doors stacked on one hinge line and turned 2.4 and 4.3 degrees apart cost
# 6.4 % (cabinet_upper's 29.0 / 26.6) and 12 % (the cupboard's 22.6 / 18.3).
HALVES_MERGE_SHARE = 0.02
# ...unless the E-step has given one half's Gaussians to the other: a half left with at most this
# share of the pair's Gaussians joins its partner whatever its motion costs. The fast fridge's
# door, cut in halves by stage 2, ended with 123 Gaussians in one half against 27,056 in the
# other (0.45 %), the remnant's motion 4.9 degrees off the door's (a cost of 3.7 % of its gain);
# the halves of two real doors hold thousands each (fridge-180: 10,513 / 9,456).
EMPTIED_HALF_SHARE = 0.05
# A part whose own motion gains less than this share of the largest gain of any movable part
# is not seen to move: it joins whichever part (or the static one) explains it no worse than
# staying put. Real parts, fast and quick suites: 0.17 of the largest and up; sink_base's
# leftovers of stage 2 (a strip inside the cabinet, a door's corner): 0.002 and 0.005.
UNSEEN_GAIN_SHARE = 0.03
# A movable part is one body: at least this share of its opaque centres lie in the largest
# 26-connected piece of their cells (BODY_CELLS times stage 2's fine voxel, grown by one cell).
# A part below it is strays the E-step gathered under a motion that hides them from the target
# views, and is judged as a part not seen to move. Real parts, fast suite: 0.84 and up (0.66
# for two doors stage 2 read as one part); such gatherings (sink_base): 0.19, 0.37, 0.38.
BODY_SHARE = 0.5
BODY_CELLS = 2.0
# ...unless its own motion gains at least this share of the largest gain: then it is seen to
# move whatever its opaque centres look like. Strays hide from the target views (sink_base's:
# 0.031); a door can have few opaque centres at the joint-type decision (cabinet_upper at
# fast: 153 of its 6994, 0.458 in one piece, all its centres 0.995) while gaining 0.45; a half
# of a door the body test joined to its other half (cabinet_tall at fast) gained 0.12-0.17.
NO_BODY_GAIN_SHARE = 0.25
# A part joins a sliding part only in line with it (as in stage 2): the box bounding the
# slide's body (the largest piece of its opaque centres, the body test's) across the slide
# spans the 2nd-98th percentiles of those centres (a stray Gaussian does not stretch it) grown
# by this share of the object's radius.
IN_LINE_MARGIN_RADII = 0.06
IN_LINE_TRIM = 0.02
# How far below a Gaussian's lowest logit a merged part's logit is set: its soft weight (e^-20)
# and the gradient it would draw are nil, so the E-step does not regrow the part.
FORGET_LOGIT = 20.0


@dataclass(frozen=True)
class Merge:
    """Part `part` joined part `into` (0: the static part). `gain`: how much lower the image
    loss is with the part moving by its own motion than staying put; `cost`: how much higher
    it is with the part moving by `into`'s motion instead of its own."""

    part: int
    into: int
    gain: float
    cost: float

    def record(self) -> dict:
        return {"part": self.part, "into": self.into, "gain": self.gain, "cost": self.cost}


def merge_parts(state: RefineState, apart: Sequence[tuple[int, int]] = (),
                halves: Sequence[tuple[int, int]] = ()) -> list[Merge]:
    """Merges, one at a time and smallest part first, every movable part of `state` that
    another part's motion (or the identity) explains within MERGE_SHARE of what its own
    explains (HALVES_MERGE_SHARE for the two parts of a pair of `halves`, whatever it costs
    for a half left with under EMPTIED_HALF_SHARE of the pair's Gaussians), and that lies in
    line with that part when it slides; no part joins its partner in a pair of `apart`. A part
    whose own motion gains at most UNSEEN_GAIN_SHARE of the largest gain, or that is no body
    (BODY_SHARE) and gains under NO_BODY_GAIN_SHARE of it, joins the part that explains it
    best, so long as no worse than staying put.
    A merged part keeps its column of logits and its motion (set to the other part's) but no
    Gaussian: the run's outputs drop it. Returns the merges in the order made."""
    kept_apart = {frozenset(pair) for pair in apart}
    shares = {frozenset(pair): HALVES_MERGE_SHARE for pair in halves}
    cell = _body_cell(state.gaussians)
    merges = []
    while (merge := _next_merge(state, kept_apart, shares, cell)) is not None:
        _apply(state, merge)
        merges.append(merge)
    return merges


def _next_merge(state: RefineState, kept_apart: set[frozenset[int]],
                shares: dict[frozenset[int], float], cell: float) -> Merge | None:
    """The first merge merge_parts makes on `state` as it is, or None; `shares`: the merge
    share of the pairs that do not use MERGE_SHARE; `cell`: the body test's voxel size."""
    ids = state.gaussians.part_ids()
    counts = torch.bincount(ids, minlength=state.motion.num_parts).tolist()
    live = state.live_parts()
    base = image_loss(state, state.motion)
    gains = {k: image_loss(state, moved_like(state.motion, k, 0)) - base for k in live}
    largest = max(gains.values(), default=0.0)
    for k in sorted(live, key=lambda k: (counts[k], k)):
        gain = gains[k]
        unseen_part = gain <= UNSEEN_GAIN_SHARE * largest or (
            gain < NO_BODY_GAIN_SHARE * largest
            and _body_share(solid_means(state.gaussians, ids == k), cell) < BODY_SHARE)
        costs = {0: gain} | {j: image_loss(state, moved_like(state.motion, k, j)) - base
                             for j in live if j != k}
        for into in sorted(costs, key=lambda j: (costs[j], j)):
            pair = frozenset((k, into))
            share = shares.get(pair, MERGE_SHARE)
            allowed = max(share * max(gain, 0.0), gain if unseen_part else -math.inf)
            if pair in shares and counts[k] <= EMPTIED_HALF_SHARE * (counts[k] + counts[into]):
                allowed = math.inf  # the images gave (nearly) all of this half to the other
            if costs[into] > allowed or pair in kept_apart:
                continue
            if into == 0 or _in_line(state, ids, k, into, cell):
                return Merge(k, into, gain, costs[into])
    return None


def _body_cell(g: Gaussians) -> float:
    """The body test's voxel: BODY_CELLS times stage 2's fine voxel for the opaque centres of
    the whole model (inf when they have no extent: every part is then one body)."""
    solid = solid_means(g).numpy()
    if len(solid) < 2 or not Scale.extent_of(solid) > 0:
        return math.inf
    return BODY_CELLS * Scale.of(solid).voxel_size(single_part=False)


def _body_share(points: torch.Tensor, cell: float) -> float:
    """The share of `points` [N, 3] in their largest 26-connected piece at `cell` (1 when
    there are none or the cell is infinite)."""
    return len(_body(points, cell)) / len(points) if len(points) else 1.0


def _body(points: torch.Tensor, cell: float) -> np.ndarray:
    """Those of `points` [N, 3] in their largest 26-connected piece at `cell` (all of them
    when the cell is infinite)."""
    points = points.numpy()
    if len(points) == 0 or not math.isfinite(cell):
        return points
    labels = geometry.piece_labels([points], cell)[0]
    return points[labels == np.bincount(labels).argmax()]


def moved_like(motion: PartMotion, k: int, j: int) -> PartMotion:
    """A copy of `motion` with part k moved by part j's motion (the identity for j = 0)."""
    qr, qd = motion.motion()
    out = copy.deepcopy(motion)
    out.set_part(k, qr[j].detach(), qd[j].detach(), prismatic=bool(motion.prismatic[j]))
    return out


def _in_line(state: RefineState, ids: torch.Tensor, k: int, j: int, cell: float) -> bool:
    """Whether part k may join part j: always when j turns (by ε or more), else when at least
    IN_LINE_SHARE of k's opaque centres lie in line with j's body (the largest piece of its
    opaque centres at `cell`) along j's slide. Two drawers of a column pulled by the same
    travel are explained by one motion but are two parts. The body, not all of j's centres:
    a drawer hidden in the cabinet in one state is matter the E-step can give strays to, and
    those can lie anywhere on the front (storage7 at fast: 696 opaque centres spanning both
    columns and every row, which put every part 'in line' with the drawer)."""
    qr, qd = state.motion.motion()
    if float(quat_angle(qr[j].detach())) >= math.radians(state.config.revolute_eps_deg):
        return True
    g = state.gaussians
    direction = dq_to_rt(qr[j].detach(), qd[j].detach())[1].numpy()
    margin = IN_LINE_MARGIN_RADII * object_radius(g, object_center(g))
    share = geometry.share_in_line(solid_means(g, ids == k).numpy(),
                                   _body(solid_means(g, ids == j), cell), direction, margin,
                                   trim=IN_LINE_TRIM)
    return share >= IN_LINE_SHARE


@torch.no_grad()
def _apply(state: RefineState, merge: Merge) -> None:
    """Part `merge.part`'s Gaussians go to `merge.into` (their two logits swapped, so each
    keeps its confidence); its logit is then set FORGET_LOGIT below every Gaussian's lowest,
    and its motion to `merge.into`'s."""
    k, j = merge.part, merge.into
    logits = state.gaussians["logits"]
    rows = logits.argmax(dim=1) == k
    mine, theirs = logits[rows, k].clone(), logits[rows, j].clone()
    logits[rows, j], logits[rows, k] = mine, theirs
    logits[:, k] = logits.min(dim=1).values - FORGET_LOGIT
    qr, qd = state.motion.motion()
    state.motion.set_part(k, qr[j], qd[j], prismatic=bool(state.motion.prismatic[j]))
    state.held_slides.pop(k, None)  # it moves as `into` now
