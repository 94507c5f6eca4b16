"""The losses of training (torch, [H,W,C] images): photometric, depth and opacity terms of
stages 1 and 3, and the E-step's part supervision (docs/method.md, "Losses"). SSIM runs as a
native op (gear.fused_ssim) wherever only the render needs a gradient; `ssim_reference` is its
torch form.

- region_pseudo_labels: 2D region masks (SAM-style, ids meaningless across images) vote on the
  part of each region from the rendered part probabilities.
- sam_ce_loss: cross-entropy of the rendered part logits against those labels.
- knn_consistency_loss: neighbouring Gaussians should carry the same part logits.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from gear.fused_ssim import fused_ssim
from gear.kinematics import safe_norm

_SSIM_WINDOW = 11
_SSIM_SIGMA = 1.5
_SSIM_C1 = 0.01**2
_SSIM_C2 = 0.03**2


def _gaussian_kernel(dtype: torch.dtype) -> torch.Tensor:
    x = torch.arange(_SSIM_WINDOW, dtype=dtype) - (_SSIM_WINDOW - 1) / 2
    g = torch.exp(-(x**2) / (2 * _SSIM_SIGMA**2))
    return g / g.sum()


def ssim(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Mean structural similarity of two [H,W,C] images in [0,1] (11x11 Gaussian window,
    zero padding): the native op (gear.fused_ssim) when only `a` may need a gradient, as in
    every photometric loss, else the torch form below."""
    _check_ssim_shapes(a, b)
    native = (a.device.type == "cpu" and b.device.type == "cpu" and a.dtype == b.dtype
              and a.dtype in (torch.float32, torch.float64))
    if not native or (b.requires_grad and torch.is_grad_enabled()):
        return ssim_reference(a, b)
    if not (bool(torch.isfinite(a).all()) and bool(torch.isfinite(b).all())):
        # The native op refuses non-finite images; the torch form lets the NaN reach the
        # loss, where training stops naming the stage, iteration and term.
        return ssim_reference(a, b)
    return fused_ssim(a, b)


def _check_ssim_shapes(a: torch.Tensor, b: torch.Tensor) -> None:
    if a.shape != b.shape or a.dim() != 3:
        raise ValueError(f"ssim: expected two [H,W,C] images of one shape: {a.shape}, {b.shape}")


def ssim_reference(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """The torch form of `ssim`, computed with a separable blur (two 1-D passes);
    differentiable in both images."""
    _check_ssim_shapes(a, b)
    channels = a.shape[2]
    g = _gaussian_kernel(a.dtype)
    pad = _SSIM_WINDOW // 2
    # the five blurred maps in one batch: x, y, x², y², xy
    x = a.permute(2, 0, 1)
    y = b.permute(2, 0, 1)
    stack = torch.cat([x, y, x * x, y * y, x * y])[None]
    n = stack.shape[1]
    rows = g.reshape(1, 1, 1, -1).expand(n, 1, 1, _SSIM_WINDOW)
    cols = g.reshape(1, 1, -1, 1).expand(n, 1, _SSIM_WINDOW, 1)
    blurred = F.conv2d(F.conv2d(stack, rows, padding=(0, pad), groups=n), cols,
                       padding=(pad, 0), groups=n)[0]
    mu_x, mu_y, xx, yy, xy = blurred.split(channels)
    var_x = xx - mu_x**2
    var_y = yy - mu_y**2
    cov = xy - mu_x * mu_y
    num = (2 * mu_x * mu_y + _SSIM_C1) * (2 * cov + _SSIM_C2)
    den = (mu_x**2 + mu_y**2 + _SSIM_C1) * (var_x + var_y + _SSIM_C2)
    return (num / den).mean()


def photometric(render: torch.Tensor, target: torch.Tensor, lambda_dssim: float) -> torch.Tensor:
    """(1 - λ) L1 + λ (1 - SSIM): the paper's 0.8 / 0.2 mix with λ = λ_D-SSIM."""
    l1 = (render - target).abs().mean()
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - ssim(render, target))


def depth_log_l1(rendered: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """mean log(1 + |D̂ − D|) over pixels with valid target depth (> 0); 0 when none."""
    valid = target > 0
    if not bool(valid.any()):
        return rendered.sum() * 0.0
    return torch.log1p((rendered[valid] - target[valid]).abs()).mean()


def opacity_binarisation(opacity_logits: torch.Tensor) -> torch.Tensor:
    """BCE(o, o > 0.5): pushes every opacity towards 0 or 1."""
    if opacity_logits.numel() == 0:
        return opacity_logits.sum()
    target = (opacity_logits.detach() > 0).to(opacity_logits.dtype)
    return F.binary_cross_entropy_with_logits(opacity_logits, target)


def composite(rgb: torch.Tensor, alpha: torch.Tensor, background: torch.Tensor) -> torch.Tensor:
    """Straight colour [H,W,3] with alpha [H,W] over a background colour [3]."""
    a = alpha[..., None]
    return rgb * a + background * (1.0 - a)


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
    # index_select rather than logits[idx]: the same values, and its backward is a plain
    # index_add (advanced indexing's accumulating index_put is slower).
    others = logits.index_select(0, idx.reshape(-1)).reshape(*idx.shape, logits.shape[1])
    dist = safe_norm(logits[:, None, :] - others, dim=-1)
    return dist.mean() if bool(valid.all()) else dist[valid].mean()
