"""`train(scene_dir, out_dir, config)`: the method's outline (docs/architecture.md).

1. Stage 1 reconstructs each state on its own (gear.pipeline.stage1).
2. Stage 2 finds the parts, their motions and part logits from the two models
   (gear.pipeline.stage2).
3. Stage 3 refines parts and motions by EM and decides the joint types
   (gear.pipeline.stage3).
4. The outputs are written (gear.outputs).

Checkpoints let an interrupted run continue to the same result (gear.pipeline.runner)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from gear import checkpoint, outputs
from gear.config import TrainConfig
from gear.data import load_scene
from gear.data.coverage import input_warnings
from gear.data.scene import STATES
from gear.device import limit_torch_threads
from gear.pipeline.common import TrainView
from gear.pipeline.runner import Runner
from gear.pipeline.stage1 import reconstruct_states
from gear.pipeline.stage2 import Stage2Result, initialise_parts
from gear.pipeline.stage3 import refine_parts


@dataclass
class TrainResult:
    joints: list[dict]
    canonical: str
    timings: dict[str, float] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)


def train(scene_dir: Path, out_dir: Path, config: TrainConfig, *, resume: bool = False,
          quiet: bool = False) -> TrainResult:
    """Runs the whole method on a scene folder and writes the outputs to `out_dir`."""
    scene = load_scene(scene_dir)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    state = checkpoint.load(out_dir / "checkpoints") if resume else None
    if resume and state is None:
        raise ValueError(f"--resume: no checkpoint in {out_dir / 'checkpoints'}")
    if state is not None:
        config = TrainConfig(**state["config"])
    config.save(out_dir / "config.json")
    runner = Runner(out_dir, config, quiet, resumed=state)
    for warning in input_warnings(scene):  # an input used only in part is said, never silent
        runner.log.say(f"warning: {warning}")
    if state is not None:
        runner.log.say(f"resuming from {state['stage']} iteration {state['iteration']}")
    torch.manual_seed(config.seed)
    # The CLI's torch thread policy (one thread unless GEAR_TORCH_THREADS says otherwise,
    # docs/training.md), restored afterwards for library callers.
    threads = torch.get_num_threads()
    limit_torch_threads()
    try:
        views = {s: [TrainView.from_view(v) for v in scene.train(s)] for s in STATES}
        models = reconstruct_states({s: scene.train(s) for s in STATES}, views, config,
                                    runner, state).models
        if state is not None and state.get("coarse") is not None:
            coarse = Stage2Result.from_checkpoint(state["coarse"])
            runner.finished("coarse", state["coarse"])
        else:
            coarse = initialise_parts(models, views, config, runner)
        refined = refine_parts(models, coarse, views, config, runner, state)

        t0 = time.perf_counter()
        if refined is None:  # static object: the canonical stage-1 model, one part
            g, motion, joints = models[coarse.canonical], None, []
        else:
            g, motion, joints = refined.gaussians, refined.motion, refined.joints_now()
        outputs.write_joints(out_dir / "joints.json", coarse.canonical, joints)
        outputs.write_ply(out_dir / "gaussians_canonical.ply", g)
        np.save(out_dir / "parts.npy", g.part_ids().numpy().astype(np.int64))
        outputs.write_view_images(out_dir, g, motion, coarse.canonical, scene.views)
        outputs.write_meshes(out_dir, g, motion, coarse.canonical,
                             {s: scene.train(s) for s in STATES}, config.mesh_voxel,
                             config.mesh_trunc)
        runner.timings["outputs"] = time.perf_counter() - t0
        runner.log.write({"event": "timings", **runner.timings})
        return TrainResult(joints, coarse.canonical, dict(runner.timings), list(coarse.notes))
    finally:
        torch.set_num_threads(threads)
        runner.log.close()
