"""`train(scene_dir, out_dir, config)`: the method's outline (docs/architecture.md).

1. Stage 1 reconstructs each state on its own (gear.pipeline.stage1).
2. Stage 2 finds the parts, their motions and part logits from the two models
   (gear.pipeline.stage2).
3. Stage 3 refines parts and motions by EM and decides the joint types
   (gear.pipeline.stage3).
4. The outputs are written (gear.outputs).

Checkpoints let an interrupted run continue to the same result (gear.pipeline.runner)."""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from gear import checkpoint, outputs
from gear.config import TrainConfig
from gear.data import load_scene
from gear.data.coverage import input_warnings, inputs_used
from gear.data.scene import STATES, Scene
from gear.device import limit_torch_threads
from gear.pipeline.common import TrainView
from gear.pipeline.runner import Runner, stops_interrupt
from gear.pipeline.stage1 import reconstruct_states
from gear.pipeline.stage2 import Stage2Result, initialise_parts
from gear.pipeline.stage3 import Stage3Result, refine_parts
from gear.run_folder import COMPLETE, RunFolder


@dataclass
class TrainResult:
    joints: list[dict]
    canonical: str
    timings: dict[str, float] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)


def train(scene_dir: Path, out_dir: Path, config: TrainConfig, *, resume: bool = False,
          overwrite: bool = False, quiet: bool = False) -> TrainResult:
    """Runs the whole method on a scene folder and writes the outputs to `out_dir`, which it
    holds for the run (gear.run_folder: lock, --resume / --overwrite, completion marker)."""
    scene = load_scene(scene_dir)
    with RunFolder.open(Path(out_dir), resume=resume, overwrite=overwrite) as folder, \
            stops_interrupt():
        return _train(scene, Path(scene_dir), folder, config, resume, quiet)


def finished_run(scene_dir: Path, out_dir: Path, config: TrainConfig) -> TrainResult | None:
    """The result of the finished run in `out_dir` when it was trained on this scene with
    this configuration (its last checkpoint's scene fingerprint and options match, as for
    --resume), else None: a benchmark scores such a run instead of training it again."""
    out_dir = Path(out_dir)
    if not (out_dir / COMPLETE).is_file() or not (out_dir / "joints.json").is_file():
        return None
    try:
        state = checkpoint.load(out_dir / "checkpoints")
        if state is None:
            return None
        checkpoint.check_resumable(state, checkpoint.scene_fingerprint(scene_dir,
                                                                       load_scene(scene_dir)),
                                   json.loads(config.to_json()))
        found = json.loads((out_dir / "joints.json").read_text())
        summary = json.loads((out_dir / COMPLETE).read_text())
    except ValueError:  # unreadable, or another scene or configuration: trained again
        return None
    return TrainResult(found["joints"], found["canonical"], summary.get("timings", {}))


def _train(scene: Scene, scene_dir: Path, folder: RunFolder, config: TrainConfig, resume: bool,
           quiet: bool) -> TrainResult:
    out_dir = folder.path
    fingerprint = checkpoint.scene_fingerprint(scene_dir, scene)
    state = checkpoint.load(out_dir / "checkpoints") if resume else None
    if resume and state is None:
        raise ValueError(f"--resume: no checkpoint in {out_dir / 'checkpoints'}")
    if state is not None:
        checkpoint.check_resumable(state, fingerprint, json.loads(config.to_json()))
        config = TrainConfig(**state["config"])
    config.save(out_dir / "config.json")
    runner = Runner(out_dir, config, quiet, resumed=state, scene=fingerprint)
    for note in folder.notes:
        runner.log.say(note)
    runner.log.say(inputs_used(scene))
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
        notes = list(coarse.notes)
        if refined is None:  # static object: the canonical stage-1 model, one part
            g, motion, joints = models[coarse.canonical], None, []
        else:
            g, motion, dropped = outputs.drop_empty_parts(refined.gaussians, refined.motion)
            joints = Stage3Result(g, motion, refined.canonical).joints()
            if dropped:
                notes.append(f"dropped {len(dropped)} part(s) left without Gaussians "
                             f"({', '.join(map(str, dropped))}): {len(joints)} movable part(s) "
                             "remain")
                runner.log.say(notes[-1])
        # Written to a staging folder and moved into place, the completion marker last: the
        # folder never shows half the outputs as if they were a finished run's.
        staged = folder.staging()
        outputs.write_joints(staged / "joints.json", coarse.canonical, joints)
        outputs.write_ply(staged / "gaussians_canonical.ply", g)
        np.save(staged / "parts.npy", g.part_ids().numpy().astype(np.int64))
        outputs.write_view_images(staged, g, motion, coarse.canonical, scene.views)
        outputs.write_meshes(staged, g, motion, coarse.canonical,
                             {s: scene.train(s) for s in STATES}, config.mesh_voxel,
                             config.mesh_trunc)
        runner.timings["outputs"] = time.perf_counter() - t0
        runner.log.write({"event": "timings", **runner.timings})
        folder.publish({"finished": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
                        "joints": len(joints), "timings": runner.timings})
        return TrainResult(joints, coarse.canonical, dict(runner.timings), notes)
    finally:
        torch.set_num_threads(threads)
        runner.log.close()
