"""`gear.losses.knn_consistency_loss` as one op of the native executor: the mean distance
between each Gaussian's part logits and its neighbours', with its gradient, in one pass over
the pairs (Rust) instead of a gathered [N, n, K] tensor and a scattered gradient.

    loss = fused_knn_consistency(logits, neighbours)

Same value and gradient as the torch reference (which the tests compare it with): negative
neighbour indices are padding, pairs whose logits agree pass a zero gradient, no valid pair
gives 0. float32 for training, float64 for gradient checks. A non-finite logit or an index
>= N raises a ValueError.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from gear import _core
from gear.splat import as_numpy

__all__ = ["fused_knn_consistency"]


class _KnnConsistency(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, logits: Tensor, neighbours: Tensor) -> Tensor:
        # The gradient comes with the value (the pass is the same); the backward scales it.
        loss, grad = _core.knn_consistency(as_numpy(logits), as_numpy(neighbours))
        ctx.save_for_backward(torch.from_numpy(grad))
        return torch.tensor(loss, dtype=logits.dtype)

    @staticmethod
    def backward(ctx: Any, grad_loss: Tensor) -> tuple[Tensor | None, None]:
        (grad,) = ctx.saved_tensors
        return (grad * grad_loss if ctx.needs_input_grad[0] else None), None


def fused_knn_consistency(logits: Tensor, neighbours: Tensor) -> Tensor:
    """Mean L2 distance between each Gaussian's part logits [N, K] (float32 or float64, CPU)
    and its neighbours' [N, n] (integer indices; negative = padding); differentiable in the
    logits."""
    for name, value in (("logits", logits), ("neighbours", neighbours)):
        if not isinstance(value, Tensor):
            raise TypeError(f"'{name}' must be a torch.Tensor, got {type(value).__name__}")
        if value.device.type != "cpu":
            raise ValueError(f"'{name}' must be on the CPU, got device {value.device}")
    if logits.dtype not in (torch.float32, torch.float64):
        raise TypeError(f"logits must be float32 or float64, got {logits.dtype}")
    if logits.dim() != 2 or neighbours.dim() != 2 or neighbours.shape[0] != logits.shape[0]:
        raise ValueError(f"logits [N, K] and neighbours [N, n] expected, got "
                         f"{list(logits.shape)} and {list(neighbours.shape)}")
    if neighbours.dtype.is_floating_point or neighbours.dtype == torch.bool:
        raise TypeError(f"neighbours must be integer indices, got {neighbours.dtype}")
    return _KnnConsistency.apply(logits, neighbours.to(torch.int64))
