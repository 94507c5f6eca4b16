"""Rasterizer speed: the CPU executor against the wgpu kernels, measured side by side in one run.

For every case (N Gaussians at an S x S image) and channel count (depth on) it times
gear.splat.rasterize forward and the backward of a weighted sum of its images on each executor
(backend "wgpu" and "cpu"), and prints the ratio wgpu / cpu of forward + backward. For the CPU
executor it also prints the Gaussian-pixel evaluations per pixel of its forward blend, the
fraction of them that were blended (useful), and its peak memory (forward state + backward
buffers); for wgpu, the evaluations per pixel its blend may make at most (every pixel of a tile
evaluates the tile's list up to its early exit). Optionally the pure-torch renderer of
gear.splat_reference too. Times are medians of `--repeats` runs after a warm-up (pipeline
compilation, buffer allocation and thread start-up are excluded).

The default scenes are random splats sized like training's: a unit ball of Gaussians covering
its silhouette a few times, sub-pixel at 90k and 128 x 128.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import numpy as np
import torch

from gear import _core, splat, splat_reference
from gear.camera import Camera
from gear.device import adapter_info

# Dense torch rendering keeps roughly this many [pixels, N] float32 tables alive at once.
_DENSE_TABLES = 16
_DENSE_BUDGET_BYTES = 2 << 30
# Pixels per tile of the wgpu blend (GPU_TILE² in gear-core's kernels).
_GPU_TILE_PIXELS = 64


def case(text: str) -> tuple[int, int]:
    """N@SIZE, e.g. 90000@128."""
    try:
        n, size = text.split("@")
        return int(n), int(size)
    except ValueError:
        message = f"expected N@SIZE (e.g. 90000@128), got {text!r}"
        raise argparse.ArgumentTypeError(message) from None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--cases", type=case, nargs="+",
                        default=[(90_000, 128), (100_000, 256), (500_000, 800)],
                        help="N@SIZE: N Gaussians at a SIZE x SIZE image")
    parser.add_argument("--channels", type=int, nargs="+", default=[3],
                        help="feature channel counts")
    parser.add_argument("--repeats", type=int, default=5, help="timed runs per measurement")
    parser.add_argument("--baseline-max", type=int, default=0,
                        help="also time the pure-torch renderer up to this many Gaussians "
                             "(default 0: not at all; it is slow)")
    parser.add_argument("--seed", type=int, default=0)


def scene(n: int, channels: int, seed: int) -> list[torch.Tensor]:
    """n Gaussians filling a unit ball, sized so that the ball is covered a few times over."""
    g = torch.Generator().manual_seed(seed)
    direction = torch.randn(n, 3, generator=g)
    direction /= direction.norm(dim=1, keepdim=True).clamp_min(1e-9)
    means = direction * torch.rand(n, 1, generator=g) ** (1 / 3)
    # Mean radius such that n disks of that radius cover the ball's silhouette ~4 times.
    radius = 2.0 / n**0.5
    log_scales = (torch.log(torch.tensor(radius)) + 0.3 * torch.randn(n, 3, generator=g))
    return [
        means,
        torch.randn(n, 4, generator=g),
        log_scales,
        torch.randn(n, generator=g),
        torch.rand(n, channels, generator=g),
    ]


def camera(size: int) -> Camera:
    return Camera.look_at(np.array([0.0, -0.5, -3.5]), np.zeros(3), np.array([0.0, -1.0, 0.0]),
                          fov_x=0.75, width=size, height=size)


Renderer = Callable[..., splat.RenderOutput]


def time_renderer(render: Renderer, arrays: list[torch.Tensor], cam: Camera,
                  repeats: int) -> tuple[float, float]:
    """Median forward and backward wall time in milliseconds."""
    forward, backward = [], []
    for _ in range(repeats):
        inputs = [a.clone().requires_grad_(True) for a in arrays]
        start = time.perf_counter()
        out = render(*inputs, cam, background=None, depth=True)
        middle = time.perf_counter()
        loss = out.features.sum() + out.alpha.sum() + 0.1 * out.depth.sum()
        loss.backward()
        end = time.perf_counter()
        forward.append(1e3 * (middle - start))
        backward.append(1e3 * (end - middle))
    return statistics.median(forward), statistics.median(backward)


def executor(backend: str) -> Renderer:
    def render(*args: object, **kwargs: object) -> splat.RenderOutput:
        return splat.rasterize(*args, **kwargs, backend=backend)

    return render


def torch_renderer(n: int, size: int) -> tuple[str, Renderer]:
    """The dense renderer when its tables fit in the budget, else the tiled one."""
    if _DENSE_TABLES * 4 * n * size * size <= _DENSE_BUDGET_BYTES:
        return "dense", splat_reference.rasterize_dense

    def tiled(*args: object, **kwargs: object) -> splat.RenderOutput:
        return splat_reference.rasterize_tiled(*args, **kwargs, block=16)

    return "tiled", tiled


def forward_stats(arrays: list[torch.Tensor], cam: Camera) -> tuple[dict, dict]:
    """The work counters of one forward pass on each executor (cpu, wgpu)."""
    args = (*(a.contiguous().numpy() for a in arrays),
            np.ascontiguousarray(cam.world_to_cam, dtype=np.float32),
            (cam.fx, cam.fy, cam.cx, cam.cy), cam.width, cam.height,
            np.zeros(arrays[4].shape[1], dtype=np.float32), True)
    *_, cpu_state = _core.rasterize_forward_cpu(*args)
    *_, gpu_state = _core.rasterize_forward(*args)
    return cpu_state.stats(), gpu_state.stats()


def run(args: argparse.Namespace) -> int:
    info = adapter_info()
    auto, reason = splat.auto_backend()
    print(f"adapter: {info['name']} ({info['backend']}, {info['device_type']}); "
          f"auto picks {auto}: {reason}")
    print(f"cpu executor: {_core.cpu_threads()} threads; torch {torch.__version__}; "
          f"median of {args.repeats} runs, depth on; times in ms")
    header = (f"{'N':>7} {'image':>9} {'C':>2} | {'wgpu fwd':>8} {'bwd':>7} {'total':>7} | "
              f"{'cpu fwd':>7} {'bwd':>6} {'total':>6} | {'wgpu/cpu':>8} | {'eval/px':>7} "
              f"{'useful':>6} {'wgpu<=':>7} | {'MiB':>5}")
    if args.baseline_max:
        header += f" | {'torch':>6} {'total':>9}"
    print(header)
    print("-" * len(header))
    for n, size in args.cases:
        cam = camera(size)
        pixels = size * size
        for channels in args.channels:
            arrays = scene(n, channels, args.seed)
            totals = {}
            line = f"{n:>7} {size:>4}x{size:<4} {channels:>2} | "
            for backend in ("wgpu", "cpu"):
                render = executor(backend)
                time_renderer(render, arrays, cam, 1)  # warm-up: pipelines, pools, threads
                fwd, bwd = time_renderer(render, arrays, cam, args.repeats)
                totals[backend] = fwd + bwd
                width = 8 if backend == "wgpu" else 7
                line += f"{fwd:>{width}.1f} {bwd:>{width - 1}.1f} {fwd + bwd:>{width - 1}.1f} | "
            cpu, gpu = forward_stats(arrays, cam)
            memory = (cpu["state_bytes"] + cpu["backward_bytes"]) / 2**20
            line += (f"{totals['wgpu'] / totals['cpu']:>7.1f}x | "
                     f"{cpu['evaluations'] / pixels:>7.1f} "
                     f"{cpu['contributions'] / max(cpu['evaluations'], 1):>6.0%} "
                     f"{gpu['pairs'] * _GPU_TILE_PIXELS / pixels:>7.0f} | {memory:>5.1f}")
            if n <= args.baseline_max:
                kind, render = torch_renderer(n, size)
                tfwd, tbwd = time_renderer(render, arrays, cam, 1)
                line += f" | {kind:>6} {tfwd + tbwd:>9.1f}"
            print(line, flush=True)
    return 0
