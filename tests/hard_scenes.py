"""Scenes, runs and measurements shared by the hard-case suite (tests/test_hard_cases.py).

Hard cases are built-in objects (gear.synth), sometimes with their joint values changed (a door
turned by 2 degrees, a drawer pulled by 1 % of the object's size, two identical states), rendered
tiny. Training runs use the `quick` profile with its schedule compressed about 4x (every event
in the same order: densification, E/M switches, joint classification) so the suite fits CI;
set GEAR_HARD_QUICK=1 to run the uncompressed quick schedule instead.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from gear.config import TrainConfig, make_config
from gear.data import Scene, load_scene
from gear.splats.init import points_from_depth
from gear.synth import build, render_scene
from gear.synth.model import Articulated

# The quick profile's schedule (300 + 300 iterations) compressed about 4x, its events in the
# same order: stage 1 densifies three times (24, 36, 48) and stops at 60; stage 3 alternates E/M
# every 13 iterations (quick: 50), densifies in E-steps until 40 and classifies joints at 40
# (quick: 150). Like quick, no opacity reset; the small-part test adds them.
COMPRESSED_QUICK = dict(
    stage1_iterations=70, stage3_iterations=80, em_interval=13,
    densify_from=20, densify_until=60, densify_interval=12,
    stage3_densify_until=40, joint_classify_iteration=40, em_refine_joint_iterations=26,
    init_max_points=1500, max_gaussians=2500, checkpoint_every=10_000,
)
FULL_QUICK = os.environ.get("GEAR_HARD_QUICK") == "1"
# The quick profile's own stage-1 schedule (300 iterations, densifying from 100 to 250 every 50),
# for cases whose stage 1 needs more than the compressed 70 iterations.
STAGE1_QUICK = {name: getattr(make_config("quick"), name) for name in
                ("stage1_iterations", "densify_from", "densify_until", "densify_interval")}


def hard_config(**overrides: object) -> TrainConfig:
    """The hard-case training config (float32, like every gear run): the compressed quick
    schedule above, or the quick profile itself with GEAR_HARD_QUICK=1."""
    base = {} if FULL_QUICK else dict(COMPRESSED_QUICK)
    return make_config("quick", {**base, "log_every": 1, **overrides})


def variant(name: str, values: dict[str, tuple[float, float]] | None = None) -> Articulated:
    """The built-in object `name` with some joints moved: {joint name: (start, end)} in radians
    or metres. Joint limits are kept (a value outside them is an error)."""
    obj = build(name)
    for part in obj.parts:
        if values and part.joint.name in values:
            start, end = values[part.joint.name]
            part.joint = dataclasses.replace(part.joint, start=start, end=end)
    return obj


def object_size(obj: Articulated) -> float:
    """Largest side of the object's bounding box in its start state."""
    verts = np.concatenate([s.vertices for group in obj.posed("start") for s in group])
    return float(np.ptp(verts, axis=0).max())


def make_scene(root: Path, obj: Articulated, res: int, views: int, effects: tuple = (),
               depth: bool = True, seed: int = 0) -> Path:
    """Renders `obj` into `root` (one test view per state); without `depth`, the depth images are
    deleted so the scene has none."""
    scene = render_scene(obj, root, res=res, views=views, test_views=1, seed=seed,
                         effects=frozenset(effects))
    if not depth:
        for folder in scene.glob("*/*/depth"):
            shutil.rmtree(folder)
    return scene


def backprojected(scene_dir: Path, voxel_fraction: float = 0.004) -> dict[str, np.ndarray]:
    """Each state's depth back-projected inside the masks and voxel-downsampled (voxel =
    `voxel_fraction` x the object's bounding-box side): a clean stand-in for a stage-1 model's
    centres, for tests that are about stage 2."""
    scene = load_scene(scene_dir, splits=("train",))
    out = {}
    for state in ("start", "end"):
        views = scene.train(state)
        probe, _ = points_from_depth(views, 1e-3, 10**7, np.random.default_rng(0))
        voxel = voxel_fraction * float(np.ptp(probe, axis=0).max())
        out[state], _ = points_from_depth(views, voxel, 10**6, np.random.default_rng(0))
    return out


@dataclass
class Run:
    """One training run: its scene, the joints it reports (start -> end, world frame), the
    stage-3 result (None when stage 2 found no motion), the log records and the notes."""

    scene: Scene
    out_dir: Path
    joints: list[dict]
    canonical: str
    num_parts: int
    refine: object | None
    coarse: dict
    timings: dict[str, float]
    records: list[dict] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def events(self, name: str) -> list[dict]:
        return [r for r in self.records if r.get("event") == name]

    def losses(self) -> list[tuple[str, int, str, float]]:
        """Every logged loss term: (stage, iteration, term, value)."""
        skip = {"stage", "iteration", "gaussians", "phase"}
        return [(r["stage"], r["iteration"], k, float(v)) for r in self.records
                if "iteration" in r and "event" not in r
                for k, v in r.items() if k not in skip]


def run_stages(scene_dir: Path, out_dir: Path, config: TrainConfig) -> Run:
    """Stages 1-3 as `gear train` runs them (same stage entry points), keeping the stage-3
    object for inspection; the output files (renders, meshes) are not written."""
    from gear.data.scene import STATES
    from gear.pipeline.common import TrainView
    from gear.pipeline.runner import Runner
    from gear.pipeline.stage1 import reconstruct_states
    from gear.pipeline.stage2 import initialise_parts
    from gear.pipeline.stage3 import refine_parts

    scene = load_scene(scene_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(config.seed)
    runner = Runner(out_dir, config, quiet=True)
    try:
        views = {s: [TrainView.from_view(v) for v in scene.train(s)] for s in STATES}
        models = reconstruct_states({s: scene.train(s) for s in STATES}, views, config,
                                    runner, None).models
        coarse = initialise_parts(models, views, config, runner)
        refine = refine_parts(models, coarse, views, config, runner, None)
    finally:
        runner.log.close()
    joints = [] if refine is None else refine.joints()
    return Run(scene, out_dir, joints, coarse.canonical, coarse.num_parts, refine,
               vars(coarse), dict(runner.timings), read_log(out_dir / "log.jsonl"),
               list(coarse.notes))


def read_log(path: Path) -> list[dict]:
    return [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]


def axis_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two lines' directions (sign-free), degrees."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    cos = abs(float(a @ b)) / (np.linalg.norm(a) * np.linalg.norm(b))
    return math.degrees(math.acos(min(1.0, cos)))


def line_distance(point: np.ndarray, origin: np.ndarray, axis: np.ndarray) -> float:
    """Distance from `point` to the line (origin, axis)."""
    d = np.asarray(axis, float) / np.linalg.norm(axis)
    off = np.asarray(point, float) - np.asarray(origin, float)
    return float(np.linalg.norm(off - (off @ d) * d))
