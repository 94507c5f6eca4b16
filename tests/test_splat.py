"""gear.splat against the pure-torch renderer (gear.splat_reference) and the f64 Rust reference.

Tests that go through gear.splat.rasterize run on both executors (backend "cpu" and "wgpu").
Tolerances: both render in float32; images within 1e-4 (max abs) of the float64 references
(but for the rare values where float32 and float64 fall on either side of the 1/255 alpha skip,
see splat_scenes.assert_images_close), gradients within 1e-3 relative L2 per input array. The
two float64 references (torch and Rust) agree to 1e-9. Finite differences check the torch
reference in float64.
"""

import math
import os
import subprocess
import sys
from pathlib import Path

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

BACKGROUND = (0.1, 0.3, 0.6)


def background(channels: int, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    return torch.tensor([BACKGROUND[c % 3] + 0.01 * c for c in range(channels)], dtype=dtype)


def as_float32(cam: splat.Camera) -> splat.Camera:
    """`cam` with every value rounded to float32, as the GPU and the Rust reference get it."""
    values = (float(np.float32(v)) for v in (cam.fx, cam.fy, cam.cx, cam.cy))
    w2c = cam.world_to_cam.astype(np.float32).astype(np.float64)
    return splat.Camera(w2c, *values, cam.width, cam.height)


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


# --- the GPU binding against the references ------------------------------------------------

# (n, channels, depth, width, height, seed, spread): sizes 1, 16, 300 (dense tables stay
# small); image sizes that are and are not multiples of the 16-pixel tile. Spread 4 puts many
# Gaussians past the 1.3x-frustum clamp of the Jacobian, a few behind the camera.
SCENES = [
    (1, 3, True, 16, 16, 10, 1.0),
    (16, 11, False, 33, 17, 11, 1.0),
    (300, 3, True, 64, 48, 12, 1.0),
    (300, 11, True, 40, 30, 13, 1.0),
    (60, 2, True, 24, 20, 14, 4.0),
]
SCENE_ARGS = ("n", "channels", "depth", "width", "height", "seed", "spread")


def scene_for(n: int, channels: int, seed: int, spread: float) -> Scene:
    """Wider-spread scenes get larger Gaussians so the clamped ones still reach the image."""
    log_scale = (-2.5, -1.2) if spread <= 1 else (-2.0, -0.5)
    return random_scene(n, channels, seed, spread, log_scale)


def loss_weights(out: splat.RenderOutput, seed: int) -> list[torch.Tensor]:
    """Fixed random upstream gradients for each image of `out` (float64)."""
    g = torch.Generator().manual_seed(seed)
    return [torch.rand(img.shape, generator=g, dtype=torch.float64) * 2 - 1 for img in images(out)]


def weighted_loss(out: splat.RenderOutput, weights: list[torch.Tensor]) -> torch.Tensor:
    return sum((img.double() * w).sum() for img, w in zip(images(out), weights, strict=True))


def gradients(scene: Scene, render, seed: int) -> tuple[splat.RenderOutput, list[torch.Tensor]]:
    """Renders `scene` (its arrays must require grad) and back-propagates fixed weights."""
    out = render(*scene.arrays())
    weighted_loss(out, loss_weights(out, seed)).backward()
    return out, [a.grad for a in scene.arrays()]


@pytest.mark.parametrize("backend", splat.BACKENDS)
@pytest.mark.parametrize(SCENE_ARGS, SCENES)
def test_gpu_matches_dense_reference(n, channels, depth, width, height, seed, spread, backend):
    scene = scene_for(n, channels, seed, spread)
    cam = as_float32(camera(width, height))

    def gpu(*arrays: torch.Tensor) -> splat.RenderOutput:
        return splat.rasterize(*arrays, cam, background(channels), depth, backend=backend)

    def dense(*arrays: torch.Tensor) -> splat.RenderOutput:
        return rasterize_dense(*arrays, cam, background(channels).double(), depth)

    got, got_grads = gradients(scene.to(torch.float32, requires_grad=True), gpu, seed)
    want, want_grads = gradients(scene.to(torch.float64, requires_grad=True), dense, seed)
    for name, a, b in zip(("features", "alpha", "depth"), images(got), images(want), strict=False):
        assert a.dtype == torch.float32, name
        assert_images_close(a, b.detach(), name)
    for name, a, b in zip(ARRAYS, got_grads, want_grads, strict=True):
        assert a.dtype == torch.float32 and a.shape == b.shape, name
        rel = relative_l2(a, b)
        assert rel <= 1e-3, f"d{name}: relative L2 error {rel:.2e}"


@pytest.mark.parametrize(SCENE_ARGS, SCENES[1:3] + SCENES[4:])
def test_rust_reference_matches_torch_reference(n, channels, depth, width, height, seed, spread):
    # Two independent float64 implementations of the contract, on the same float32 inputs.
    scene = scene_for(n, channels, seed, spread)
    cam = as_float32(camera(width, height))
    *outputs, state = _core.reference_forward(*core_args(scene, cam, background(channels), depth))
    scene64 = scene.to(torch.float64, requires_grad=True)
    want = rasterize_dense(*scene64.arrays(), cam, background(channels).double(), depth)
    for got, expected in zip(outputs, images(want), strict=False):
        assert got.dtype == np.float64
        np.testing.assert_allclose(got, expected.detach().numpy(), rtol=0, atol=1e-9)

    weights = loss_weights(want, seed)
    weighted_loss(want, weights).backward()
    grad_depth = weights[2].numpy() if depth else None
    got_grads = _core.reference_backward(state, weights[0].numpy(), weights[1].numpy(), grad_depth)
    for name, got, array in zip(ARRAYS, got_grads, scene64.arrays(), strict=True):
        rel = relative_l2(torch.from_numpy(np.asarray(got)), array.grad)
        assert rel <= 1e-9, f"d{name}: relative L2 error {rel:.2e}"


def test_gpu_matches_rust_reference_on_a_larger_scene():
    # 3,000 Gaussians are too many for the dense torch table but cheap for the Rust reference.
    scene = random_scene(3000, 11, seed=17, spread=1.3, log_scale=(-4.0, -2.0))
    cam = camera(96, 80)
    args = core_args(scene, cam, background(11), True)
    *got, gpu_state = _core.rasterize_forward(*args)
    *want, ref_state = _core.reference_forward(*args)
    for name, a, b in zip(("features", "alpha", "depth"), got, want, strict=True):
        assert_images_close(torch.from_numpy(a), torch.from_numpy(b), name)
    g = torch.Generator().manual_seed(3)
    weights = [torch.rand(img.shape, generator=g, dtype=torch.float64) * 2 - 1 for img in want]
    got_grads = _core.rasterize_backward(gpu_state, *(w.float().numpy() for w in weights))
    want_grads = _core.reference_backward(ref_state, *(w.numpy() for w in weights))
    for name, a, b in zip(ARRAYS, got_grads, want_grads, strict=True):
        rel = relative_l2(torch.from_numpy(a), torch.from_numpy(b))
        assert rel <= 1e-3, f"d{name}: relative L2 error {rel:.2e}"


def test_cas_accumulation_matches_atomic_accumulation():
    scene = random_scene(300, 4, seed=21)
    args = core_args(scene, camera(40, 30), background(4), True)
    grads = []
    for force_cas in (False, True):
        *outputs, state = _core.rasterize_forward(*args, force_cas)
        weights = [np.ones_like(img) for img in outputs]
        grads.append(_core.rasterize_backward(state, *weights))
    for name, atomic, cas in zip(ARRAYS, *grads, strict=True):
        # Same terms, summed in another order: float32 rounding only.
        rel = relative_l2(torch.from_numpy(cas), torch.from_numpy(atomic))
        assert rel <= 1e-5, f"d{name}: CAS vs atomic relative L2 {rel:.2e}"


@pytest.mark.parametrize("backend", splat.BACKENDS)
def test_any_memory_layout_is_accepted(backend):
    # Transposed views and a Fortran-order camera matrix render like contiguous inputs.
    scene = random_scene(30, 4, seed=8)
    cam = camera(20, 16)
    fortran_cam = splat.Camera(
        np.asfortranarray(cam.world_to_cam), cam.fx, cam.fy, cam.cx, cam.cy, 20, 16
    )
    arrays = list(scene.arrays())
    arrays[0] = arrays[0].T.contiguous().T
    arrays[4] = arrays[4].T.contiguous().T
    assert not arrays[0].is_contiguous()
    got = splat.rasterize(*arrays, fortran_cam, depth=True, backend=backend)
    want = splat.rasterize(*scene.arrays(), cam, depth=True, backend=backend)
    for a, b in zip(images(got), images(want), strict=True):
        assert torch.equal(a, b)


@pytest.mark.parametrize("backend", splat.BACKENDS)
def test_gradients_only_for_inputs_that_require_them(backend):
    scene = random_scene(20, 3, seed=5)
    scene.features.requires_grad_(True)
    scene.log_scales.requires_grad_(True)
    out = splat.rasterize(*scene.arrays(), camera(16, 16), backend=backend)
    assert out.depth is None
    (out.features.sum() + out.alpha.sum()).backward()
    assert scene.means.grad is None and scene.quats.grad is None
    assert scene.opacity_logits.grad is None
    assert scene.features.grad.abs().sum() > 0 and scene.log_scales.grad.abs().sum() > 0



@pytest.mark.parametrize("backend", splat.BACKENDS)
@pytest.mark.parametrize("channels", [1, 5])
def test_detached_features_leave_geometry_gradients_unchanged(channels, backend):
    # Detached features skip their gradients in the kernel; the geometry's must not change
    # (beyond the float32 rounding of atomics adding in another order).
    scene = random_scene(300, channels, seed=23)
    cam = camera(40, 30)
    geometry = [a.requires_grad_(True) for a in scene.arrays()[:4]]
    grads = []
    for features in (scene.features.clone().requires_grad_(True), scene.features):
        out = splat.rasterize(*geometry, features, cam, background(channels), depth=True,
                              backend=backend)
        loss = weighted_loss(out, loss_weights(out, seed=5))
        grads.append(torch.autograd.grad(loss, geometry))
    for name, with_features, detached in zip(ARRAYS, *grads, strict=False):
        assert with_features.abs().sum() > 0, name
        rel = relative_l2(detached, with_features)
        assert rel <= 1e-6, f"d{name}: detached vs attached features relative L2 {rel:.2e}"


def test_backward_without_feature_gradients_returns_none_for_them():
    scene = random_scene(30, 3, seed=9)
    args = core_args(scene, camera(20, 16), background(3), False)
    *outputs, state = _core.rasterize_forward(*args)
    weights = [np.ones_like(img) for img in outputs[:2]]
    full = _core.rasterize_backward(state, *weights)
    partial = _core.rasterize_backward(state, *weights, features_grad=False)
    assert full[4].shape == (30, 3) and partial[4] is None
    for name, a, b in zip(ARRAYS[:4], full, partial, strict=False):
        assert relative_l2(torch.from_numpy(b), torch.from_numpy(a)) <= 1e-6, name


# --- bad input -----------------------------------------------------------------------------


def test_wrong_dtype_names_the_argument():
    scene = random_scene(4)
    arrays = list(scene.arrays())
    arrays[0] = arrays[0].double()
    with pytest.raises(TypeError, match=r"'means'.*float32"):
        splat.rasterize(*arrays, camera())
    with pytest.raises(TypeError, match="'quats'"):
        splat.rasterize(scene.means, scene.quats.numpy(), *scene.arrays()[2:], camera())


@pytest.mark.parametrize(
    ("index", "bad", "name"),
    [
        (1, torch.zeros(4, 3), "quats"),
        (2, torch.zeros(3, 3), "log_scales"),
        (3, torch.zeros(4, 1), "opacity_logits"),
        (4, torch.zeros(4, 0), "features"),
        (4, torch.zeros(4, 65), "features"),
    ],
)
def test_wrong_shape_names_the_argument(index, bad, name):
    arrays = list(random_scene(4).arrays())
    arrays[index] = bad
    with pytest.raises(ValueError, match=f"'{name}'"):
        splat.rasterize(*arrays, camera())


def test_bad_camera_and_background_are_rejected():
    scene = random_scene(4)
    with pytest.raises(TypeError, match="'camera'"):
        splat.rasterize(*scene.arrays(), np.eye(4))
    broken = camera()
    object.__setattr__(broken, "fx", float("nan"))  # bypass the constructor's own check
    with pytest.raises(ValueError, match=r"'camera'.*non-finite"):
        splat.rasterize(*scene.arrays(), broken)
    with pytest.raises(ValueError, match="'background'"):
        splat.rasterize(*scene.arrays(), camera(), background=torch.zeros(2))
    with pytest.raises(ValueError, match=r"'background'.*non-finite"):
        splat.rasterize(*scene.arrays(), camera(), background=torch.full((3,), float("inf")))


FALLBACK_RENDER = """
import sys
import numpy as np
import torch
sys.path.insert(0, sys.argv[2])
from gear import _core, splat
from splat_scenes import camera, random_scene
info = _core.adapter_info()
scene = random_scene(400, 3, seed=21).to(torch.float32, requires_grad=True)
cam = camera(40, 32)
out = splat.rasterize(*scene.arrays(), cam, torch.tensor([0.1, 0.3, 0.6]), True, backend="wgpu")
(out.features.sum() + out.depth.sum()).backward()
np.savez(sys.argv[1], subgroups=info["subgroups"], atomics=info["float32_atomics"],
         image=out.features.detach().numpy(), depth=out.depth.detach().numpy(),
         **{f"d_{i}": a.grad.numpy() for i, a in enumerate(scene.arrays())})
"""


def test_disabled_features_take_the_fallback_paths_with_the_same_result(tmp_path):
    """GEAR_DISABLE_FEATURES=subgroups,float32_atomics: the adapter reports both off and the
    per-row blend + compare-and-swap paths render the same image and gradients (1e-5 image,
    1e-4 relative L2 gradients: atomics sum in another order) as the default process; a
    misspelt feature is a clear error, not a silent no-op."""
    tests_dir = str(Path(__file__).parent)
    results = {}
    for label, disable in (("default", ""), ("fallback", "subgroups, float32_atomics")):
        env = {**os.environ, "GEAR_DISABLE_FEATURES": disable}
        path = tmp_path / f"{label}.npz"
        run = subprocess.run([sys.executable, "-c", FALLBACK_RENDER, str(path), tests_dir],
                             env=env, capture_output=True, text=True)
        assert run.returncode == 0, run.stderr
        results[label] = np.load(path)
    assert not results["fallback"]["subgroups"] and not results["fallback"]["atomics"]
    default, fallback = results["default"], results["fallback"]
    for name in ("image", "depth"):
        np.testing.assert_allclose(fallback[name], default[name], atol=1e-5, err_msg=name)
    for i, name in enumerate(ARRAYS):
        rel = relative_l2(torch.from_numpy(fallback[f"d_{i}"]), torch.from_numpy(default[f"d_{i}"]))
        assert rel <= 1e-4, f"d{name}: {rel:.2e}"
    env = {**os.environ, "GEAR_DISABLE_FEATURES": "subgroup"}
    run = subprocess.run([sys.executable, "-c", "from gear import _core; _core.adapter_info()"],
                         env=env, capture_output=True, text=True)
    assert run.returncode != 0 and "unknown feature \"subgroup\"" in run.stderr, run.stderr
