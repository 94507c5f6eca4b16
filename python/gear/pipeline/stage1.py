"""Stage 1: an ordinary Gaussian model of each state on its own (docs/method.md, "Stage 1").

Entry point `reconstruct_states` -> `Stage1Result` (one model per state)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from gear import checkpoint
from gear.config import TrainConfig
from gear.data.scene import STATES
from gear.losses import opacity_binarisation
from gear.pipeline.common import Stage, TrainView, check_finite, gaussian_lrs, image_terms, means_lr
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


def reconstruct_states(views: dict[str, list], train_views: dict[str, list[TrainView]],
                       config: TrainConfig, runner: Runner, resume: dict | None) -> Stage1Result:
    """Trains each state's model in turn from its initial Gaussians (`views`: the scene's
    training views per state, for the initialisation), or continues from `resume`."""
    c = config
    done = {} if resume is None else resume["models"]
    models: dict[str, Gaussians] = {}
    for index, state in enumerate(STATES):
        name = f"stage1-{state}"
        if state in done:
            models[state] = checkpoint.gaussians_from_state(done[state])
            continue
        runner.finished("models", Stage1Result(models).to_checkpoint())  # saved beside it
        start = 0
        if resume is not None and resume["stage"] == name:
            g = checkpoint.gaussians_from_state(resume["current"])
            start = resume["iteration"]
        else:
            g = initial_gaussians(views[state], c, c.seed + index)
            add_sh(g, c.sh_degree, c.lr_sh)
            runner.log.say(f"{name}: {len(g)} initial Gaussians")
        stage = ReconstructState(g, train_views[state], c, c.seed * 1000 + index, state)
        if start:
            stage.load_state_dict(resume["stage_state"])
        runner.run(stage, start, c.stage1_iterations)
        models[state] = g
        runner.finished("models", Stage1Result(models).to_checkpoint())
        runner.save(f"{name}-done", c.stage1_iterations)
    result = Stage1Result(models)
    runner.finished("models", result.to_checkpoint())
    return result
