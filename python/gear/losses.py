"""Image and Gaussian losses of METHOD.md §2/§4 (torch, [H,W,C] images)."""

from __future__ import annotations

import torch
import torch.nn.functional as F

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
    zero padding), computed with a separable blur (two 1-D passes)."""
    if a.shape != b.shape or a.dim() != 3:
        raise ValueError(f"ssim: expected two [H,W,C] images of one shape: {a.shape}, {b.shape}")
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
    """(1 - λ) L1 + λ (1 - SSIM): the 0.8 / 0.2 mix of METHOD.md with λ = λ_D-SSIM."""
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
