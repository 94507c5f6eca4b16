"""Rasterizer speed: the CPU executor against the wgpu kernels, measured side by side in one run.

For every case (N Gaussians at an S x S image) and channel count (depth on) it times
gear.splat.rasterize forward and the backward of a weighted sum of its images on each executor
(backend "wgpu" and "cpu"), and prints the ratio wgpu / cpu of forward + backward. For each
executor it also prints the Gaussian-pixel evaluations per pixel of its forward blend and the
fraction of them that were blended (useful): the CPU executor counts them always, the wgpu
blend in its counting variant (a separate forward pass, outside the timings). The wgpu blend
evaluates quads of four pixels of a tile row (with subgroups, for every row of the tile at
once), the CPU executor rows of eight, so their evaluation counts differ by design while the
blended pairs are the same. Last, the CPU executor's peak memory (forward state + backward
buffers). Optionally the pure-torch renderer of gear.splat_reference too. Times are medians of
`--repeats` runs after a warm-up (pipeline compilation, buffer allocation and thread start-up
are excluded).

The default scenes are random splats sized like training's: a unit ball of Gaussians covering
its silhouette a few times, sub-pixel at 90k and 128 x 128. With `--checkpoint RUN --scene
SCENE` the scenes are instead a trained model's Gaussians seen from its scene's training
cameras (the first `--views` of them, in the state the model is placed in).
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import torch

from gear import _core, checkpoint, splat, splat_reference
from gear.camera import Camera
from gear.data import load_scene
from gear.device import adapter_info
from gear.run_folder import RunFolderError
from gear.twin import Twin

# Dense torch rendering keeps roughly this many [pixels, N] float32 tables alive at once.
_DENSE_TABLES = 16
_DENSE_BUDGET_BYTES = 2 << 30


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
    parser.add_argument("--checkpoint", type=Path, default=None, metavar="RUN_OR_CKPT",
                        help="time a trained model instead of random splats: a run folder of "
                             "`gear train` (finished or not) or its checkpoint file; needs "
                             "--scene")
    parser.add_argument("--scene", type=Path, default=None,
                        help="the scene the model was trained on (its cameras are used)")
    parser.add_argument("--views", type=int, default=3,
                        help="training views of the scene to time with --checkpoint")


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
# A scene to time: a label, the five rasterizer inputs and a camera.
Case = tuple[str, list[torch.Tensor], Camera]


def trained_model(path: Path) -> tuple[list[torch.Tensor], str, str]:
    """The latest model of a run (folder or checkpoint file): its five rasterizer inputs, the
    state ("start" or "end") it is placed in, and what it is. A finished run's exported twin;
    else its checkpoint's model in training, else the last model a stage finished."""
    if path.is_dir() and (path / "complete.json").exists():
        twin = Twin.load(path)
        return [t.float() for t in twin.splat_arrays()], twin.canonical, "finished run"
    folder = path.parent if path.name == checkpoint.LAST else path / "checkpoints"
    saved = checkpoint.load(folder) if folder.is_dir() else None
    if saved is None:
        raise RunFolderError(f"{path}: not a run folder of `gear train` with a checkpoint, nor "
                             f"its checkpoints/{checkpoint.LAST}")
    stage = str(saved["stage"])
    # Stage 1 trains the model of the state in its name; stage 3 the canonical state's.
    canonical = (saved.get("coarse") or {}).get("canonical")
    if stage == "stage1":  # both states in training: the last one's model
        state = next(reversed(saved["current"]))
        model = saved["current"][state]
        what = f"stage1-{state} model at iteration {saved['iterations'][state]}"
    elif saved.get("current") is not None:
        model = saved["current"]
        state = stage.removeprefix("stage1-") if stage.startswith("stage1-") else canonical
        what = f"{stage} model at iteration {saved['iteration']}"
    elif saved.get("refined") is not None:
        model, state, what = saved["refined"]["gaussians"], canonical, "stage-3 model"
    elif saved.get("models"):
        state = canonical or next(reversed(saved["models"]))
        model, what = saved["models"][state], f"stage-1 model of {state}"
    else:
        raise RunFolderError(f"{path}: its checkpoint holds no model yet")
    arrays = checkpoint.gaussians_from_state(model).splat_arrays()
    return [t.detach().float() for t in arrays], state, what


def checkpoint_cases(args: argparse.Namespace) -> Iterator[Case]:
    """The trained model seen from each of the first --views training cameras of its state."""
    if args.scene is None:
        raise RunFolderError("--checkpoint needs --scene (the scene the model was trained on)")
    arrays, state, what = trained_model(args.checkpoint)
    views = load_scene(args.scene, splits=("train",)).train(state)[: max(args.views, 1)]
    if not views:
        raise RunFolderError(f"{args.scene}: no training views of state {state!r}")
    print(f"{args.checkpoint}: {what}, {len(arrays[0])} Gaussians, state {state}; "
          f"{len(views)} training view(s) of {args.scene}")
    for view in views:
        yield view.name, arrays, view.camera


def random_cases(args: argparse.Namespace) -> Iterator[Case]:
    for n, size in args.cases:
        for channels in args.channels:
            yield "random", scene(n, channels, args.seed), camera(size)


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


def torch_renderer(n: int, pixels: int) -> tuple[str, Renderer]:
    """The dense renderer when its tables fit in the budget, else the tiled one."""
    if _DENSE_TABLES * 4 * n * pixels <= _DENSE_BUDGET_BYTES:
        return "dense", splat_reference.rasterize_dense

    def tiled(*args: object, **kwargs: object) -> splat.RenderOutput:
        return splat_reference.rasterize_tiled(*args, **kwargs, block=16)

    return "tiled", tiled


def forward_stats(arrays: list[torch.Tensor], cam: Camera) -> tuple[dict, dict]:
    """The work counters of one forward pass on each executor (cpu, wgpu: the counting
    variant of its blend)."""
    args = (*(a.contiguous().numpy() for a in arrays),
            np.ascontiguousarray(cam.world_to_cam, dtype=np.float32),
            (cam.fx, cam.fy, cam.cx, cam.cy), cam.width, cam.height,
            np.zeros(arrays[4].shape[1], dtype=np.float32), True)
    *_, cpu_state = _core.rasterize_forward_cpu(*args)
    *_, gpu_state = _core.rasterize_forward_counted(*args)
    return cpu_state.stats(), gpu_state.stats()


def evaluations(stats: dict, pixels: int) -> str:
    """Evaluations per pixel and the fraction of them blended."""
    useful = stats["contributions"] / max(stats["evaluations"], 1)
    return f"{stats['evaluations'] / pixels:>7.1f} {useful:>6.0%}"


def run(args: argparse.Namespace) -> int:
    cases = list(checkpoint_cases(args) if args.checkpoint is not None else random_cases(args))
    info = adapter_info()
    auto, reason = splat.auto_backend()
    print(f"adapter: {info['name']} ({info['backend']}, {info['device_type']}); "
          f"auto picks {auto}: {reason}")
    print(f"cpu executor: {_core.cpu_threads()} threads; torch {torch.__version__}; "
          f"median of {args.repeats} runs, depth on; times in ms")
    header = (f"{'scene':>16} {'N':>7} {'image':>9} {'C':>2} | {'wgpu fwd':>8} {'bwd':>7} "
              f"{'total':>7} | {'cpu fwd':>7} {'bwd':>6} {'total':>6} | {'wgpu/cpu':>8} | "
              f"{'cpu ev/px':>9} {'useful':>6} | {'wgpu ev/px':>10} {'useful':>6} | {'MiB':>5}")
    if args.baseline_max:
        header += f" | {'torch':>6} {'total':>9}"
    print(header)
    print("-" * len(header))
    for label, arrays, cam in cases:
        n, channels = len(arrays[0]), arrays[4].shape[1]
        totals = {}
        line = (f"{label[-16:]:>16} {n:>7} {cam.width:>4}x{cam.height:<4} {channels:>2} | ")
        for backend in ("wgpu", "cpu"):
            render = executor(backend)
            time_renderer(render, arrays, cam, 1)  # warm-up: pipelines, pools, threads
            fwd, bwd = time_renderer(render, arrays, cam, args.repeats)
            totals[backend] = fwd + bwd
            width = 8 if backend == "wgpu" else 7
            line += f"{fwd:>{width}.1f} {bwd:>{width - 1}.1f} {fwd + bwd:>{width - 1}.1f} | "
        cpu, gpu = forward_stats(arrays, cam)
        pixels = cam.width * cam.height
        memory = (cpu["state_bytes"] + cpu["backward_bytes"]) / 2**20
        line += (f"{totals['wgpu'] / totals['cpu']:>7.1f}x | {evaluations(cpu, pixels):>16} | "
                 f"{evaluations(gpu, pixels):>17} | {memory:>5.1f}")
        if n <= args.baseline_max:
            kind, render = torch_renderer(n, pixels)
            tfwd, tbwd = time_renderer(render, arrays, cam, 1)
            line += f" | {kind:>6} {tfwd + tbwd:>9.1f}"
        print(line, flush=True)
    return 0
