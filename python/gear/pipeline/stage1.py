"""Stage 1: an ordinary Gaussian model of each state on its own (docs/method.md, "Stage 1").

Entry point `reconstruct_states` -> `Stage1Result` (one model per state)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from gear import checkpoint
from gear.config import TrainConfig
from gear.data.scene import STATES
from gear.losses import opacity_binarisation
from gear.pipeline.common import (
    Iterating,
    Stage,
    TrainView,
    check_finite,
    gaussian_lrs,
    image_terms,
    map_beside,
    means_lr,
)
from gear.pipeline.runner import Runner
from gear.splats import Densifier, Gaussians, gaussian_budget, render
from gear.splats.init import initial_gaussians, scene_extent
from gear.splats.sh import add_sh

# Weight of the silhouette loss on a view without depth (docs/method.md, "Stage 1").
MASK_WEIGHT_WITHOUT_DEPTH = 1.0


class ReconstructState(Stage):
    """The per-iteration work of stage 1 on one state."""

    def __init__(
        self, gaussians: Gaussians, views: Sequence[TrainView], config: TrainConfig, seed: int,
        state: str,
    ) -> None:
        super().__init__(config, seed)
        self.name = f"stage1-{state}"
        self.state = state
        self.gaussians = gaussians
        self.views = list(views)
        self.extent = scene_extent([v.camera for v in self.views])
        if gaussians.optimizer is None:
            gaussians.setup_optimizer(gaussian_lrs(config, self.extent))
        self.densifier = Densifier(gaussians, gaussian_budget(config, [v.camera for v in views]))
        self.total = config.stage1_iterations

    def step(self, it: int) -> dict[str, float]:
        c, g = self.config, self.gaussians
        g.set_lr("means", means_lr(c, it, self.total) * self.extent)
        view = self.pick(self.views)
        bg = self.background()
        out = render(g, view.camera, bg, depth=view.depth is not None)
        terms = image_terms(out, view, bg, c)
        if view.depth is None:
            terms["mask"] = MASK_WEIGHT_WITHOUT_DEPTH * (out.alpha - view.alpha).abs().mean()
        terms["opacity"] = c.lambda_opacity * opacity_binarisation(g["opacity"])
        check_finite(terms, self.name, it)
        loss = sum(terms.values())
        g.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.densifier.accumulate(g["means"], view.camera, it + 1, c.densify_until)
        g.optimizer.step()
        self.events += self.densifier.maintain(g, it + 1, c, self.extent, c.densify_until,
                                               True, self.generator)
        return {k: v.item() for k, v in terms.items()}

    def state_dict(self) -> dict:
        return {"generator": self.generator.get_state(), "densifier": self.densifier.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.generator.set_state(state["generator"])
        self.densifier.load_state_dict(state["densifier"])

    def checkpoint(self) -> dict:
        return {"current": checkpoint.gaussians_state(self.gaussians),
                "stage_state": self.state_dict()}


@dataclass
class Stage1Result:
    """One trained Gaussian model per state ("start", "end")."""

    models: dict[str, Gaussians]

    def to_checkpoint(self) -> dict:
        return {s: checkpoint.gaussians_state(g) for s, g in self.models.items()}

    @classmethod
    def from_checkpoint(cls, state: dict) -> Stage1Result:
        return cls({s: checkpoint.gaussians_from_state(g) for s, g in state.items()})


class BothStates(Iterating):
    """Stage 1 of every state not yet trained, in lockstep: each iteration steps every state's
    model, one beside the other (common.map_beside). The states share nothing (own Gaussians,
    optimiser, generator), so the models are bit for bit those of training them one after the
    other (docs/training.md, "Both states at once"). A state resumed at a later iteration than
    the others waits until they reach it."""

    name = "stage1"

    def __init__(self, stages: Sequence[ReconstructState], starts: Sequence[int]) -> None:
        super().__init__()
        self.stages = list(stages)
        self.done = {s.state: start for s, start in zip(self.stages, starts, strict=True)}

    def step(self, it: int) -> dict[str, float]:
        due = [s for s in self.stages if self.done[s.state] <= it]
        results = map_beside(lambda stage: stage.step(it), due)
        terms = {}
        for stage, stage_terms in zip(due, results, strict=True):
            self.done[stage.state] = it + 1
            terms.update({f"{stage.state}/{k}": v for k, v in stage_terms.items()})
            self.events += [{**event, "stage": stage.name} for event in stage.events]
            stage.events.clear()
        return terms

    def gaussian_count(self) -> dict[str, int]:
        return {s.state: len(s.gaussians) for s in self.stages}

    def checkpoint(self) -> dict:
        return {"current": {s.state: checkpoint.gaussians_state(s.gaussians) for s in self.stages},
                "stage_state": {s.state: s.state_dict() for s in self.stages},
                "iterations": dict(self.done)}


def reconstruct_states(views: dict[str, list], train_views: dict[str, list[TrainView]],
                       config: TrainConfig, runner: Runner, resume: dict | None) -> Stage1Result:
    """Trains the model of each state not finished yet (BothStates) from its initial Gaussians
    (`views`: the scene's training views per state, for the initialisation), or continues from
    `resume`."""
    c = config
    done = {} if resume is None else resume["models"]
    models = {s: checkpoint.gaussians_from_state(done[s]) for s in STATES if s in done}
    stages, starts = [], []
    for index, state in enumerate(STATES):
        if state in models:
            continue
        saved = _progress(resume, state)
        if saved is None:
            g, start = initial_gaussians(views[state], c, c.seed + index), 0
            add_sh(g, c.sh_degree, c.lr_sh)
            runner.log.say(f"stage1-{state}: {len(g)} initial Gaussians")
        else:
            g, start = checkpoint.gaussians_from_state(saved[0]), saved[2]
        stage = ReconstructState(g, train_views[state], c, c.seed * 1000 + index, state)
        if start:
            stage.load_state_dict(saved[1])
        stages.append(stage)
        starts.append(start)
    if stages:
        runner.finished("models", Stage1Result(models).to_checkpoint())  # saved beside them
        runner.run(BothStates(stages, starts), min(starts), c.stage1_iterations)
        models.update({s.state: s.gaussians for s in stages})
    result = Stage1Result({s: models[s] for s in STATES})
    runner.finished("models", result.to_checkpoint())
    if stages:
        runner.save("stage1-done", c.stage1_iterations)
    return result


def _progress(resume: dict | None, state: str) -> tuple[dict, dict, int] | None:
    """What `resume` holds of `state`'s stage 1 in progress: (Gaussians, stage state,
    iteration), or None. Reads BothStates' checkpoints and those of a run that trained the
    states one after the other (stage "stage1-<state>")."""
    if resume is None:
        return None
    if resume["stage"] == BothStates.name and state in resume["current"]:
        return (resume["current"][state], resume["stage_state"][state],
                resume["iterations"][state])
    if resume["stage"] == f"stage1-{state}":
        return resume["current"], resume["stage_state"], resume["iteration"]
    return None
