"""The E-step's part supervision and the joint-type decision of stage 3 (METHOD.md section 4).

- region_pseudo_labels: 2D region masks (SAM-style, ids meaningless across images) vote on the
  part of each region from the rendered part probabilities.
- sam_ce_loss: cross-entropy of the rendered part logits against those labels.
- knn_consistency_loss: neighbouring Gaussians should carry the same part logits.
- classify_joints: a revolute part that barely turns becomes prismatic, optionally choosing
  between the readings by the images instead of by the threshold alone.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from gear.kinematics import PartMotion, quat_angle, resolve_ambiguous_joint, safe_norm

IGNORE = -1


def _check_image(t: torch.Tensor, name: str, ndim: int) -> None:
    if t.dim() != ndim:
        raise ValueError(f"{name}: expected {ndim} dimensions, got shape {list(t.shape)}")


def region_pseudo_labels(
    prob: torch.Tensor | np.ndarray,
    regions: torch.Tensor | np.ndarray,
    prismatic: torch.Tensor | Sequence[bool],
    gamma: float = 4.0,
    min_conf: float = 0.5,
    min_gap: float = 0.2,
    min_area: int = 50,
) -> torch.Tensor:
    """Per-pixel part labels [H, W] int64 from rendered part probabilities [H, W, K].

    For each region u (id > 0): votes[u, c] = sum of p(pixel, c) over its pixels, with the votes
    of prismatic parts multiplied by `gamma` (small, often occluded drawers would otherwise be
    outvoted by the static body). The region's argmax replaces its pixels' own argmax when the
    region is trusted: mean over its pixels of the max probability > min_conf, mean top-1 minus
    top-2 gap > min_gap, and area >= min_area pixels. Pixels of untrusted regions keep their own
    argmax; pixels outside every region (id 0) are IGNORE (-1).
    """
    prob = torch.as_tensor(prob)
    _check_image(prob, "prob", 3)
    regions = torch.as_tensor(np.asarray(regions) if not torch.is_tensor(regions) else regions)
    if regions.shape != prob.shape[:2]:
        raise ValueError(
            f"regions: shape {list(regions.shape)} does not match prob {list(prob.shape[:2])}"
        )
    num_parts = prob.shape[-1]
    boost = torch.as_tensor(prismatic, dtype=torch.bool, device=prob.device).reshape(-1)
    if boost.numel() != num_parts:
        raise ValueError(f"prismatic: expected {num_parts} flags, got {boost.numel()}")
    if num_parts < 2:
        raise ValueError(f"prob: needs at least 2 parts in the last dimension, got {num_parts}")

    p = prob.detach().reshape(-1, num_parts)
    labels = p.argmax(dim=-1)
    ids = regions.to(prob.device).reshape(-1).long()
    inside = ids > 0
    if not inside.any():
        return torch.full(prob.shape[:2], IGNORE, dtype=torch.int64, device=prob.device)

    # Compact the region ids of this image to 0..U-1.
    uniq, slot = torch.unique(ids[inside], return_inverse=True)
    num_regions = uniq.numel()
    pin = p[inside]
    top2 = pin.topk(2, dim=-1).values
    area = torch.zeros(num_regions, dtype=p.dtype, device=p.device).index_add_(
        0, slot, torch.ones_like(slot, dtype=p.dtype)
    )
    votes = torch.zeros(num_regions, num_parts, dtype=p.dtype, device=p.device)
    votes.index_add_(0, slot, pin)
    conf = torch.zeros_like(area).index_add_(0, slot, top2[:, 0]) / area
    gap = torch.zeros_like(area).index_add_(0, slot, top2[:, 0] - top2[:, 1]) / area
    weights = torch.where(boost, gamma, 1.0).to(p.dtype)
    region_label = (votes * weights).argmax(dim=-1)
    trusted = (conf > min_conf) & (gap > min_gap) & (area >= min_area)

    inside_labels = torch.where(trusted[slot], region_label[slot], labels[inside])
    labels = torch.full_like(labels, IGNORE)
    labels[inside] = inside_labels
    return labels.reshape(prob.shape[:2])


def sam_ce_loss(
    logit_image: torch.Tensor,
    labels: torch.Tensor,
    fg_mask: torch.Tensor,
    static_weight: float = 1.2,
) -> torch.Tensor:
    """Class-weighted cross-entropy of rendered part logits [H, W, K] against pseudo-labels,
    over foreground pixels with a label (the static class weighted by `static_weight`).

    Zero (still connected to the graph) when no pixel qualifies.
    """
    _check_image(logit_image, "logit_image", 3)
    if labels.shape != logit_image.shape[:2] or fg_mask.shape != logit_image.shape[:2]:
        raise ValueError(
            f"labels {list(labels.shape)} and fg_mask {list(fg_mask.shape)} must match "
            f"logit_image {list(logit_image.shape[:2])}"
        )
    num_parts = logit_image.shape[-1]
    keep = fg_mask.to(torch.bool) & (labels >= 0)
    if not keep.any():
        return logit_image.sum() * 0.0
    weight = torch.ones(num_parts, dtype=logit_image.dtype, device=logit_image.device)
    weight[0] = static_weight
    return F.cross_entropy(logit_image[keep], labels[keep].long(), weight=weight)


def knn_consistency_loss(logits: torch.Tensor, neighbours: torch.Tensor) -> torch.Tensor:
    """Mean L2 distance between each Gaussian's part logits [N, K] and its neighbours' [N, n].

    Negative neighbour indices (padding when fewer points than neighbours exist) are skipped.
    The gradient is zero, not NaN, where the logits already agree.
    """
    if logits.dim() != 2 or neighbours.dim() != 2 or neighbours.shape[0] != logits.shape[0]:
        raise ValueError(
            f"logits [N, K] and neighbours [N, n] expected, got {list(logits.shape)} and "
            f"{list(neighbours.shape)}"
        )
    if neighbours.numel() and int(neighbours.max()) >= logits.shape[0]:
        raise ValueError(f"neighbours: index {int(neighbours.max())} >= N = {logits.shape[0]}")
    valid = neighbours >= 0
    if not valid.any():
        return logits.sum() * 0.0
    idx = neighbours.clamp(min=0).long()
    dist = safe_norm(logits[:, None, :] - logits[idx], dim=-1)
    return dist[valid].mean()


Motion = tuple[np.ndarray, np.ndarray]


def _as_candidates(entry: Motion | Sequence[Motion]) -> list[Motion]:
    """One part's stage-2 guesses: a bare (R, t) pair or a list of them."""
    try:
        bare = np.asarray(entry[0], float).shape == (3, 3) and np.asarray(entry[1], float).size == 3
    except (ValueError, TypeError):  # a list of pairs does not convert to one float array
        bare = False
    return [entry] if bare else list(entry)


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
    init_motions: Sequence[Motion | Sequence[Motion]] | None = None,
    small_hinge_margin: float = 0.0,
) -> list[int]:
    """Turns revolute parts whose rotation is below `eps_deg` into prismatic ones.

    Without `score` this is the paper's rule. With `score` (the photometric + depth loss of a
    candidate PartMotion, see kinematics.resolve_ambiguous_joint) a part is ambiguous when it
    turned less than `eps_deg` or when stage 2 left it more than one guess
    (`init_motions[k-1]`: an (R, t) or a list of them, e.g. CoarseInit.candidates). An
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
    guesses = [_as_candidates(e) for e in init_motions] if init_motions is not None else None
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
