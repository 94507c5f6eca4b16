"""The one render call of training, outputs and the twin: a set of Gaussians (optionally
posed, or carrying other per-Gaussian features such as part logits) seen from one camera."""

from __future__ import annotations

import functools
import threading
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
    layers: StaticLayers | None = None,
) -> Any:  # RenderOutput(.features [H,W,C], .alpha [H,W], .depth [H,W] | None)
    """`splats` seen from `camera` over `background` [C] (black when None).

    pose: (means, quats) to draw instead of the stored ones (a posed or deformed model, see
    gear.kinematics.pose_parts). features: [N,C] to blend instead of the RGB colours (those
    are view-dependent when the splats carry spherical harmonics, see gear.splats.sh).
    extra: [N,E] more channels (e.g. part logits) blended after those over a black background,
    in the same pass: one projection and sort serve both (blending is per channel).
    detach: no gradient reaches the stored parameters (a given pose or features keep their
    own graph). held: the first `held` Gaussians pass no gradient at all (constants of the
    caller, e.g. a static part; their backward work is skipped). layers: the static layers of
    the first layers.count <= held Gaussians, which stay as they are from render to render:
    the same images for less work (gear.splat.static_layer)."""
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
    draw = rasterizer()
    arrays = (means, quats, log_scales, opacity, feats)
    layer = None
    if layers is not None and layers.serve(draw):
        layer = layers.layer(arrays, camera, depth)
    extra_args = {"layer": layer} if layer is not None else {}
    return draw(*arrays, camera, background=bg, depth=depth, held=held, **extra_args)


# What the static layers of one model may hold at most: past it, further cameras render in
# full (at 128² a layer of a 50k-Gaussian static part holds ~5.4 MiB, 64 cameras ~345 MiB).
LAYER_BUDGET_BYTES = 2 << 30


class StaticLayers:
    """The static layers (gear.splat.static_layer) of the first `count` Gaussians of a model
    whose first `count` stay as they are (e.g. a static part held while the others move),
    one per camera, depth setting and channel count, each made at its first render while
    they hold less than `budget` bytes. Empty without the executor's layers (the torch
    reference, the wgpu kernels)."""

    def __init__(self, count: int, budget: int = LAYER_BUDGET_BYTES) -> None:
        self.count = count
        self.budget = budget
        self._layers: dict[tuple[int, bool, int], tuple[Camera, Any]] = {}
        self._bytes = 0
        self._making = threading.Lock()

    @staticmethod
    def serve(draw: Callable) -> bool:
        """Whether renders by `draw` can start from a layer (the native rasterizer's)."""
        from gear import _core

        if not hasattr(_core, "static_layer_cpu"):
            return False
        from gear.splat import rasterize

        return draw is rasterize

    def layer(self, arrays: tuple[torch.Tensor, ...], camera: Camera, depth: bool) -> Any:
        """The layer for `camera`, made from the first `count` rows of `arrays` (means, quats,
        log_scales, opacity logits, features) if it is not there yet; None where the executor
        keeps no layers (wgpu) or the layers made hold the budget already."""
        key = (id(camera), depth, arrays[-1].shape[1])
        # One layer made at a time: renders beside each other (the M-step's views) neither
        # make one twice nor both pass the budget.
        with self._making:
            if key not in self._layers:
                if self._bytes >= self.budget:
                    return None
                from gear.splat import static_layer

                made = static_layer(*(t.detach()[: self.count] for t in arrays), camera, depth)
                # The camera is kept with its layer so that its id cannot be reused meanwhile.
                self._layers[key] = (camera, made)
                self._bytes += made.nbytes if made is not None else 0
            return self._layers[key][1]

    def __len__(self) -> int:
        """Layers made so far."""
        return len(self._layers)

    def nbytes(self) -> int:
        """Bytes the layers hold."""
        return self._bytes
