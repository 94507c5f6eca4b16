"""What a state's images see, for stage 2's check that a part really moved: its stage-1 model
rendered from a few of its training views (docs/method.md, "Stage 2")."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from gear.pipeline.common import TrainView
from gear.splats import Gaussians, render


class SurfaceTest:
    """`test(points [M,3], tolerance) -> (on_surface [M], free [M])` over up to `max_views`
    of `views` rendered from `model`: whether each point lies, within `tolerance` in depth, on
    the surface shown (alpha > 0.5) in some view, and whether some view sees through it
    (outside the silhouette, or in front of the surface by more than `tolerance`); `votes`
    counts the views of each. The renders are made on first use: stage 2 asks only the target
    state's test."""

    def __init__(self, model: Gaussians, views: Sequence[TrainView], max_views: int = 8) -> None:
        self.model, self.views, self.max_views = model, list(views), max_views
        self._seen: list[tuple] | None = None

    def _renders(self) -> list[tuple]:
        if self._seen is None:
            self._seen = []
            with torch.no_grad():
                for view in self.views[:: max(1, len(self.views) // self.max_views)]:
                    out = render(self.model, view.camera, torch.zeros(3), depth=True)
                    alpha = out.alpha.numpy()
                    depth = out.depth.numpy() / np.maximum(alpha, 1e-6)  # the surface's depth
                    self._seen.append((view.camera, alpha > 0.5, depth))
        return self._seen

    def votes(self, points: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
        """(on [M], through [M]): in how many of the views each point lies on the surface
        shown, within `tolerance` in depth, and in how many that view sees through it."""
        on = np.zeros(len(points), dtype=np.int64)
        through = np.zeros(len(points), dtype=np.int64)
        for camera, solid, depth in self._renders():
            uv, z = camera.project(points)
            ok = np.isfinite(uv).all(axis=1) & (z > 0)
            u = np.floor(np.where(ok, uv[:, 0], -1)).astype(np.int64)
            v = np.floor(np.where(ok, uv[:, 1], -1)).astype(np.int64)
            ok &= (u >= 0) & (v >= 0) & (u < camera.width) & (v < camera.height)
            idx = np.flatnonzero(ok)
            uu, vv = u[idx], v[idx]
            gap = z[idx] - depth[vv, uu]
            on[idx[solid[vv, uu] & (np.abs(gap) < tolerance)]] += 1
            through[idx[~solid[vv, uu] | (gap < -tolerance)]] += 1
        return on, through

    def __call__(self, points: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
        on, through = self.votes(points, tolerance)
        return on > 0, through > 0
