"""`gear.kinematics.deform` as one fused op of the native executor: Gaussians moved by the
linear dual-quaternion blend of K part motions, forward and backward in one pass per Gaussian
(Rust threads) instead of a chain of [N, K] tensor operations.

    means_d, quats_d = fused_deform(means, quats, weights, qr, qd)
    means_d, quats_d = fused_deform(means, quats, logits, qr, qd, softmax=True)

Same maths and conventions as the torch reference (gear.kinematics.deform, which the tests
compare it with): each Gaussian's part motions are sign-aligned with its heaviest part, mixed
by its weights and normalised; gradients flow to all five inputs (to qr and qd only when they
require them). With `softmax=True` the third input holds part logits and each Gaussian's
weights are their softmax (torch's softmax along a short last dimension costs more than this
whole op). float32 for training; float64 runs the same code in double precision, for
gradient checks. Non-finite inputs raise a ValueError.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from gear import _core
from gear.splat import as_numpy

__all__ = ["fused_deform"]


class _FusedDeform(torch.autograd.Function):
    @staticmethod
    def forward(
        ctx: Any, means: Tensor, quats: Tensor, weights: Tensor, qr: Tensor, qd: Tensor,
        softmax: bool,
    ) -> tuple[Tensor, Tensor]:
        arrays = [as_numpy(t) for t in (means, quats, weights, qr, qd)]
        means_d, quats_d, softmax_weights = _core.deform(*arrays, softmax)
        ctx.save_for_backward(means, quats, weights, qr, qd)
        ctx.softmax = softmax
        # The per-Gaussian softmax, kept for the backward (which would compute it again).
        ctx.softmax_weights = softmax_weights
        return torch.from_numpy(means_d), torch.from_numpy(quats_d)

    @staticmethod
    def backward(
        ctx: Any, grad_means: Tensor | None, grad_quats: Tensor | None
    ) -> tuple[Tensor | None, ...]:
        inputs = ctx.saved_tensors
        means, quats = inputs[0], inputs[1]
        gm = torch.zeros_like(means) if grad_means is None else grad_means
        gq = torch.zeros_like(quats) if grad_quats is None else grad_quats
        wanted = ctx.needs_input_grad
        grads = _core.deform_backward(
            *[as_numpy(t) for t in inputs], as_numpy(gm.to(means.dtype)),
            as_numpy(gq.to(means.dtype)), wanted[3] or wanted[4], ctx.softmax,
            ctx.softmax_weights,
        )
        return *(
            torch.from_numpy(g) if want and g is not None else None
            for g, want in zip(grads, wanted[:5], strict=True)
        ), None


def fused_deform(
    means: Tensor, quats: Tensor, weights: Tensor, qr: Tensor, qd: Tensor, *,
    softmax: bool = False,
) -> tuple[Tensor, Tensor]:
    """Moves Gaussians (means [N,3], quats [N,4]) by the blend of K part motions (qr, qd
    [K,4]) with weights [N,K] (logits whose softmax per Gaussian gives the weights, with
    `softmax`); returns (means', quats'). CPU tensors of one dtype, float32 or float64 (see
    the module docstring)."""
    named = {"means": means, "quats": quats, "weights": weights, "qr": qr, "qd": qd}
    for name, value in named.items():
        if not isinstance(value, Tensor):
            raise TypeError(f"'{name}' must be a torch.Tensor, got {type(value).__name__}")
        if value.device.type != "cpu":
            raise ValueError(f"'{name}' must be on the CPU, got device {value.device}")
    dtypes = {t.dtype for t in named.values()}
    if len(dtypes) != 1 or means.dtype not in (torch.float32, torch.float64):
        raise TypeError("means, quats, weights, qr and qd must all be float32 or all float64, "
                        f"got {', '.join(str(t.dtype) for t in named.values())}")
    return _FusedDeform.apply(means, quats, weights, qr, qd, bool(softmax))
