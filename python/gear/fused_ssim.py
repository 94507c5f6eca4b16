"""`gear.losses.ssim_reference` as one op of the native executor: the mean SSIM of two
[H, W, C] images and its gradient with respect to the first, computed together (Rust: separable
blurs over whole rows, channels in parallel) instead of torch's depthwise convolutions and ~30
elementwise kernels with their backward.

    value = fused_ssim(render, target)

The gradient flows to the first image only (the render; the target is data):
`gear.losses.ssim` calls this op when the second needs none, the torch form otherwise.
float32 for training, float64 for gradient checks; a non-finite value raises a ValueError.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from gear import _core
from gear.splat import as_numpy

__all__ = ["fused_ssim"]


class _FusedSsim(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, a: Tensor, b: Tensor) -> Tensor:
        # The gradient comes with the value (they share the blurred moments).
        value, grad = _core.ssim(as_numpy(a), as_numpy(b), bool(ctx.needs_input_grad[0]))
        if grad is not None:
            ctx.save_for_backward(torch.from_numpy(grad))
        return torch.tensor(value, dtype=a.dtype)

    @staticmethod
    def backward(ctx: Any, grad_value: Tensor) -> tuple[Tensor, None]:
        (grad,) = ctx.saved_tensors
        return grad * grad_value, None


def fused_ssim(a: Tensor, b: Tensor) -> Tensor:
    """Mean SSIM of the [H, W, C] CPU images `a` and `b` (one float dtype), differentiable in
    `a` only."""
    if b.requires_grad and torch.is_grad_enabled():
        raise ValueError("fused_ssim: the second image must not need a gradient")
    if a.dtype != b.dtype or a.dtype not in (torch.float32, torch.float64):
        raise TypeError(f"fused_ssim: two float32 or two float64 images expected, got "
                        f"{a.dtype} and {b.dtype}")
    return _FusedSsim.apply(a, b)
