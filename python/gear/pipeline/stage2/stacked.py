"""Stage 2's hand-off of doors that may be stacked on one hinge line: two doors above each other
on the same axis, opened by different angles (a cupboard's upper and lower doors, 40.7 and
31.3 degrees), form one dynamic piece, and the centres cannot tell them from one door: a
single real door's two halves, each fitted its own turn, differ by 2-3 degrees at a fast
model's noise, the stacked doors by 4-9 (docs/method.md, "Doors stacked on one hinge line").
So a hinged part at least STACK_ASPECT times taller along its axis than wide is handed to
stage 3 as two parts, cut across the axis at the median of its centres, with the same motion:
stage 3's images then fit each half's motion, and its merge of parts read twice
(stage3.merge) joins the halves again at its end when one motion explains both."""

from __future__ import annotations

import numpy as np

from gear import geometry
from gear.articulation import RigidMotion
from gear.metrics import rotation_angle_deg
from gear.pipeline.stage2.hypotheses import axis_of

# A part is cut in two when its extent along its hinge axis is at least this many times its
# extent across (along its widest direction perpendicular to the axis): doors stacked on one
# line are tall. A lever, a lid or a temple of glasses is thin along its hinge: never cut.
STACK_ASPECT = 1.5
# Extents between these percentiles of the part's centres (a stray Gaussian does not count).
EXTENT_PERCENTILES = (2.0, 98.0)
# Only turns of at least this many degrees: a hinge hardly opened shows no door apart.
MIN_TURN_DEG = 5.0
# Each half needs at least this many Gaussians.
MIN_HALF_GAUSSIANS = 50


def _extent(values: np.ndarray) -> float:
    low, high = np.percentile(values, EXTENT_PERCENTILES)
    return float(high - low)


def stacked_cut(means: np.ndarray, motion: RigidMotion, voxel_size: float) -> np.ndarray | None:
    """Which of a part's canonical centres `means` [M, 3] lie beyond the median along its hinge
    axis (that of `motion`, canonical -> target), when the part is a candidate for two stacked
    doors (tall along the axis, turned by MIN_TURN_DEG or more); else None. Its shape is that
    of its body, the largest piece of its centres connected at `voxel_size`: a real upper
    cabinet's pair of doors came from stage 2 with a chunk of the door across the cabinet
    (13 % of the part's centres, 1.4 away), which made the pair look as wide as tall."""
    rot = np.asarray(motion[0], dtype=np.float64)
    if len(means) < 2 * MIN_HALF_GAUSSIANS or rotation_angle_deg(rot) < MIN_TURN_DEG:
        return None
    axis = axis_of(rot)
    body = means[geometry.piece_labels([means], voxel_size)[0] == 1]
    along = body @ axis
    across = body - np.outer(along, axis)
    centred = across - across.mean(axis=0)
    widest = np.linalg.svd(centred, full_matrices=False)[2][0]
    if _extent(along) < STACK_ASPECT * _extent(centred @ widest):
        return None
    beyond = means @ axis > np.median(along)
    if min(beyond.sum(), (~beyond).sum()) < MIN_HALF_GAUSSIANS:
        return None
    return beyond


def split_stacked(
    logits: np.ndarray, candidates: list[list[RigidMotion]], means: np.ndarray,
    voxel_size: float,
) -> tuple[np.ndarray, list[list[RigidMotion]], list[tuple[int, int]], list[str]]:
    """Part logits [N, K] and per-movable-part motion candidates with every candidate for two
    stacked doors (stacked_cut of the canonical centres `means` [N, 3] whose largest logit is
    its, at stage 2's `voxel_size`) cut in two: the half beyond the median becomes a new part,
    last, with the same candidates. Everyone's logit of the new part is a copy of the cut
    part's, but for the halves: the moved half keeps the cut part's (seeded) logit for the new
    part and takes its lowest logit for the cut part, the other half its lowest for the new
    part. Returns them, the pairs of halves (cut part, new part) and a note per cut."""
    owner = logits.argmax(axis=1)
    out = logits.copy()
    out_candidates = list(candidates)
    halves, notes = [], []
    for part, motions in enumerate(candidates, start=1):
        members = np.flatnonzero(owner == part)
        beyond = stacked_cut(means[members], motions[0], voxel_size)
        if beyond is None:
            continue
        moved, stays = members[beyond], members[~beyond]
        column = logits[:, part].copy()
        column[stays] = logits[stays].min(axis=1)
        out[moved, part] = logits[moved].min(axis=1)
        out = np.concatenate([out, column[:, None]], axis=1)
        out_candidates.append(list(motions))
        halves.append((part, len(out_candidates)))
        notes.append(f"part {part}: tall along its hinge: one half ({len(moved)} "
                     f"Gaussians) is part {len(out_candidates)} until stage 3's images "
                     "join them")
    return out, out_candidates, halves, notes
