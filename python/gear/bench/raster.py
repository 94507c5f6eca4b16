"""Rasterizer speed: GPU forward/backward vs the pure-torch renderer, measured in one run.

For every scene size, image size and channel count (depth on) it times gear.splat.rasterize
(forward) and the backward of a weighted sum of its images, then the same for the pure-torch
renderer of gear.splat_reference (dense where its [pixels, N] tables fit in memory, else the
tiled version), and prints the speed-ups. Times are medians of `--repeats` runs after a warm-up
(pipeline compilation and buffer allocation are excluded).
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import numpy as np
import torch

from gear import splat, splat_reference
from gear.camera import Camera
from gear.device import adapter_info

# Dense torch rendering keeps roughly this many [pixels, N] float32 tables alive at once.
_DENSE_TABLES = 16
_DENSE_BUDGET_BYTES = 2 << 30


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000, 500_000],
                        help="numbers of Gaussians")
    parser.add_argument("--resolutions", type=int, nargs="+", default=[256, 800],
                        help="square image sizes in pixels")
    parser.add_argument("--channels", type=int, nargs="+", default=[3, 11],
                        help="feature channel counts")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per measurement")
    parser.add_argument("--baseline-max", type=int, default=100_000,
                        help="skip the pure-torch baseline above this many Gaussians (it is slow)")
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


def torch_renderer(n: int, size: int) -> tuple[str, Renderer]:
    """The dense renderer when its tables fit in the budget, else the tiled one."""
    if _DENSE_TABLES * 4 * n * size * size <= _DENSE_BUDGET_BYTES:
        return "dense", splat_reference.rasterize_dense

    def tiled(*args: object, **kwargs: object) -> splat.RenderOutput:
        return splat_reference.rasterize_tiled(*args, **kwargs, block=16)

    return "tiled", tiled


def run(args: argparse.Namespace) -> int:
    info = adapter_info()
    print(f"adapter: {info['name']} ({info['backend']}, {info['device_type']}), "
          f"float32 atomics: {info['float32_atomics']}")
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads; "
          f"median of {args.repeats} runs, depth on; times in ms")
    header = (f"{'N':>8} {'image':>9} {'C':>3} | {'gpu fwd':>8} {'gpu bwd':>8} {'total':>8} | "
              f"{'torch':>6} {'fwd':>9} {'bwd':>9} | {'speed-up':>8}")
    print(header)
    print("-" * len(header))
    for n in args.sizes:
        for size in args.resolutions:
            cam = camera(size)
            for channels in args.channels:
                arrays = scene(n, channels, args.seed)
                time_renderer(splat.rasterize, arrays, cam, 1)  # warm-up: pipelines, pool
                fwd, bwd = time_renderer(splat.rasterize, arrays, cam, args.repeats)
                line = (f"{n:>8} {size:>4}x{size:<4} {channels:>3} | {fwd:>8.1f} {bwd:>8.1f} "
                        f"{fwd + bwd:>8.1f} | ")
                if n <= args.baseline_max:
                    kind, render = torch_renderer(n, size)
                    tfwd, tbwd = time_renderer(render, arrays, cam, 1)
                    line += (f"{kind:>6} {tfwd:>9.1f} {tbwd:>9.1f} | "
                             f"{(tfwd + tbwd) / (fwd + bwd):>7.1f}x")
                else:
                    line += f"{'-':>6} {'skipped':>9} {'':>9} | {'-':>8}"
                print(line, flush=True)
    return 0
