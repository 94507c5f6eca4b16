"""Where a training iteration's time goes, on a run's own model: stage 1, stage 3's E-step and
M-step, each split into rasterizer forward / backward, Adam and the rest.

`gear bench step RUN --scene SCENE` rebuilds, from RUN's checkpoint, the stage states the run
trains (stage 1 on the canonical state's model, stage 3 on its refined or in-training model)
and times `--steps` iterations of each after `--warmup` untimed ones. The steps run on a copy:
RUN is only read. Times are wall milliseconds per iteration (the median over the steps) and the
process CPU time (every thread: the rasterizer's and torch's), which is what compares on a
shared machine. The split comes from torch's profiler: the rasterizer's autograd function
(forward and backward), the optimisers' steps, and the rest of the iteration (losses, posing,
KNN, densification statistics, Python). The profiler sees only the thread it runs on, so the
work that training runs beside the caller (the M-step's views: pipeline.common.map_beside)
runs in turn here: the phases are timed without that overlap.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import statistics
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile

from gear import checkpoint
from gear.config import TrainConfig
from gear.data import load_scene
from gear.data.scene import STATES
from gear.device import limit_torch_threads
from gear.pipeline.common import Stage, TrainView, in_turn
from gear.pipeline.stage1 import ReconstructState, Stage1Result
from gear.pipeline.stage2 import Stage2Result
from gear.pipeline.stage3.refine import Refine, refine_state, resumed_refine_state
from gear.run_folder import RunFolderError

# The profiler's names for the rasterizer's autograd function and for the optimisers' steps.
RASTER_FORWARD = "_Rasterize"
RASTER_BACKWARD = "_RasterizeBackward"
OPTIMIZER_PREFIX = "Optimizer.step#"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", type=Path, metavar="RUN",
                        help="a run folder of `gear train` (finished or in stage 3)")
    parser.add_argument("--scene", type=Path, required=True,
                        help="the scene folder the run was trained on")
    parser.add_argument("--steps", type=int, default=5, help="timed iterations per phase")
    parser.add_argument("--warmup", type=int, default=2, help="untimed iterations first")


@dataclass
class PhaseTiming:
    """One phase's per-iteration figures (milliseconds; medians over the timed steps)."""

    phase: str
    gaussians: int
    wall: float
    cpu: float
    raster_forward: float
    raster_backward: float
    raster_calls: float
    optimizer: float

    @property
    def rest(self) -> float:
        return max(self.wall - self.raster_forward - self.raster_backward - self.optimizer, 0.0)


def run(args: argparse.Namespace) -> int:
    if args.steps < 1 or args.warmup < 0:
        raise ValueError("--steps must be >= 1 and --warmup >= 0")
    limit_torch_threads()  # the thread policy of `gear train`
    timings = [time_phase(name, stage, it, args.steps, args.warmup)
               for name, stage, it in phases(args.run, args.scene)]
    print(markdown_table(timings))
    return 0


def phases(run_dir: Path, scene_dir: Path) -> Iterator[tuple[str, Stage, int]]:
    """(name, stage state, iteration) of stage 1 and of stage 3's E- and M-steps, late in
    their schedules (past densification, with a frozen anchor's renders cached)."""
    saved = checkpoint.load(run_dir / "checkpoints") if (run_dir / "checkpoints").is_dir() else None
    if saved is None or not saved.get("models") or saved.get("coarse") is None:
        raise RunFolderError(f"{run_dir}: needs a run of `gear train` past stage 2 "
                             "(a checkpoint with stage-1 models and stage 2's parts)")
    config = TrainConfig(**saved["config"])
    scene = load_scene(scene_dir)
    if checkpoint.scene_fingerprint(scene_dir, scene) != saved.get("scene"):
        raise RunFolderError(f"{scene_dir}: not the scene {run_dir} was trained on")
    views = {s: [TrainView.from_view(v) for v in scene.train(s)] for s in STATES}
    models = Stage1Result.from_checkpoint(saved["models"]).models
    coarse = Stage2Result.from_checkpoint(saved["coarse"])

    canonical = models[coarse.canonical].clone()
    stage1 = ReconstructState(canonical, views[coarse.canonical], config, config.seed,
                              coarse.canonical)
    yield "stage 1", stage1, config.stage1_iterations - 1

    refine = stage3_state(saved, models, coarse, views, config)
    refine.cache_anchor_renders()
    for phase in ("E", "M"):
        it = next(i for i in range(config.stage3_iterations - 1, -1, -1)
                  if refine.phase(i) == phase and i != config.joint_classify_iteration)
        if phase == "M":
            make_static_layers(refine)
        yield f"stage 3, {phase}-step", refine, it


def make_static_layers(refine: Refine) -> None:
    """Renders every target view of the held model once: an M-phase of hundreds of steps
    makes the static part's layer of each view at its first render and draws over it after,
    so the timed steps should find them made."""
    with torch.no_grad():
        views = refine.target_views
        refine.held_image_terms(refine.motion, views, [torch.zeros(3)] * len(views))


def stage3_state(saved: dict, models: dict, coarse: Stage2Result,
                 views: dict[str, list[TrainView]], config: TrainConfig) -> Refine:
    """Stage 3's state as the checkpoint left it: in training, or the refined result."""
    if str(saved["stage"]) == "stage3":
        return resumed_refine_state(saved, coarse, views, config)
    refined = saved.get("refined")
    if refined is None:
        raise RunFolderError("the run has not reached stage 3 yet: time it once stage 3 runs")
    state = refine_state(checkpoint.gaussians_from_state(refined["gaussians"]),
                         models[coarse.canonical], coarse, views, config)
    state.motion.load_state_dict(refined["motion"])
    return state


def time_phase(name: str, stage: Stage, it: int, steps: int, warmup: int) -> PhaseTiming:
    """Iteration `it` of `stage` run warmup + steps times (in turn: see the module's doc); the
    medians of the timed ones."""
    with in_turn():
        return _timed_phase(name, stage, it, steps, warmup)


def _timed_phase(name: str, stage: Stage, it: int, steps: int, warmup: int) -> PhaseTiming:
    for _ in range(warmup):
        stage.step(it)
    walls, cpus, forwards, backwards, calls, optimizers = [], [], [], [], [], []
    for _ in range(steps):
        with _quiet_profiler() as prof:
            wall0, cpu0 = time.perf_counter(), time.process_time()
            stage.step(it)
            walls.append(1e3 * (time.perf_counter() - wall0))
            cpus.append(1e3 * (time.process_time() - cpu0))
        events = prof.key_averages()
        forwards.append(_total(events, lambda k: k == RASTER_FORWARD))
        backwards.append(_total(events, lambda k: k == RASTER_BACKWARD))
        calls.append(sum(e.count for e in events if e.key == RASTER_FORWARD))
        optimizers.append(_total(events, lambda k: k.startswith(OPTIMIZER_PREFIX)))
    return PhaseTiming(name, len(stage.gaussians), *(statistics.median(v) for v in (
        walls, cpus, forwards, backwards, calls, optimizers)))


def _total(events: object, wanted: Callable[[str], bool]) -> float:
    """Milliseconds of wall time inside the profiler events whose name `wanted` accepts."""
    return sum(e.cpu_time_total for e in events if wanted(e.key)) / 1e3  # type: ignore[attr-defined]


@contextlib.contextmanager
def _quiet_profiler() -> Iterator[profile]:
    """torch's CPU profiler with its start / stop chatter on the C-level stderr silenced."""
    saved = os.dup(2)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
        prof = profile(activities=[ProfilerActivity.CPU])
        prof.__enter__()
        os.dup2(saved, 2)
        try:
            yield prof
        finally:
            os.dup2(devnull, 2)
            prof.__exit__(None, None, None)
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)


def markdown_table(timings: list[PhaseTiming]) -> str:
    rows = ["| ms / iteration | " + " | ".join(t.phase for t in timings) + " |",
            "|---|" + "---|" * len(timings)]

    def row(label: str, values: list[str]) -> None:
        rows.append(f"| {label} | " + " | ".join(values) + " |")

    row("Gaussians", [f"{t.gaussians:,}" for t in timings])
    row("render forward (calls)", [f"{t.raster_forward:.1f} ({t.raster_calls:.0f})"
                                   for t in timings])
    row("render backward", [f"{t.raster_backward:.1f}" for t in timings])
    row("optimiser steps", [f"{t.optimizer:.1f}" for t in timings])
    row("rest (losses, posing, KNN, statistics, Python)", [f"{t.rest:.1f}" for t in timings])
    row("**wall**", [f"**{t.wall:.1f}**" for t in timings])
    row("process CPU", [f"{t.cpu:.1f}" for t in timings])
    return "\n".join(rows)
