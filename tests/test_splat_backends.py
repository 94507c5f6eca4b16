"""Choosing the rasterizer's executor, and what the CPU executor promises beyond the contract:
the two executors agree through torch autograd, and CPU gradients are bitwise identical for
any thread count (GEAR_THREADS) and from run to run."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from gear import _core, splat
from splat_scenes import ARRAYS, camera, random_scene, relative_l2

BACKGROUND = torch.tensor([0.1, 0.3, 0.6])


def render_and_grads(
    backend: str, seed: int = 3, held: int = 0, layered: bool = False
) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """Images and gradients of a random scene; `layered`: drawn over a static layer of the
    `held` first Gaussians."""
    scene = random_scene(2000, 3, seed, 1.0, (-3.5, -2.0)).to(torch.float32, requires_grad=True)
    cam = camera(61, 45)
    layer = splat.static_layer(*(a.detach()[:held] for a in scene.arrays()), cam, True,
                               backend=backend) if layered else None
    out = splat.rasterize(*scene.arrays(), cam, BACKGROUND, True, backend=backend, held=held,
                          layer=layer)
    g = torch.Generator().manual_seed(seed)
    images = [out.features, out.alpha, out.depth]
    loss = sum((img * torch.rand(img.shape, generator=g)).sum() for img in images)
    loss.backward()
    return [img.detach() for img in images], [a.grad for a in scene.arrays()]


def test_cpu_and_wgpu_agree_through_autograd():
    cpu_images, cpu_grads = render_and_grads("cpu")
    gpu_images, gpu_grads = render_and_grads("wgpu")
    for name, a, b in zip(("features", "alpha", "depth"), cpu_images, gpu_images, strict=True):
        assert (a - b).abs().max().item() <= 1e-4, name
    for name, a, b in zip(ARRAYS, cpu_grads, gpu_grads, strict=True):
        assert b.abs().sum() > 0, name
        assert relative_l2(a, b) <= 1e-4, f"d{name}: {relative_l2(a, b):.2e}"


@pytest.mark.parametrize("backend", ["cpu", "wgpu"])
def test_held_gaussians_pass_no_gradient_and_leave_the_others(backend):
    """The first `held` Gaussians (the caller's constants) get zero gradients through
    autograd; the others' are those of a full backward (bit-identical on the CPU executor; the
    wgpu kernels add with atomics in no fixed order) and the images are unchanged."""
    held = 1200
    images, full = render_and_grads(backend)
    held_images, part = render_and_grads(backend, held=held)
    for a, b in zip(images, held_images, strict=True):
        assert torch.equal(a, b)
    for name, a, b in zip(ARRAYS, full, part, strict=True):
        assert torch.count_nonzero(b[:held]) == 0, name
        assert b[held:].abs().sum() > 0, name
        if backend == "cpu":
            assert torch.equal(a[held:], b[held:]), name
        else:
            assert relative_l2(a[held:], b[held:]) <= 1e-5, name


@pytest.mark.parametrize("backend", ["cpu", "wgpu"])
def test_a_static_layer_changes_nothing_but_the_work(backend):
    """Over a static layer of the held Gaussians the CPU executor gives the images and the
    others' gradients of the full render bit for bit; the wgpu kernels keep no layers
    (static_layer gives None) and render everything each time."""
    held = 1200
    images, grads = render_and_grads(backend, held=held)
    layered_images, layered_grads = render_and_grads(backend, held=held, layered=True)
    for a, b in zip(images, layered_images, strict=True):
        assert torch.equal(a, b)
    for name, a, b in zip(ARRAYS, grads, layered_grads, strict=True):
        assert b[held:].abs().sum() > 0, name
        if backend == "cpu":
            assert torch.equal(a, b), name
        else:
            assert relative_l2(a, b) <= 1e-5, name
    scene = random_scene(10, 3, 1, 1.0, (-3.5, -2.0)).to(torch.float32)
    layer = splat.static_layer(*scene.arrays(), camera(31, 23), backend=backend)
    assert (layer is None) == (backend == "wgpu")


def test_a_static_layer_is_checked():
    """A render over a layer must hold the layer's Gaussians, unchanged, seen by the same
    camera with the same depth setting: else a one-line error naming what differs."""
    scene = random_scene(300, 3, 9, 1.0, (-3.5, -2.0)).to(torch.float32)
    cam = camera(31, 23)
    layer = splat.static_layer(*(a[:100] for a in scene.arrays()), cam, backend="cpu")
    assert len(layer) == 100 and "100 Gaussians" in repr(layer) and layer.nbytes > 0

    def render(cam=cam, depth=False, held=100, arrays=scene.arrays()):  # noqa: B008
        return splat.rasterize(*arrays, cam, depth=depth, held=held, layer=layer, backend="cpu")

    assert torch.isfinite(render().features).all()
    with pytest.raises(ValueError, match="'layer' holds 100"):
        render(held=99)
    with pytest.raises(ValueError, match="another camera"):
        render(cam=camera(31, 24))
    with pytest.raises(ValueError, match="depth"):
        render(depth=True)
    moved = [a.clone() for a in scene.arrays()]
    moved[0][42, 1] += 1e-3
    with pytest.raises(ValueError, match="not the layer's"):
        render(arrays=moved)


def test_held_matches_the_reference_and_is_checked():
    """The torch reference cuts the held rows from the graph: the same gradients as the CPU
    executor's (to the executors' parity tolerance); a bad `held` is a one-line error."""
    from gear.splat_reference import rasterize_dense

    scene = random_scene(300, 3, 9, 1.0, (-3.5, -2.0)).to(torch.float32, requires_grad=True)
    grads = []
    for render in (rasterize_dense, lambda *a, **k: splat.rasterize(*a, **k, backend="cpu")):
        for a in scene.arrays():
            a.grad = None
        out = render(*scene.arrays(), camera(31, 23), BACKGROUND, held=120)
        (out.features.sum() + out.alpha.sum()).backward()
        grads.append([a.grad.clone() for a in scene.arrays()])
    for name, ref, cpu in zip(ARRAYS, *grads, strict=True):
        assert torch.count_nonzero(ref[:120]) == 0 and torch.count_nonzero(cpu[:120]) == 0
        assert relative_l2(cpu[120:], ref[120:]) <= 1e-4, name
    for bad, error in ((301, ValueError), (-1, ValueError), (2.5, TypeError)):
        with pytest.raises(error, match="'held'"):
            splat.rasterize(*scene.arrays(), camera(31, 23), held=bad)


def test_gear_backend_chooses_the_executor(monkeypatch):
    scene = random_scene(50, 3, seed=4)
    cam = camera(20, 16)
    for value, executor in (("cpu", "cpu"), ("WGPU", "wgpu"), ("auto", splat.auto_backend()[0])):
        monkeypatch.setenv("GEAR_BACKEND", value)
        assert splat.resolve_backend() == executor
        got = splat.rasterize(*scene.arrays(), cam).features
        want = splat.rasterize(*scene.arrays(), cam, backend=executor).features
        assert torch.equal(got, want), value


def test_unknown_backends_are_one_line_errors(monkeypatch):
    scene = random_scene(5, 3, seed=4)
    monkeypatch.setenv("GEAR_BACKEND", "cuda")
    message = r"^GEAR_BACKEND must be one of auto, cpu, wgpu; got 'cuda'$"
    with pytest.raises(ValueError, match=message):
        splat.rasterize(*scene.arrays(), camera(8, 8))
    monkeypatch.delenv("GEAR_BACKEND")
    with pytest.raises(ValueError, match="'backend' must be None, 'cpu' or 'wgpu'"):
        splat.rasterize(*scene.arrays(), camera(8, 8), backend="gpu")


def test_auto_picks_cpu_exactly_on_a_software_adapter():
    executor, reason = splat.auto_backend()
    software = _core.adapter_info()["device_type"] == "Cpu"
    assert executor == ("cpu" if software else "wgpu")
    assert reason and "\n" not in reason


def test_cpu_state_reports_its_work():
    scene = random_scene(500, 3, seed=6)
    args = [a.detach().numpy() for a in scene.arrays()]
    cam = camera(40, 30)
    *_, state = _core.rasterize_forward_cpu(
        *args, cam.world_to_cam.astype(np.float32), (cam.fx, cam.fy, cam.cx, cam.cy),
        cam.width, cam.height, BACKGROUND.numpy(), False)
    stats = state.stats()
    assert 0 < stats["contributions"] <= stats["evaluations"] <= stats["pairs"] * 64
    assert stats["state_bytes"] > 0 and stats["backward_bytes"] > 0


THREADED_RUN = """
import sys
import numpy as np
sys.path.insert(0, sys.argv[2])
from test_splat_backends import render_and_grads
images, grads = render_and_grads("cpu", seed=8)
np.savez(sys.argv[1], *[t.numpy() for t in images + grads])
"""


def run_with_threads(threads: str, path: Path) -> list[np.ndarray]:
    env = {**os.environ, "GEAR_THREADS": threads}
    tests_dir = str(Path(__file__).parent)
    run = subprocess.run([sys.executable, "-c", THREADED_RUN, str(path), tests_dir],
                         env=env, capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    saved = np.load(path)
    return [saved[k] for k in sorted(saved.files, key=lambda k: int(k.split("_")[1]))]


def test_cpu_results_are_bitwise_identical_for_any_thread_count(tmp_path):
    first = run_with_threads("1", tmp_path / "1.npz")
    for i, threads in enumerate(("2", "7", "7")):
        other = run_with_threads(threads, tmp_path / f"{threads}-{i}.npz")
        for a, b in zip(first, other, strict=True):
            assert a.tobytes() == b.tobytes(), f"{threads} threads differ from 1"


def test_bad_gear_threads_is_an_error():
    env = {**os.environ, "GEAR_THREADS": "many"}
    run = subprocess.run([sys.executable, "-c", "from gear import _core; _core.cpu_threads()"],
                         env=env, capture_output=True, text=True)
    assert run.returncode != 0
    assert "GEAR_THREADS must be a positive integer, got 'many'" in run.stderr
