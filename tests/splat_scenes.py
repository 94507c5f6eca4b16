"""Small random Gaussian scenes shared by the rasterizer tests."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from gear.camera import Camera

ARRAYS = ("means", "quats", "log_scales", "opacity_logits", "features")


@dataclass
class Scene:
    means: Tensor
    quats: Tensor
    log_scales: Tensor
    opacity_logits: Tensor
    features: Tensor

    def arrays(self) -> tuple[Tensor, ...]:
        return tuple(getattr(self, name) for name in ARRAYS)

    def to(self, dtype: torch.dtype, requires_grad: bool = False) -> Scene:
        """A copy in `dtype`, each array a fresh leaf."""
        return Scene(
            *(a.detach().to(dtype).clone().requires_grad_(requires_grad) for a in self.arrays())
        )

    def cat(self, other: Scene) -> Scene:
        pairs = zip(self.arrays(), other.arrays(), strict=True)
        return Scene(*(torch.cat([a, b]) for a, b in pairs))


def camera(width: int = 24, height: int = 20, fov_x: float = 0.9) -> Camera:
    """A camera about 4 units from the origin, looking at it from a slight angle."""
    return Camera.look_at(
        np.array([0.7, -0.5, -3.9]), np.zeros(3), np.array([0.0, -1.0, 0.0]), fov_x, width, height
    )


def random_scene(
    n: int,
    channels: int = 3,
    seed: int = 0,
    spread: float = 1.0,
    log_scale: tuple[float, float] = (-2.5, -1.2),
    logit: tuple[float, float] = (-1.5, 2.0),
) -> Scene:
    """`n` Gaussians in the cube [-spread, spread]³ around the origin (in view of `camera`),
    with unnormalised quaternions, log-scales and opacity logits drawn from the given ranges,
    and features in [-0.5, 1.5]. float32."""
    g = torch.Generator().manual_seed(seed)

    def uniform(shape: tuple[int, ...], lo: float, hi: float) -> Tensor:
        return lo + (hi - lo) * torch.rand(shape, generator=g)

    return Scene(
        means=uniform((n, 3), -spread, spread),
        quats=torch.randn((n, 4), generator=g) * uniform((n, 1), 0.3, 2.0),
        log_scales=uniform((n, 3), *log_scale),
        opacity_logits=uniform((n,), *logit),
        features=uniform((n, channels), -0.5, 1.5),
    )


def relative_l2(got: Tensor, want: Tensor) -> float:
    """‖got - want‖ / ‖want‖ (in float64; 0/0 counts as 0)."""
    got, want = got.double(), want.double()
    norm = want.norm().item()
    diff = (got - want).norm().item()
    return diff / norm if norm > 0 else diff


def core_args(scene: Scene, cam: Camera, background: Tensor, depth: bool) -> tuple:
    """Positional arguments of _core.rasterize_forward / _core.reference_forward."""
    arrays = (a.detach().float().contiguous().numpy() for a in scene.arrays())
    return (
        *arrays,
        np.ascontiguousarray(cam.world_to_cam, dtype=np.float32),
        (cam.fx, cam.fy, cam.cx, cam.cy),
        cam.width,
        cam.height,
        background.float().numpy(),
        depth,
    )


def assert_images_close(got: Tensor, want: Tensor, name: str, atol: float = 1e-4) -> None:
    """A float32 image against a float64 reference of the same shape: every value within
    `atol`, except where the two precisions fall on either side of the 1/255 alpha skip. Such a
    flip moves a value by at most ~1/255 of the blended magnitude, and it is rare: at most
    0.01% of the values (none in images under 10,000 values) may differ by up to
    2/255·max(1, max|want|)."""
    assert got.shape == want.shape, f"{name}: shape {tuple(got.shape)} vs {tuple(want.shape)}"
    err = (got.double() - want.double()).abs()
    assert torch.isfinite(err).all(), f"{name}: non-finite values"
    outliers = int((err > atol).sum())
    allowed = int(1e-4 * err.numel())
    step = 2 / 255 * max(1.0, want.abs().max().item()) if want.numel() else 0.0
    assert outliers <= allowed and (err.numel() == 0 or err.max().item() <= max(atol, step)), (
        f"{name}: max abs error {err.max().item():.2e}, {outliers} values over {atol:g} "
        f"({allowed} allowed)"
    )
