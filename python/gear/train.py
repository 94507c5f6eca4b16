"""`train(scene_dir, out_dir, config)`: stage 1 per state, stage 2 coarse init, stage 3 EM,
then the outputs. Checkpoints let an interrupted run continue to the same result."""

from __future__ import annotations

import json
import signal
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree
from tqdm import tqdm

from gear import checkpoint
from gear.coarse import SurfaceTest
from gear.config import TrainConfig
from gear.data import Scene, load_scene
from gear.data.coverage import input_warnings
from gear.device import limit_torch_threads
from gear.model import Gaussians, points_from_depth, points_from_masks, render, scene_extent
from gear.stages import ReconstructState, Refine, TrainView

STATES = ("start", "end")


@dataclass
class TrainResult:
    joints: list[dict]
    canonical: str
    timings: dict[str, float] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)


class RunLog:
    """log.jsonl (one JSON object per line) plus the console, unless quiet."""

    def __init__(self, path: Path, quiet: bool, append: bool) -> None:
        self.path, self.quiet = path, quiet
        self._fh = open(path, "a" if append else "w")  # a resumed run continues its log

    def write(self, record: dict) -> None:
        self._fh.write(json.dumps(record, default=_jsonable) + "\n")
        self._fh.flush()

    def say(self, message: str) -> None:
        self.write({"message": message})
        if not self.quiet:
            tqdm.write(message)

    def close(self) -> None:
        self._fh.close()


def _jsonable(value: object) -> object:
    if isinstance(value, np.ndarray | torch.Tensor):
        return np.asarray(value).tolist()
    if isinstance(value, np.generic):
        return value.item()
    return str(value)


class _Interrupt:
    """Turns Ctrl-C into a flag checked between iterations, so the checkpoint written on
    interruption is a consistent iteration boundary."""

    def __init__(self) -> None:
        self.requested = False

    def __enter__(self) -> _Interrupt:
        self._previous = signal.signal(signal.SIGINT, self._handler)
        return self

    def _handler(self, _sig: int, _frame: object) -> None:
        self.requested = True

    def __exit__(self, *exc: object) -> None:
        signal.signal(signal.SIGINT, self._previous)


def initial_gaussians(views: list, config: TrainConfig, seed: int) -> Gaussians:
    """From depth back-projection when every view has depth, else a visual hull of the masks."""
    rng = np.random.default_rng(seed)
    extent = scene_extent([v.camera for v in views])
    if all(v.depth is not None for v in views):
        pts, cols = points_from_depth(
            views, config.init_voxel_fraction * extent, config.init_max_points, rng
        )
    else:
        pts, cols = points_from_masks(views, config.random_init_points, rng)
        if len(pts) > config.init_max_points:
            pick = rng.choice(len(pts), config.init_max_points, replace=False)
            pts, cols = pts[pick], cols[pick]
    return Gaussians.from_points(pts, cols)


# Stage 2 sees only the centres of Gaussians at least this opaque (sigmoid of the opacity
# logit): a low-opacity floater is a centre with almost no image behind it, and the voxel
# differences of stage 2 turn such centres into dynamic components, i.e. noise parts. The
# stage-1 loss binarises opacity (BCE towards 0 or 1), so on a converged model 0.5 splits
# surface from haze.
STAGE2_MIN_OPACITY = 0.5
# ... unless fewer than this fraction of a state's Gaussians pass: a short run (the quick
# profile's 300 iterations) has not binarised yet (there a median opacity of ~0.2 is surface),
# and the threshold would leave stage 2 a sparse, biased sample of it.
STAGE2_MIN_OPAQUE_FRACTION = 0.5


def stage2_selection(model: Gaussians) -> tuple[np.ndarray, int]:
    """(the Gaussians stage 2 should see, how many are above STAGE2_MIN_OPACITY): those above
    it, or all of them when fewer than STAGE2_MIN_OPAQUE_FRACTION pass; the count says which."""
    opaque = torch.sigmoid(model["opacity"].detach()).numpy() > STAGE2_MIN_OPACITY
    keep = opaque if opaque.mean() >= STAGE2_MIN_OPAQUE_FRACTION else np.ones_like(opaque)
    return keep, int(opaque.sum())


def spread_logits(points: np.ndarray, keep: np.ndarray, logits: np.ndarray) -> np.ndarray:
    """Part logits for every point [N, K] from those of the kept points `logits` [keep.sum(),
    K]: a dropped point takes the logits of its nearest kept point."""
    out = np.empty((len(points), logits.shape[1]), dtype=logits.dtype)
    out[keep] = logits
    if (~keep).any():
        _, nearest = cKDTree(points[keep]).query(points[~keep], k=1)
        out[~keep] = logits[nearest]
    return out


def surface_test(model: Gaussians, views: list[TrainView], max_views: int = 8) -> SurfaceTest:
    """`look(points [M,3], tolerance) -> (on_surface [M], free [M])` over up to `max_views` of
    `views` rendered from `model`: whether each point lies, within `tolerance` in depth, on the
    surface shown (alpha > 0.5) in some view, and whether some view sees through it (outside
    the silhouette, or in front of the surface by more than `tolerance`). Stage 2 uses it on
    the target state's stage-1 model to check that the target images see a part move."""
    seen = []
    with torch.no_grad():
        for view in views[:: max(1, len(views) // max_views)]:
            out = render(model["means"], model["quats"], model["log_scales"], model["opacity"],
                         model.rgb(), view.camera, torch.zeros(3), depth=True)
            alpha = out.alpha.numpy()
            depth = out.depth.numpy() / np.maximum(alpha, 1e-6)  # expected depth of the surface
            seen.append((view.camera, alpha > 0.5, depth))

    def look(points: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
        hit = np.zeros(len(points), dtype=bool)
        free = np.zeros(len(points), dtype=bool)
        for camera, solid, depth in seen:
            uv, z = camera.project(points)
            ok = np.isfinite(uv).all(axis=1) & (z > 0)
            u = np.floor(np.where(ok, uv[:, 0], -1)).astype(np.int64)
            v = np.floor(np.where(ok, uv[:, 1], -1)).astype(np.int64)
            ok &= (u >= 0) & (v >= 0) & (u < camera.width) & (v < camera.height)
            idx = np.flatnonzero(ok)
            uu, vv = u[idx], v[idx]
            gap = z[idx] - depth[vv, uu]
            hit[idx[solid[vv, uu] & (np.abs(gap) < tolerance)]] = True
            free[idx[~solid[vv, uu] | (gap < -tolerance)]] = True
        return hit, free

    return look


class Trainer:
    def __init__(self, scene: Scene, out_dir: Path, config: TrainConfig, quiet: bool,
                 resume: bool = False) -> None:
        self.scene, self.out_dir, self.config, self.quiet = scene, out_dir, config, quiet
        self.ckpt_dir = out_dir / "checkpoints"
        self.log = RunLog(out_dir / "log.jsonl", quiet, append=resume)
        self.timings: dict[str, float] = {}
        self.models: dict[str, Gaussians] = {}
        self.coarse: dict | None = None
        self.views = {s: [TrainView.from_view(v) for v in scene.train(s)] for s in STATES}

    # --- checkpoints ---
    def _payload(self, stage_name: str, iteration: int, stage_obj: object) -> dict:
        payload = {
            "stage": stage_name,
            "iteration": iteration,
            "config": json.loads(self.config.to_json()),
            "models": {s: checkpoint.gaussians_state(g) for s, g in self.models.items()},
            "coarse": self.coarse,
            "timings": dict(self.timings),
        }
        if stage_obj is not None:
            payload["current"] = checkpoint.gaussians_state(stage_obj.gaussians)
            payload["stage_state"] = stage_obj.state_dict()
            if isinstance(stage_obj, Refine):
                payload["frozen"] = checkpoint.gaussians_state(stage_obj.frozen)
        return payload

    def _save(self, stage_name: str, iteration: int, stage_obj: object) -> None:
        path = checkpoint.save(self.ckpt_dir, self._payload(stage_name, iteration, stage_obj))
        self.log.write({"event": "checkpoint", "stage": stage_name, "iteration": iteration,
                        "path": str(path)})

    # --- the loop every stage shares ---
    def _run(self, stage, start: int, total: int, status: Callable[[], str] | None = None) -> None:  # noqa: ANN001
        c = self.config
        bar = tqdm(total=total, initial=start, desc=stage.name, disable=self.quiet,
                   dynamic_ncols=True, leave=True)
        t0 = time.perf_counter()
        previous_phase = None
        with _Interrupt() as interrupt:
            for it in range(start, total):
                phase = stage.phase(it) if isinstance(stage, Refine) else None
                if phase != previous_phase and status is not None:
                    self.log.write({"event": "phase", "stage": stage.name, "iteration": it,
                                    "phase": phase, "joints": self._joints_now(stage)})
                previous_phase = phase
                terms = stage.step(it)
                for event in stage.events:
                    self.log.write({"stage": stage.name, **event})
                stage.events.clear()
                if it % c.log_every == 0 or it + 1 == total:
                    record = {"stage": stage.name, "iteration": it,
                              "gaussians": len(stage.gaussians),
                              **({"phase": phase} if phase else {}), **terms}
                    self.log.write(record)
                    postfix = " ".join(f"{k}={v:.4f}" for k, v in terms.items())
                    if status is not None:
                        postfix += " " + status()
                    bar.set_postfix_str(f"n={len(stage.gaussians)} {postfix}", refresh=False)
                bar.update(1)
                done = it + 1
                if interrupt.requested:
                    self.timings[stage.name] = (self.timings.get(stage.name, 0.0)
                                                + time.perf_counter() - t0)
                    self._save(stage.name, done, stage)
                    bar.close()
                    message = (f"interrupted: checkpoint saved at {stage.name} iteration {done}; "
                               "continue with --resume")
                    self.log.write({"message": message})
                    print(message, file=sys.stderr)
                    raise KeyboardInterrupt
                if done % c.checkpoint_every == 0 and done < total:
                    self._save(stage.name, done, stage)
        bar.close()
        elapsed = time.perf_counter() - t0
        self.timings[stage.name] = self.timings.get(stage.name, 0.0) + elapsed
        self.log.write({"event": "stage_done", "stage": stage.name, "seconds": elapsed})

    def _joints_now(self, stage: Refine) -> list[dict]:
        from gear.outputs import object_center, start_to_end_joints

        return start_to_end_joints(stage.motion, self.coarse["canonical"],
                                   object_center(stage.gaussians))

    # --- stages ---
    def stage1(self, resume: dict | None) -> None:
        c = self.config
        for index, state in enumerate(STATES):
            name = f"stage1-{state}"
            if resume is not None and state in resume["models"]:
                self.models[state] = checkpoint.gaussians_from_state(resume["models"][state])
                continue
            start = 0
            if resume is not None and resume["stage"] == name:
                g = checkpoint.gaussians_from_state(resume["current"])
                start = resume["iteration"]
            else:
                g = initial_gaussians(self.scene.train(state), c, c.seed + index)
                self.log.say(f"{name}: {len(g)} initial Gaussians")
            stage = ReconstructState(g, self.views[state], c, c.seed * 1000 + index, state)
            if start:
                stage.load_state_dict(resume["stage_state"])
            self._run(stage, start, c.stage1_iterations)
            self.models[state] = g
            self._save(f"{name}-done", c.stage1_iterations, None)

    def stage2(self) -> None:
        from gear.coarse import coarse_init

        c = self.config
        t0 = time.perf_counter()
        centres = {s: self.models[s]["means"].detach().numpy() for s in STATES}
        selection = {s: stage2_selection(self.models[s]) for s in STATES}
        keep = {s: selection[s][0] for s in STATES}
        init = coarse_init(
            centres["start"][keep["start"]],
            centres["end"][keep["end"]],
            c.num_parts,
            c.voxel_size,
            on_target_surface=lambda state: surface_test(self.models[state], self.views[state]),
        )
        canonical = init.canonical
        logits = spread_logits(centres[canonical], keep[canonical],
                               np.asarray(init.logits, dtype=np.float32))
        self.timings["stage2"] = time.perf_counter() - t0
        self.coarse = {
            "canonical": init.canonical,
            "num_parts": int(init.num_parts),
            "logits": torch.as_tensor(logits),
            "motions": [(np.asarray(r), np.asarray(t)) for r, t in init.motions],
            # per movable part: its motion first, then near-ties of the other joint kind
            "candidates": [[(np.asarray(r), np.asarray(t)) for r, t in part]
                           for part in init.candidates] or None,
            "voxel_size": init.voxel_size,
            "notes": list(init.notes),
        }
        for state in STATES:
            opaque = selection[state][1]
            used = int(keep[state].sum())
            reason = "opaque" if used == opaque else "all: under half opaque, not yet binarised"
            self.log.say(f"stage2: {used} of {len(keep[state])} {state} centres ({reason}; "
                         f"{opaque} above opacity {STAGE2_MIN_OPACITY})")
        for note in init.notes:
            self.log.say(f"stage2: {note}")
        self.log.say(f"stage2: canonical state '{init.canonical}', {init.num_parts} part(s)")
        self.log.write({"event": "stage_done", "stage": "stage2",
                        "seconds": self.timings["stage2"]})

    def stage3(self, resume: dict | None) -> Refine | None:
        from gear.kinematics import PartMotion

        c, coarse = self.config, self.coarse
        canonical = coarse["canonical"]
        target = "end" if canonical == "start" else "start"
        if coarse["num_parts"] == 1:
            self.log.say("no motion detected between the two states: one static part")
            return None
        if resume is not None and resume["stage"] in ("stage3", "stage3-done"):
            g = checkpoint.gaussians_from_state(resume["current"])
            frozen = checkpoint.gaussians_from_state(resume["frozen"])
            start = resume["iteration"]
        else:
            base = self.models[canonical]
            g = base.clone()
            g.add_param("logits", coarse["logits"], c.lr_logits)
            frozen = base.clone()
            start = 0
        motion = PartMotion.from_rt(coarse["motions"])
        stage = Refine(g, motion, frozen, self.views[canonical], self.views[target], c,
                       c.seed * 1000 + 7,
                       init_motions=coarse.get("candidates") or coarse["motions"])
        if start:
            stage.load_state_dict(resume["stage_state"])

        def status() -> str:
            joints = self._joints_now(stage)
            return " ".join(
                f"j{j['part']}={j['angle_deg']:.1f}°" if j["type"] == "revolute"
                else f"j{j['part']}={j['distance']:.3f}" for j in joints
            )

        self._run(stage, start, c.stage3_iterations, status)
        self._save("stage3-done", c.stage3_iterations, stage)
        return stage


def train(scene_dir: Path, out_dir: Path, config: TrainConfig, *, resume: bool = False,
          quiet: bool = False) -> TrainResult:
    """Runs the whole method on a scene folder and writes the outputs to `out_dir`."""
    from gear import outputs

    scene = load_scene(scene_dir)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    state = checkpoint.load(out_dir / "checkpoints") if resume else None
    if resume and state is None:
        raise ValueError(f"--resume: no checkpoint in {out_dir / 'checkpoints'}")
    if state is not None:
        config = TrainConfig(**state["config"])
    config.save(out_dir / "config.json")
    trainer = Trainer(scene, out_dir, config, quiet, resume=state is not None)
    for warning in input_warnings(scene):  # an input used only in part is said, never silent
        trainer.log.say(f"warning: {warning}")
    if state is not None:
        trainer.timings.update(state["timings"])
        trainer.log.say(f"resuming from {state['stage']} iteration {state['iteration']}")
    torch.manual_seed(config.seed)
    # The torch thread policy of the CLI (gear.device.limit_torch_threads: one thread unless
    # GEAR_TORCH_THREADS says otherwise), restored afterwards for library callers. Measured on
    # the 64 px quick fridge: 33.8 vs 8.9 it/s with one thread vs torch's default two.
    threads = torch.get_num_threads()
    limit_torch_threads()
    try:
        trainer.stage1(state)
        if state is not None and state.get("coarse") is not None:
            trainer.coarse = state["coarse"]
        else:
            trainer.stage2()
        refine = trainer.stage3(state)
        t0 = time.perf_counter()
        canonical = trainer.coarse["canonical"]
        if refine is None:  # static object: the canonical stage-1 model, one part
            g, motion = trainer.models[canonical], None
            joints: list[dict] = []
        else:
            g, motion = refine.gaussians, refine.motion
            joints = outputs.start_to_end_joints(motion, canonical, outputs.object_center(g))
        outputs.write_joints(out_dir / "joints.json", canonical, joints)
        outputs.write_ply(out_dir / "gaussians_canonical.ply", g)
        np.save(out_dir / "parts.npy", g.part_ids().numpy().astype(np.int64))
        outputs.write_view_images(out_dir, g, motion, canonical, scene.views)
        outputs.write_meshes(out_dir, g, motion, canonical,
                             {s: scene.train(s) for s in STATES}, config.mesh_voxel,
                             config.mesh_trunc)
        trainer.timings["outputs"] = time.perf_counter() - t0
        trainer.log.write({"event": "timings", **trainer.timings})
        return TrainResult(joints, canonical, dict(trainer.timings),
                           list(trainer.coarse.get("notes", [])))
    finally:
        torch.set_num_threads(threads)
        trainer.log.close()
