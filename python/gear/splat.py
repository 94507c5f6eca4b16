"""Differentiable Gaussian rasterization: a torch.autograd.Function over two executors of one
contract, the wgpu kernels and a native multi-threaded CPU executor.

    out = rasterize(means, quats, log_scales, opacity_logits, features, camera)
    out.features  [H,W,C] = sum_i w_i f_i + T_final * background
    out.alpha     [H,W]   = 1 - T_final
    out.depth     [H,W]   = sum_i w_i z_i (camera-space z), only with depth=True
with w_i = alpha_i T_i, opacity = sigmoid(opacity_logits), scale = exp(log_scales) and
quaternions (w, x, y, z), unnormalised. The maths is the rasterizer contract
(docs/raster-contract.md); gear.splat_reference is the same in pure torch.

Executor: `backend="cpu"` or `"wgpu"`; None follows the environment variable GEAR_BACKEND
(`auto`, `cpu` or `wgpu`; default `auto`: the CPU executor when the wgpu adapter is a software
one (lavapipe, SwiftShader, WARP) or none can be created, else wgpu). The CPU executor uses
GEAR_THREADS threads (default: every core); its gradients are bit-identical for any count.

Gaussians that stay put over many renders from one camera (stage 3's held static part) can be
kept as a static layer (`static_layer`): `rasterize(..., held=n, layer=...)` with those n
first then projects and bins only the others and blends only the tiles they reach, for the
same images and gradients bit for bit (the CPU executor; wgpu renders everything each time).

Inputs are float32 CPU tensors; wrong shapes or dtypes raise an error naming the argument.
Non-finite Gaussian values are not errors: such Gaussians are culled (zero output, zero grad).
"""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from gear import _core
from gear.camera import Camera

__all__ = [
    "BACKENDS", "Camera", "RenderOutput", "as_numpy", "auto_backend", "check_held", "rasterize",
    "resolve_backend", "static_layer",
]

MAX_CHANNELS = 64
BACKENDS = ("cpu", "wgpu")
_ENVIRONMENT_CHOICES = ("auto", *BACKENDS)


@functools.cache
def auto_backend() -> tuple[str, str]:
    """The executor `auto` picks, and why (one line)."""
    try:
        info = _core.adapter_info()
    except _core.GpuUnavailableError as error:
        reason = str(error).splitlines()[0] if str(error) else "none found"
        return "cpu", f"no wgpu adapter can be created ({reason})"
    if info["device_type"] == "Cpu":
        return "cpu", f"the wgpu adapter {info['name']} is a software one"
    return "wgpu", f"the wgpu adapter {info['name']} is a GPU ({info['device_type']})"


def resolve_backend(backend: str | None = None) -> str:
    """`backend` ("cpu" or "wgpu"), or for None what GEAR_BACKEND asks for."""
    if backend is None:
        value = os.environ.get("GEAR_BACKEND", "").strip().lower() or "auto"
        if value not in _ENVIRONMENT_CHOICES:
            raise ValueError(
                f"GEAR_BACKEND must be one of {', '.join(_ENVIRONMENT_CHOICES)}; got "
                f"{os.environ['GEAR_BACKEND']!r}"
            )
        return auto_backend()[0] if value == "auto" else value
    if backend not in BACKENDS:
        raise ValueError(f"'backend' must be None, 'cpu' or 'wgpu'; got {backend!r}")
    return backend


@dataclass
class RenderOutput:
    """Rendered images (torch tensors): features [H,W,C], alpha [H,W], depth [H,W] or None."""

    features: Tensor
    alpha: Tensor
    depth: Tensor | None = None


def _check_tensor(value: Any, name: str, shape: tuple[int | str, ...]) -> Tensor:
    """A float32 CPU tensor of `shape` (ints fixed, strings free) or a clear error."""
    spelled = "[" + ", ".join(str(d) for d in shape) + "]"
    if not isinstance(value, Tensor):
        raise TypeError(
            f"'{name}' must be a torch.Tensor of shape {spelled}, got {type(value).__name__}"
        )
    if value.dtype != torch.float32:
        raise TypeError(f"'{name}' must be float32, got {value.dtype}")
    if value.device.type != "cpu":
        raise ValueError(f"'{name}' must be on the CPU, got device {value.device}")
    if value.dim() != len(shape) or any(
        isinstance(want, int) and got != want for got, want in zip(value.shape, shape, strict=True)
    ):
        raise ValueError(f"'{name}' must have shape {spelled}, got {list(value.shape)}")
    return value


def _check_inputs(arrays: tuple[Tensor, ...], camera: Camera, background: Tensor | None) -> Tensor:
    """Validates every argument (`arrays`: means, quats, log_scales, opacity_logits,
    features); returns the background (zeros when None)."""
    means, quats, log_scales, opacity_logits, features = arrays
    n = _check_tensor(means, "means", ("N", 3)).shape[0]
    _check_tensor(quats, "quats", (n, 4))
    _check_tensor(log_scales, "log_scales", (n, 3))
    _check_tensor(opacity_logits, "opacity_logits", (n,))
    channels = _check_tensor(features, "features", (n, "C")).shape[1]
    if not 1 <= channels <= MAX_CHANNELS:
        raise ValueError(f"'features' must have 1..{MAX_CHANNELS} channels, got {channels}")
    if not isinstance(camera, Camera):
        raise TypeError(f"'camera' must be a gear.splat.Camera, got {type(camera).__name__}")
    intrinsics = (camera.fx, camera.fy, camera.cx, camera.cy)
    if not (np.isfinite(camera.world_to_cam).all() and np.isfinite(intrinsics).all()):
        raise ValueError("'camera' has non-finite values")
    if background is None:
        return torch.zeros(channels, dtype=torch.float32)
    _check_tensor(background, "background", (channels,))
    if not torch.isfinite(background).all():
        raise ValueError("'background' has non-finite values")
    return background


def check_held(held: Any, n: int) -> int:
    """`held` (how many leading Gaussians are the caller's constants) as an int in [0, n], or
    a clear error."""
    if isinstance(held, bool) or not isinstance(held, int | np.integer):
        raise TypeError(f"'held' must be an int, got {type(held).__name__}")
    if not 0 <= held <= n:
        raise ValueError(f"'held' must be in [0, {n}] (the Gaussians rendered), got {held}")
    return int(held)


def as_numpy(t: Tensor) -> np.ndarray:
    """A zero-copy view of a contiguous CPU tensor; others (e.g. the expanded gradient
    of a sum) are copied by numpy on this thread rather than by a torch kernel on its OpenMP
    workers, which would compete with the executor's threads for the cores."""
    return np.ascontiguousarray(t.detach().numpy())


def _camera_args(camera: Camera) -> tuple:
    """The camera as the native bindings take it: world-to-camera [4, 4] float32, (fx, fy,
    cx, cy), width, height."""
    return (np.ascontiguousarray(camera.world_to_cam, dtype=np.float32),
            (camera.fx, camera.fy, camera.cx, camera.cy), camera.width, camera.height)


class _Rasterize(torch.autograd.Function):
    """Outputs (features, alpha) or (features, alpha, depth); gradients to the five arrays."""

    @staticmethod
    def forward(
        ctx: Any,
        means: Tensor,
        quats: Tensor,
        log_scales: Tensor,
        opacity_logits: Tensor,
        features: Tensor,
        camera: Camera,
        background: Tensor,
        depth: bool,
        backend: str,
        held: int,
        layer: Any,
    ) -> tuple[Tensor, ...]:
        render = _core.rasterize_forward_cpu if backend == "cpu" else _core.rasterize_forward
        if layer is not None and backend == "cpu":
            render = functools.partial(_core.rasterize_forward_over, layer)
        image, alpha, depth_image, state = render(
            *(as_numpy(t) for t in (means, quats, log_scales, opacity_logits, features)),
            *_camera_args(camera),
            as_numpy(background),
            depth,
        )
        ctx.state = state
        ctx.depth = depth
        ctx.held = held
        outputs = (torch.from_numpy(image), torch.from_numpy(alpha))
        return (*outputs, torch.from_numpy(depth_image)) if depth else outputs

    @staticmethod
    def backward(ctx: Any, *grads: Tensor) -> tuple[Tensor | None, ...]:
        grad_depth = as_numpy(grads[2].float()) if ctx.depth else None
        wanted = ctx.needs_input_grad[:5]
        # Constant features (e.g. detached colours) skip their gradients, a per-channel cost of
        # the backward; the feature image's gradient still enters the others.
        arrays = _core.rasterize_backward(
            ctx.state,
            as_numpy(grads[0].float()),
            as_numpy(grads[1].float()),
            grad_depth,
            features_grad=wanted[4],
            held=ctx.held,
        )
        input_grads = tuple(
            torch.from_numpy(g) if need else None for g, need in zip(arrays, wanted, strict=True)
        )
        return (*input_grads, None, None, None, None, None, None)


def rasterize(
    means: Tensor,
    quats: Tensor,
    log_scales: Tensor,
    opacity_logits: Tensor,
    features: Tensor,
    camera: Camera,
    background: Tensor | None = None,
    depth: bool = False,
    backend: str | None = None,
    held: int = 0,
    layer: Any = None,
) -> RenderOutput:
    """Renders N Gaussians seen by `camera` (see the module docstring).

    means [N,3], quats [N,4] (w, x, y, z), log_scales [N,3], opacity_logits [N], features
    [N,C] (1 <= C <= 64), background [C] (None: zeros): float32 CPU tensors. Gradients flow to
    the five Gaussian arrays that require them, but for the first `held` Gaussians: constants
    of the caller (e.g. a static part), whose gradients are zeros and cost the CPU executor's
    backward no work beyond replaying them for the others' transmittance. `layer`: a
    `static_layer` of the first len(layer) <= `held` Gaussians, made for this camera and
    depth setting (the same images, less work). `backend`: "cpu", "wgpu" or None
    (GEAR_BACKEND).
    """
    arrays = (means, quats, log_scales, opacity_logits, features)
    background = _check_inputs(arrays, camera, background)
    held = check_held(held, means.shape[0])
    if layer is not None and len(layer) > held:
        raise ValueError(f"'layer' holds {len(layer)} Gaussians: hold them all (held >= "
                         f"{len(layer)}), got held={held}")
    executor = resolve_backend(backend)
    outputs = _Rasterize.apply(*arrays, camera, background, bool(depth), executor, held, layer)
    return RenderOutput(outputs[0], outputs[1], outputs[2] if depth else None)


def static_layer(
    means: Tensor,
    quats: Tensor,
    log_scales: Tensor,
    opacity_logits: Tensor,
    features: Tensor,
    camera: Camera,
    depth: bool = False,
    backend: str | None = None,
) -> Any:
    """The render of these Gaussians seen by `camera`, kept so that `rasterize(..., held=n,
    layer=...)` can draw more Gaussians over them (these n first, unchanged: an error
    otherwise). None where the executor keeps no layers (wgpu renders everything each time,
    with the same result). Arguments as `rasterize`'s; `depth` as the renders over it."""
    arrays = (means, quats, log_scales, opacity_logits, features)
    _check_inputs(arrays, camera, None)
    if resolve_backend(backend) != "cpu":
        return None
    return _core.static_layer_cpu(*(as_numpy(t) for t in arrays), *_camera_args(camera),
                                  bool(depth))
