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
from gear.geometry import NearestTree
from gear.metrics import rotation_angle_deg
from gear.pipeline.stage2.hypotheses import axis_of, dominant_plane

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
# Two doors stacked on one hinge line and turned by different angles show it in their faces:
# the halves' dominant planes (within a voxel) lie as far from parallel as the doors' angles
# differ, in whichever state the doors are open. A part whose halves' faces lie within this
# of parallel in both states is one slab and is not cut. Fast models: a real cupboard's two
# stacked pairs (4.3 and 9.4 degrees apart) 4.5 and 10.4; one fridge door turned 176 degrees
# 0.8 (cut, its halves ended stage 3 a degree apart and stayed two parts).
MIN_HALVES_TILT_DEG = 2.0
# Target centres within this many voxels of a half moved by the part's motion are its face
# in the target state.
NEAR_VOXELS = 2.0


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


def _faces_tilt(first: np.ndarray, second: np.ndarray, voxel_size: float) -> float | None:
    """The angle in degrees between the dominant planes (within `voxel_size`) of two point
    sets, or None when either has none."""
    planes = [dominant_plane(points, voxel_size) if len(points) >= 3 else None
              for points in (first, second)]
    if planes[0] is None or planes[1] is None:
        return None
    cosine = abs(float(planes[0].axes[-1] @ planes[1].axes[-1]))
    return float(np.degrees(np.arccos(min(1.0, cosine))))


def halves_tilt(means: np.ndarray, beyond: np.ndarray, motion: RigidMotion,
                target: np.ndarray | None, voxel_size: float) -> float | None:
    """How far from parallel the faces of a part's two halves lie (degrees), the larger over
    the canonical state (the halves' centres `means[beyond]`, `means[~beyond]`) and the
    target state (the `target` centres within NEAR_VOXELS of each half moved by `motion`, when
    given); None when a half has no dominant plane in either state."""
    tilts = [_faces_tilt(means[beyond], means[~beyond], voxel_size)]
    if target is not None and len(target):
        rot, trans = (np.asarray(m, dtype=np.float64) for m in motion)
        tree = NearestTree(target)
        near = []
        for half in (beyond, ~beyond):
            distance, index = tree.query(means[half] @ rot.T + trans)
            near.append(target[np.unique(index[distance <= NEAR_VOXELS * voxel_size])])
        tilts.append(_faces_tilt(near[0], near[1], voxel_size))
    known = [t for t in tilts if t is not None]
    return max(known) if known else None


def split_stacked(
    logits: np.ndarray, candidates: list[list[RigidMotion]], means: np.ndarray,
    voxel_size: float, target: np.ndarray | None = None,
) -> tuple[np.ndarray, list[list[RigidMotion]], list[tuple[int, int]], list[str]]:
    """Part logits [N, K] and per-movable-part motion candidates with every candidate for two
    stacked doors (stacked_cut of the canonical centres `means` [N, 3] whose largest logit is
    its, at stage 2's `voxel_size`) cut in two: the half beyond the median becomes a new part,
    last, with the same candidates. Everyone's logit of the new part is a copy of the cut
    part's, but for the halves: the moved half keeps the cut part's (seeded) logit for the new
    part and takes its lowest logit for the cut part, the other half its lowest for the new
    part. A candidate whose halves' faces lie within MIN_HALVES_TILT_DEG of parallel in both
    states (halves_tilt; the `target` state's centres, when given) is one slab, left whole.
    Returns them, the pairs of halves (cut part, new part) and a note per candidate."""
    owner = logits.argmax(axis=1)
    out = logits.copy()
    out_candidates = list(candidates)
    halves, notes = [], []
    for part, motions in enumerate(candidates, start=1):
        members = np.flatnonzero(owner == part)
        beyond = stacked_cut(means[members], motions[0], voxel_size)
        if beyond is None:
            continue
        tilt = halves_tilt(means[members], beyond, motions[0], target, voxel_size)
        if tilt is not None and tilt < MIN_HALVES_TILT_DEG:
            notes.append(f"part {part}: tall along its hinge, but one slab (its halves' faces "
                         f"{tilt:.1f} degrees from parallel): not cut")
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
