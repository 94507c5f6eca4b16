"""View-dependent colour from real spherical harmonics (degree 0..3), a differentiable op run
before the rasterizer (docs/raster-contract.md, "View-dependent colour"):

    rgb = sh_to_rgb(dirs, coeffs)        # dirs [N,3], coeffs [N,(d+1)^2,3] -> rgb [N,3]
    rgb = max(sum_k coeffs[:, k] * Y_k(dirs / |dirs|) + 0.5, 0)

with the basis and constants of 3D Gaussian Splatting. Gradients flow to `coeffs` and to
`dirs` (through the normalisation); a direction shorter than 1e-12 counts as the zero vector
(only the k = 0 term remains) and gets a zero gradient, so nothing becomes NaN.

float32 inputs run on the executor `backend` ("cpu", "wgpu", None = GEAR_BACKEND, as for
gear.splat.rasterize); float64 inputs run the f64 CPU reference (for gradient checks).
Non-finite inputs raise a ValueError.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from gear import _core
from gear.splat import as_numpy, resolve_backend

__all__ = ["MAX_DEGREE", "SH_C0", "coefficient_count", "sh_to_rgb"]

MAX_DEGREE = 3
SH_C0 = 0.28209479177387814  # Y_0: the degree-0 term of a colour is SH_C0 * coeffs[:, 0]


def coefficient_count(degree: int) -> int:
    """Coefficients per colour channel at `degree`: (degree + 1)^2."""
    return (degree + 1) ** 2


class _ShToRgb(torch.autograd.Function):
    """rgb [N,3] from dirs [N,3] and coeffs [N,K,3]; gradients to both."""

    @staticmethod
    def forward(ctx: Any, dirs: Tensor, coeffs: Tensor, backend: str) -> Tensor:
        d, c = as_numpy(dirs), as_numpy(coeffs)
        if dirs.dtype == torch.float64:
            rgb = _core.sh_reference_forward(d, c)
        else:
            rgb = _core.sh_to_rgb(d, c, backend)
        ctx.save_for_backward(dirs, coeffs)
        ctx.backend = backend
        return torch.from_numpy(rgb)

    @staticmethod
    def backward(ctx: Any, grad_rgb: Tensor) -> tuple[Tensor | None, ...]:
        dirs, coeffs = ctx.saved_tensors
        d, c = as_numpy(dirs), as_numpy(coeffs)
        g = as_numpy(grad_rgb.to(dirs.dtype))
        if dirs.dtype == torch.float64:
            grad_coeffs, grad_dirs = _core.sh_reference_backward(d, c, g)
        else:
            grad_coeffs, grad_dirs = _core.sh_to_rgb_backward(d, c, g, ctx.backend)
        wanted = ctx.needs_input_grad
        return (
            torch.from_numpy(grad_dirs) if wanted[0] else None,
            torch.from_numpy(grad_coeffs) if wanted[1] else None,
            None,
        )


def sh_to_rgb(dirs: Tensor, coeffs: Tensor, backend: str | None = None) -> Tensor:
    """Colours [N,3] of N Gaussians seen along `dirs` [N,3] (from each Gaussian towards the
    camera, in the frame the coefficients live in) with `coeffs` [N,K,3], K = 1, 4, 9 or 16:
    CPU tensors, both float32 or both float64 (see the module docstring)."""
    for name, value in (("dirs", dirs), ("coeffs", coeffs)):
        if not isinstance(value, Tensor):
            raise TypeError(f"'{name}' must be a torch.Tensor, got {type(value).__name__}")
        if value.dtype not in (torch.float32, torch.float64):
            raise TypeError(f"'{name}' must be float32 or float64, got {value.dtype}")
        if value.device.type != "cpu":
            raise ValueError(f"'{name}' must be on the CPU, got device {value.device}")
    if dirs.dtype != coeffs.dtype:
        raise TypeError(f"'dirs' and 'coeffs' must share a dtype, got {dirs.dtype} and "
                        f"{coeffs.dtype}")
    if dirs.dim() != 2 or dirs.shape[1] != 3:
        raise ValueError(f"'dirs' must have shape [N, 3], got {list(dirs.shape)}")
    n = dirs.shape[0]
    counts = [coefficient_count(d) for d in range(MAX_DEGREE + 1)]
    if coeffs.dim() != 3 or coeffs.shape[0] != n or coeffs.shape[2] != 3 or (
        coeffs.shape[1] not in counts
    ):
        raise ValueError(f"'coeffs' must have shape [{n}, K, 3] with K in {counts}, got "
                         f"{list(coeffs.shape)}")
    executor = resolve_backend(backend)
    return _ShToRgb.apply(dirs, coeffs, executor)
