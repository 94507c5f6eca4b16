"""gear.splat.rasterize (both executors) on hard inputs: outputs and gradients finite, and what
they should be.

Culled Gaussians (behind the camera, at the near plane, non-finite, opacity below 1/255,
off-screen) must change nothing and get exactly zero gradient.
"""

import math

import numpy as np
import pytest
import torch

from gear import _core, splat
from gear.splat_reference import rasterize_dense, rasterize_tiled
from splat_scenes import (
    ARRAYS,
    Scene,
    assert_images_close,
    camera,
    core_args,
    random_scene,
    relative_l2,
)

IDENTITY = (1.0, 0.0, 0.0, 0.0)
BACKGROUND = (0.25, 0.5, 0.75)


def axis_camera(width: int = 17, height: int = 13) -> splat.Camera:
    """At the origin looking down +z; the principal point is the centre of pixel (8, 6)."""
    return splat.Camera(np.eye(4), 20.0, 20.0, 8.5, 6.5, width, height)


def gaussians(rows: list[tuple], channels: int = 3) -> Scene:
    """Rows of (mean, quat, log_scale, logit); features (1, 2, ...) / 10 per channel."""
    return Scene(
        means=torch.tensor([r[0] for r in rows], dtype=torch.float32).reshape(-1, 3),
        quats=torch.tensor([r[1] for r in rows], dtype=torch.float32).reshape(-1, 4),
        log_scales=torch.tensor([[r[2]] * 3 for r in rows], dtype=torch.float32).reshape(-1, 3),
        opacity_logits=torch.tensor([r[3] for r in rows], dtype=torch.float32),
        features=torch.arange(1, channels + 1, dtype=torch.float32).repeat(len(rows), 1) / 10,
    )



@pytest.fixture(autouse=True, params=splat.BACKENDS)
def backend(request, monkeypatch) -> str:
    """Every test here runs on both executors (gear.splat.rasterize follows GEAR_BACKEND)."""
    monkeypatch.setenv("GEAR_BACKEND", request.param)
    return request.param

def render(
    scene: Scene, cam: splat.Camera, dense: bool = False
) -> tuple[splat.RenderOutput, list[torch.Tensor]]:
    """Render with depth (or, with `dense`, the float64 pure-torch reference), then the
    gradients of a fixed weighted sum of the three images; asserts that all are finite."""
    dtype = torch.float64 if dense else torch.float32
    scene = scene.to(dtype, requires_grad=True)
    bg = torch.tensor(BACKGROUND[: scene.features.shape[1]], dtype=dtype)
    rasterizer = rasterize_dense if dense else splat.rasterize
    out = rasterizer(*scene.arrays(), cam, bg, depth=True)
    g = torch.Generator().manual_seed(0)
    loss = sum(
        (img * torch.rand(img.shape, generator=g, dtype=torch.float64).to(dtype)).sum()
        for img in (out.features, out.alpha, out.depth)
    )
    loss.backward()
    grads = [a.grad for a in scene.arrays()]
    for name, value in [("features", out.features), ("alpha", out.alpha), ("depth", out.depth)]:
        assert torch.isfinite(value).all(), f"non-finite {name} image"
    for name, grad in zip(ARRAYS, grads, strict=True):
        assert torch.isfinite(grad).all(), f"non-finite d{name}"
    assert (out.alpha >= 0).all() and (out.alpha <= 1).all()
    return out, grads


def assert_matches_dense(
    scene: Scene, cam: splat.Camera, out: splat.RenderOutput, grads: list[torch.Tensor]
) -> tuple[splat.RenderOutput, list[torch.Tensor]]:
    """The GPU's `render(scene, cam)` against the float64 dense reference's: images within
    assert_images_close, gradients within 1e-3 relative L2. Returns the reference's."""
    want, want_grads = render(scene, cam, dense=True)
    for name in ("features", "alpha", "depth"):
        assert_images_close(getattr(out, name), getattr(want, name).detach(), name)
    for name, a, b in zip(ARRAYS, grads, want_grads, strict=True):
        rel = relative_l2(a, b)
        assert rel <= 1e-3, f"GPU d{name}: relative L2 error {rel:.2e}"
    return want, want_grads


def assert_culled(scene: Scene, culled: list[int], cam: splat.Camera) -> None:
    """Gaussians `culled` change no pixel and get exactly zero gradient."""
    out, grads = render(scene, cam)
    kept = [i for i in range(scene.means.shape[0]) if i not in culled]
    alone, _ = render(Scene(*(a[kept] for a in scene.arrays())), cam)
    for a, b in [
        (out.features, alone.features),
        (out.alpha, alone.alpha),
        (out.depth, alone.depth),
    ]:
        torch.testing.assert_close(a, b, rtol=0, atol=1e-6)
    for name, grad in zip(ARRAYS, grads, strict=True):
        assert (grad[culled] == 0).all(), f"d{name} of a culled Gaussian is not zero"


def test_near_plane_and_behind_the_camera():
    scene = gaussians(
        [
            ((0.0, 0.0, 2.0), IDENTITY, -2.0, 1.0),  # visible
            ((0.0, 0.0, 0.005), IDENTITY, -2.0, 1.0),  # closer than the near plane
            ((0.0, 0.0, -1.0), IDENTITY, -2.0, 1.0),  # behind
            ((0.1, 0.0, 0.0), IDENTITY, -2.0, 1.0),  # in the camera plane
            ((3.0, -2.0, 0.02), IDENTITY, -2.0, 1.0),  # just past the near plane, far off axis
        ]
    )
    assert_culled(scene, [1, 2, 3], axis_camera())
    # A Gaussian right at the near plane, on the axis, fills the whole view.
    out, _ = render(gaussians([((0.0, 0.0, 0.0101), IDENTITY, -2.0, 1.0)]), axis_camera())
    assert (out.alpha > 0.5).all()


def test_non_finite_and_transparent_gaussians_are_culled():
    scene = random_scene(12, seed=4)
    scene.means[3, 1] = float("nan")
    scene.quats[5, 0] = float("inf")
    scene.log_scales[7, 2] = float("-inf")
    scene.features[8, 0] = float("nan")
    scene.opacity_logits[9] = -50.0
    scene.log_scales[10] = 100.0  # exp overflows float32
    assert_culled(scene, [3, 5, 7, 8, 9, 10], camera(24, 20))


def test_tiny_and_huge_scales():
    cam = axis_camera()
    logit = 0.3
    o = 1 / (1 + math.exp(-logit))
    # A 1e-7 scale leaves only the 0.3 px² low-pass: alpha = o at the centre pixel and
    # o·exp(-½·1/0.3) one pixel to the side.
    tiny, _ = render(gaussians([((0.0, 0.0, 2.0), IDENTITY, math.log(1e-7), logit)]), cam)
    assert tiny.alpha[6, 8].item() == pytest.approx(o, abs=1e-5)
    assert tiny.alpha[6, 9].item() == pytest.approx(o * math.exp(-0.5 / 0.3), abs=1e-5)
    # A 1e3 scale covers the image with nearly constant alpha = o.
    huge, _ = render(gaussians([((0.0, 0.0, 5.0), IDENTITY, math.log(1e3), logit)]), cam)
    torch.testing.assert_close(huge.alpha, torch.full_like(huge.alpha, o), rtol=0, atol=1e-4)


def test_zero_quaternion_is_the_identity_with_zero_gradient():
    rows = [((0.05, 0.0, 2.0), (0.0, 0.0, 0.0, 0.0), -2.0, 1.0)]
    zero = gaussians(rows)
    zero.log_scales = torch.tensor([[-2.0, -2.6, -2.3]])
    identity = gaussians(rows)
    identity.log_scales = zero.log_scales.clone()
    identity.quats = torch.tensor([IDENTITY])
    out, grads = render(zero, axis_camera())
    expected, _ = render(identity, axis_camera())
    torch.testing.assert_close(out.features, expected.features, rtol=0, atol=1e-6)
    assert (grads[1] == 0).all()
    assert (grads[2] != 0).all()


def test_saturated_opacity_logits():
    cam = axis_camera()
    out, grads = render(
        gaussians(
            [
                ((0.0, 0.0, 2.0), IDENTITY, -2.0, 50.0),
                ((0.1, 0.0, 1.5), IDENTITY, -2.0, -50.0),
            ]
        ),
        cam,
    )
    assert out.alpha[6, 8].item() == pytest.approx(0.999, abs=1e-6)  # the 0.999 clamp
    assert (grads[3] == 0).all()  # sigmoid'(±50) underflows; -50 is culled outright
    assert all((g[1] == 0).all() for g in grads)


def test_ten_thousand_gaussians_on_one_pixel():
    # Means along the ray through the centre of pixel (8, 6), random depths: blending stops
    # after a handful at the centre and after some hundreds at the faint edges; most of the
    # stack is hidden and gets zero gradient.
    cam = axis_camera()
    n = 10_000
    g = torch.Generator().manual_seed(1)
    z = 2 + 4 * torch.rand(n, generator=g)
    scene = Scene(
        means=torch.stack([torch.zeros(n), torch.zeros(n), z], 1),
        quats=torch.randn(n, 4, generator=g),
        log_scales=-3.3 + 0.6 * torch.rand(n, 3, generator=g),  # anisotropic: dquats != 0
        opacity_logits=torch.rand(n, generator=g) * 2,
        features=torch.rand(n, 3, generator=g),
    )
    out, grads = render(scene, cam)
    assert out.alpha.max().item() <= 1 - 1e-4 + 1e-6
    assert_matches_dense(scene, cam, out, grads)
    contributing = (grads[4] != 0).any(1)
    assert 0 < contributing.sum() < n // 5


def test_all_off_screen_and_empty_scenes_show_the_background():
    cam = camera(24, 20)
    off = random_scene(50, seed=6)
    off.means[:, 0] += 40.0  # far to the side of the view
    empty = random_scene(0)
    for scene in (off, empty):
        out, grads = render(scene, cam)
        assert torch.equal(out.features, torch.tensor(BACKGROUND).expand(20, 24, 3))
        assert (out.alpha == 0).all() and (out.depth == 0).all()
        for grad, array in zip(grads, scene.arrays(), strict=True):
            assert grad.shape == array.shape and (grad == 0).all()


@pytest.mark.parametrize(("width", "height", "n"), [(1, 1, 50), (1000, 700, 200)])
def test_extreme_image_sizes_match_the_reference(width, height, n):
    cam = camera(width, height)
    scene = random_scene(n, seed=7, log_scale=(-4.0, -2.5))
    out, _ = render(scene, cam)
    want = rasterize_tiled(
        *scene.to(torch.float64).arrays(),
        cam,
        torch.tensor(BACKGROUND, dtype=torch.float64),
        depth=True,
    )
    for name in ("features", "alpha", "depth"):
        assert_images_close(getattr(out, name), getattr(want, name), name)


def adversarial_scene() -> Scene:
    """40 ordinary Gaussians in front of `axis_camera`, plus one of each hard case."""
    ordinary = random_scene(40, seed=9)
    ordinary.means[:, 2] += 4.0
    ordinary.features = torch.full((40, 3), 0.5) + 0.3 * ordinary.features
    hard = gaussians(
        [
            ((0.0, 0.0, 0.0101), IDENTITY, -2.0, 1.0),  # at the near plane, fills the view
            ((0.0, 0.0, 0.005), IDENTITY, -2.0, 1.0),  # closer than the near plane
            ((0.0, 0.0, -1.0), IDENTITY, -2.0, 1.0),  # behind
            ((0.3, 0.0, 2.0), (0.0, 0.0, 0.0, 0.0), -2.5, 0.5),  # zero quaternion
            ((-0.2, 0.1, 3.0), IDENTITY, math.log(1e-7), 0.8),  # point-like
            ((0.0, 0.0, 50.0), IDENTITY, math.log(1e3), -1.0),  # huge, behind everything
            ((0.1, -0.1, 2.5), IDENTITY, -2.0, 50.0),  # opaque: the 0.999 clamp
            ((0.1, 0.1, 2.5), IDENTITY, -2.0, -50.0),  # transparent: culled
            ((float("nan"), 0.0, 2.0), IDENTITY, -2.0, 1.0),  # non-finite
            ((5.0, 0.0, 0.5), IDENTITY, -0.5, 1.0),  # far off-axis: clamped Jacobian
        ]
    )
    return ordinary.cat(hard)


def test_adversarial_scene_matches_the_references():
    # The GPU (float32) against the float64 torch reference, and the float64 Rust reference
    # against it too (the camera and background are exact in float32, so the two references
    # see identical inputs and agree to rounding).
    cam = axis_camera()
    scene = adversarial_scene()
    out, grads = render(scene, cam)
    want, want_grads = assert_matches_dense(scene, cam, out, grads)

    args = core_args(scene, cam, torch.tensor(BACKGROUND), True)
    *images, state = _core.reference_forward(*args)
    for name, image in zip(("features", "alpha", "depth"), images, strict=True):
        np.testing.assert_allclose(image, getattr(want, name).detach().numpy(), atol=1e-9)
    g = torch.Generator().manual_seed(0)  # the weights `render` used
    weights = [torch.rand(img.shape, generator=g, dtype=torch.float64).numpy() for img in images]
    ref_grads = _core.reference_backward(state, *weights)
    for name, a, b in zip(ARRAYS, ref_grads, want_grads, strict=True):
        rel = relative_l2(torch.from_numpy(a), b)
        assert rel <= 1e-9, f"reference d{name}: relative L2 error {rel:.2e}"
