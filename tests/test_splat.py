"""gear.splat against the pure-torch renderer (gear.splat_reference) and the f64 Rust reference.

Tolerances: the GPU renders in float32; images within 1e-4 (max abs) of the float64 references,
gradients within 1e-3 relative L2 per input array. The two float64 references (torch and Rust)
agree to 1e-9. Finite differences check the torch reference in float64.
"""

import math

import numpy as np
import pytest
import torch

from gear import splat
from gear.splat_reference import rasterize_dense, rasterize_tiled
from splat_scenes import Scene, camera, random_scene

BACKGROUND = (0.1, 0.3, 0.6)


def background(channels: int, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    return torch.tensor([BACKGROUND[c % 3] + 0.01 * c for c in range(channels)], dtype=dtype)


def images(out: splat.RenderOutput) -> list[torch.Tensor]:
    return [out.features, out.alpha] + ([out.depth] if out.depth is not None else [])


# --- the pure-torch reference on its own -------------------------------------------------


@pytest.mark.parametrize(("channels", "depth", "seed"), [(3, True, 0), (1, False, 1)])
def test_dense_reference_gradients_match_finite_differences(channels, depth, seed):
    # Float64 central differences; the hard cut-offs (1/255 skip, T < 1e-4, 0.999 clamp) are
    # steps, and these seeds put no pixel within reach of one at the step size used.
    scene = random_scene(5, channels, seed).to(torch.float64, requires_grad=True)
    cam = camera(12, 10)
    bg = background(channels, torch.float64)

    def render(*arrays: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return tuple(images(rasterize_dense(*arrays, cam, bg, depth)))

    assert torch.autograd.gradcheck(
        render, scene.arrays(), eps=1e-6, atol=1e-7, rtol=1e-5, fast_mode=True
    )


def test_single_gaussian_centre_pixel_and_background():
    # A Gaussian on the optical axis of a camera whose principal point is the centre of pixel
    # (6, 5): there power = 0, so alpha = sigmoid(logit) exactly.
    cam = splat.Camera(np.eye(4), 10.0, 10.0, 6.5, 5.5, 12, 10)
    scene = Scene(
        means=torch.tensor([[0.0, 0.0, 2.0]]),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]),
        log_scales=torch.full((1, 3), -3.0),
        opacity_logits=torch.tensor([0.5]),
        features=torch.tensor([[0.2, 0.5, 0.9]]),
    ).to(torch.float64)
    bg = background(3, torch.float64)
    out = rasterize_dense(*scene.arrays(), cam, bg, depth=True)
    o = 1 / (1 + math.exp(-0.5))
    torch.testing.assert_close(out.alpha[5, 6].item(), o, rtol=0, atol=1e-15)
    torch.testing.assert_close(out.features[5, 6], o * scene.features[0] + (1 - o) * bg)
    torch.testing.assert_close(out.depth[5, 6].item(), 2 * o, rtol=0, atol=1e-15)
    # Far from the Gaussian only the background shows.
    assert out.alpha[0, 0] == 0 and out.depth[0, 0] == 0
    assert torch.equal(out.features[0, 0], bg)


def test_tiled_reference_equals_dense():
    scene = random_scene(60, 2, seed=3).to(torch.float64)
    cam = camera(45, 37)  # not multiples of the 16-pixel tile nor of the block
    bg = background(2, torch.float64)
    dense = rasterize_dense(*scene.arrays(), cam, bg, depth=True)
    tiled = rasterize_tiled(*scene.arrays(), cam, bg, depth=True, block=32)
    for a, b in zip(images(dense), images(tiled), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12)
