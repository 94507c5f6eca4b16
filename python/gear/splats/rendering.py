"""The one render call of training, outputs and the twin: a set of Gaussians (optionally
posed, or carrying other per-Gaussian features such as part logits) seen from one camera."""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, Protocol

import torch

from gear.camera import Camera
from gear.splats.sh import view_rgb


class Splats(Protocol):
    """Anything the renderer can draw: gear.splats.Gaussians, gear.twin.Twin."""

    def splat_arrays(self) -> tuple[torch.Tensor, ...]:
        """(means [N,3], quats [N,4], log_scales [N,3], opacity logits [N], rgb [N,3])."""
        ...


@functools.cache
def rasterizer() -> Callable:
    """The executor every render goes through: the GPU kernels when the extension has them,
    else the torch reference (same signature and maths; slow, for tiny scenes)."""
    from gear import _core

    if hasattr(_core, "rasterize_forward"):
        from gear.splat import rasterize

        return rasterize
    from gear.splat_reference import rasterize_dense

    return rasterize_dense


def render(
    splats: Splats,
    camera: Camera,
    background: torch.Tensor | None = None,
    *,
    pose: tuple[torch.Tensor, torch.Tensor] | None = None,
    features: torch.Tensor | None = None,
    extra: torch.Tensor | None = None,
    depth: bool = False,
    detach: bool = False,
    held: int = 0,
) -> Any:  # RenderOutput(.features [H,W,C], .alpha [H,W], .depth [H,W] | None)
    """`splats` seen from `camera` over `background` [C] (black when None).

    pose: (means, quats) to draw instead of the stored ones (a posed or deformed model, see
    gear.kinematics.pose_parts). features: [N,C] to blend instead of the RGB colours (those
    are view-dependent when the splats carry spherical harmonics, see gear.splats.sh).
    extra: [N,E] more channels (e.g. part logits) blended after those over a black background,
    in the same pass: one projection and sort serve both (blending is per channel).
    detach: no gradient reaches the stored parameters (a given pose or features keep their
    own graph). held: the first `held` Gaussians pass no gradient at all (constants of the
    caller, e.g. a static part; their backward work is skipped)."""
    stored = splats.splat_arrays()
    if detach:
        stored = tuple(t.detach() for t in stored)
    means, quats, log_scales, opacity, rgb = stored
    canonical_quats = quats
    if pose is not None:
        means, quats = pose
    feats = features
    if feats is None:  # the colours, view-dependent when the splats carry SH coefficients
        feats = view_rgb(splats, rgb, camera, means, quats, canonical_quats, detach)
    bg = torch.zeros(feats.shape[1]) if background is None else background
    if extra is not None:
        feats = torch.cat([feats, extra], dim=1)
        bg = torch.cat([bg, torch.zeros(extra.shape[1], dtype=bg.dtype)])
    return rasterizer()(means, quats, log_scales, opacity, feats, camera, background=bg,
                        depth=depth, held=held)
