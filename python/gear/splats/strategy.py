"""The densification strategy: the statistics it gathers (screen-space gradient of each
Gaussian's centre), its edits (clone, split, prune, opacity reset) and their schedule
(docs/method.md, "Densification"). The Gaussians themselves only know how to keep their Adam
state aligned through an edit (gear.splats.gaussians)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from gear.camera import Camera
from gear.config import TrainConfig
from gear.kinematics import quat_to_matrix
from gear.splats.gaussians import Gaussians

SPLIT_COPIES = 2
SPLIT_SHRINK = 0.8 * SPLIT_COPIES  # split children are this much smaller than the parent
RESET_OPACITY = 0.01


def small_part_mask(g: Gaussians, threshold: int) -> torch.Tensor:
    """Gaussians of movable parts (argmax >= 1) that have fewer than `threshold` members."""
    ids = g.part_ids()
    counts = torch.bincount(ids, minlength=g.num_parts)
    small = counts < threshold
    small[0] = False
    return small[ids]


def gaussian_budget(config: TrainConfig, cameras: Sequence[Camera]) -> int:
    """The most Gaussians densification may reach: `max_gaussians` and, when
    `max_gaussians_per_pixel` is set, that many per pixel of the largest training view."""
    budget = config.max_gaussians
    if config.max_gaussians_per_pixel is not None:
        pixels = max(c.width * c.height for c in cameras)
        budget = min(budget, max(1, int(config.max_gaussians_per_pixel * pixels)))
    return budget


class Densifier:
    """Adaptive density control of one set of Gaussians during one stage, within `budget`
    Gaussians (None: the config's `max_gaussians`; see gaussian_budget)."""

    def __init__(self, g: Gaussians, budget: int | None = None) -> None:
        self.budget = budget
        self.reset_stats(len(g))

    def reset_stats(self, n: int) -> None:
        self.grad_accum = torch.zeros(n)
        self.grad_count = torch.zeros(n)

    def state_dict(self) -> dict[str, torch.Tensor]:
        """The statistics gathered since the last edit: a run resumed inside a densification
        interval densifies as the uninterrupted one does."""
        return {"grad_accum": self.grad_accum.clone(), "grad_count": self.grad_count.clone()}

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        self.grad_accum, self.grad_count = state["grad_accum"], state["grad_count"]

    @torch.no_grad()
    def accumulate(self, rendered_means: torch.Tensor, camera: Camera, next_iteration: int,
                   densify_until: int) -> None:
        """Adds the screen-space (NDC) norm of dL/d(projected centre) of each visible Gaussian.

        `rendered_means` are the positions that were rendered (deformed in stage 3) with their
        .grad retained; the projected-centre gradient follows from the camera-space one as
        dL/du = dL/dx_cam * z / fx (scaled by W/2 into NDC as the 2e-4 threshold assumes).
        Nothing once `next_iteration` (the one `maintain` is called with next) has reached
        `densify_until`: no densification is left to read the statistics (half of a fast run's
        iterations, ~2 ms each at 80k Gaussians).
        """
        grad = rendered_means.grad
        if grad is None or next_iteration >= densify_until:
            return
        rot = torch.as_tensor(camera.world_to_cam[:3, :3], dtype=torch.float32)
        trans = torch.as_tensor(camera.world_to_cam[:3, 3], dtype=torch.float32)
        g_cam = grad @ rot.T
        z = (rendered_means.detach() @ rot.T + trans)[:, 2].clamp_min(1e-6)
        gx = g_cam[:, 0] * z / camera.fx * 0.5 * camera.width
        gy = g_cam[:, 1] * z / camera.fy * 0.5 * camera.height
        # Adding a masked norm and a 0/1 count to every Gaussian, rather than indexing both
        # with the visibility mask, gives the same sums at a fraction of the cost (the mask
        # also keeps a culled non-finite Gaussian's NaN norm out).
        visible = (grad != 0).any(dim=1)
        self.grad_accum += torch.where(visible, torch.sqrt(gx * gx + gy * gy), 0.0)
        self.grad_count += visible

    def maintain(self, g: Gaussians, it: int, config: TrainConfig, extent: float,
                 densify_until: int, allowed: bool, generator: torch.Generator) -> list[dict]:
        """Densify/prune and opacity reset at their configured iterations; the log events."""
        c, events = config, []
        if allowed and it > 0 and c.densify_from <= it < densify_until and (
            it % c.densify_interval == 0
        ):
            max_scale = c.prune_max_scale * extent if it > c.opacity_reset_interval else None
            info = self.densify_and_prune(
                g, c.densify_grad_threshold, extent, c.percent_dense, c.prune_opacity,
                max_scale, c.max_gaussians if self.budget is None else self.budget, generator,
            )
            events.append({"event": "densify", "iteration": it, **info})
        if it > 0 and it % c.opacity_reset_interval == 0 and it < densify_until:
            protect = small_part_mask(g, c.small_part_threshold) if g.num_parts > 1 else None
            n = self.reset_opacity(g, protect)
            events.append({"event": "opacity_reset", "iteration": it, "reset": n})
        return events

    @torch.no_grad()
    def densify_and_prune(
        self,
        g: Gaussians,
        grad_threshold: float,
        extent: float,
        percent_dense: float,
        min_opacity: float,
        max_scale: float | None,
        max_gaussians: int,
        generator: torch.Generator,
    ) -> dict[str, int]:
        """Clones small and splits large Gaussians whose mean screen gradient exceeds the
        threshold, then prunes transparent (and, when `max_scale` is set, huge) ones."""
        avg = self.grad_accum / self.grad_count.clamp_min(1)
        hot = avg >= grad_threshold
        scale = torch.exp(g["log_scales"].detach()).max(dim=1).values
        clone = hot & (scale <= percent_dense * extent)
        split = hot & ~clone
        cost = clone.long() + SPLIT_COPIES * split.long()  # Gaussians each candidate adds
        budget = max(max_gaussians - len(g), 0)
        if int(cost.sum()) > budget:  # over budget: the strongest gradients first
            order = torch.argsort(avg, descending=True)
            chosen = torch.zeros_like(hot)
            chosen[order[torch.cumsum(cost[order], 0) <= budget]] = True
            clone &= chosen
            split &= chosen
        n_new = int(clone.sum()) + SPLIT_COPIES * int(split.sum())
        n_before = len(g)
        extra = {name: t.detach()[clone] for name, t in g.params.items()}
        if bool(split.any()):
            children = {
                name: t.detach()[split].repeat(SPLIT_COPIES, *([1] * (t.dim() - 1)))
                for name, t in g.params.items()
            }
            parent_scale = torch.exp(children["log_scales"])
            offset = torch.randn(parent_scale.shape, generator=generator) * parent_scale
            quats = children["quats"]
            rot = quat_to_matrix(quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12))
            children["means"] = children["means"] + (rot @ offset[..., None])[..., 0]
            children["log_scales"] = children["log_scales"] - float(np.log(SPLIT_SHRINK))
            extra = {name: torch.cat([extra[name], children[name]]) for name in extra}
        if n_new:
            g.append(extra)
        drop = torch.cat([split, torch.zeros(n_new, dtype=torch.bool)])
        drop |= torch.sigmoid(g["opacity"].detach()) < min_opacity
        if max_scale is not None:
            drop |= torch.exp(g["log_scales"].detach()).max(dim=1).values > max_scale
        if bool(drop.all()):  # never prune to nothing: keep the most opaque Gaussian
            drop[g["opacity"].detach().argmax()] = False
        g.keep(~drop)
        self.reset_stats(len(g))
        return dict(cloned=int(clone.sum()), split=int(split.sum()), pruned=int(drop.sum()),
                    before=n_before, after=len(g))

    @torch.no_grad()
    def reset_opacity(self, g: Gaussians, protect: torch.Tensor | None = None) -> int:
        """Opacity := min(o, 0.01) except for `protect`ed Gaussians (their Adam state too)."""
        target = torch.ones(len(g), dtype=torch.bool)
        if protect is not None:
            target &= ~protect
        g.lower_opacity(target, RESET_OPACITY)
        return int(target.sum())
