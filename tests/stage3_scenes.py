"""Tiny stage-3 scenes shared by the joint-scoring and part-merging tests: Gaussians posed
under hard part assignment and rendered with the deterministic torch reference from a ring of
cameras in front of the object, which sits away from the world origin as real objects do."""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from gear.articulation import PartMotion
from gear.camera import Camera
from gear.data import View
from gear.kinematics import deform
from gear.pipeline.common import TrainView
from gear.splat_reference import rasterize_dense
from gear.splats import Gaussians

RES = 16
# The object sits away from the world origin: a hinge's translation then differs from the
# displacement of its part.
OFFSET = np.array([0.6, 0.0, 0.0])


def wall() -> torch.Tensor:
    """A static wall of 12 centres in the plane y = 0.15."""
    wx, wz = torch.meshgrid(torch.linspace(-0.4, 0.4, 4), torch.linspace(-0.3, 0.3, 3),
                            indexing="ij")
    return torch.stack([wx.flatten(), torch.full((12,), 0.15), wz.flatten()], 1)


def plank(x0: float, x1: float, z: float = 0.0, columns: int = 3) -> torch.Tensor:
    """A plank of 2 x `columns` centres from x0 to x1 at height z, in front of the wall."""
    px, pz = torch.meshgrid(torch.linspace(x0, x1, columns), torch.tensor([z - 0.05, z + 0.05]),
                            indexing="ij")
    return torch.stack([px.flatten(), torch.full((2 * columns,), -0.1), pz.flatten()], 1)


def rot_z(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])


def grid_gaussians(blocks: list[tuple[torch.Tensor, int]], seed: int = 0) -> Gaussians:
    """Opaque isotropic Gaussians at the centres of each (centres [n, 3], part) block (moved by
    OFFSET), hard-assigned to their part (logits ±3), with random colours."""
    means = torch.cat([c for c, _ in blocks]) + torch.as_tensor(OFFSET, dtype=torch.float32)
    parts = torch.cat([torch.full((len(c),), p) for c, p in blocks])
    n, k = len(means), int(parts.max()) + 1
    logits = torch.full((n, k), -3.0)
    logits[torch.arange(n), parts] = 3.0
    return Gaussians(dict(
        means=means,
        quats=torch.tensor([1.0, 0, 0, 0]).repeat(n, 1),
        log_scales=torch.full((n, 3), -2.3),
        opacity=torch.full((n,), 3.0),
        colors=torch.rand(n, 3, generator=torch.Generator().manual_seed(seed)),
        logits=logits,
    ))


def views_of(g: Gaussians, motion: PartMotion, n: int = 3) -> list[TrainView]:
    """Renders of the hard-assigned model moved by `motion` from a ring of cameras in front."""
    weights = F.one_hot(g.part_ids(), g.num_parts).float()
    qr, qd = motion.motion()
    out_views = []
    with torch.no_grad():
        means, quats = deform(g["means"], g["quats"], weights, qr, qd)
        for i in range(n):
            a = -np.pi / 2 + (i - 1) * 0.6  # in front of the object (towards -y)
            eye = OFFSET + np.array([2 * np.cos(a), 2 * np.sin(a), 0.8])
            cam = Camera.look_at(eye, OFFSET, np.array([0, 0, 1.0]), 0.9, RES, RES)
            out = rasterize_dense(means, quats, g["log_scales"], g["opacity"], g.rgb(), cam,
                                  depth=True)
            alpha = out.alpha.numpy()
            rgb = out.features.numpy() / np.maximum(alpha, 1e-6)[..., None]
            depth = np.where(alpha > 0.5, out.depth.numpy() / np.maximum(alpha, 1e-6), 0.0)
            out_views.append(TrainView.from_view(View(
                f"v{i}", cam, np.clip(rgb, 0, 1).astype(np.float32), alpha.astype(np.float32),
                depth.astype(np.float32))))
    return out_views
