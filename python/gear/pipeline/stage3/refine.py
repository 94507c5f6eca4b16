"""Stage 3's entry point: the canonical model with part logits and per-part motions, refined
by alternating E- and M-steps, with the joint types decided once on the way
(docs/method.md, "Stage 3"). `refine_parts` -> a `Stage3Result` (the refined Gaussians and
part motions; None for a static object)."""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

from gear import checkpoint
from gear.articulation import PartMotion
from gear.config import TrainConfig
from gear.pipeline.common import TrainView
from gear.pipeline.runner import Runner
from gear.pipeline.stage2 import Stage2Result
from gear.pipeline.stage3.estep import gaussian_step
from gear.pipeline.stage3.hinge_lines import recall_hinge_lines
from gear.pipeline.stage3.joint_types import classify
from gear.pipeline.stage3.joints import object_center, start_to_end_joints
from gear.pipeline.stage3.landing import land_hinges
from gear.pipeline.stage3.merge import merge_parts
from gear.pipeline.stage3.mstep import motion_step
from gear.pipeline.stage3.rods import untwist_rods
from gear.pipeline.stage3.shared import RefineState
from gear.pipeline.stage3.square_axes import square_axes
from gear.splats import Gaussians


@dataclass
class Stage3Result:
    """The refined canonical Gaussians (with their part logits), the part motions (canonical
    -> target, joint types decided) and the canonical state."""

    gaussians: Gaussians
    motion: PartMotion
    canonical: str

    def joints(self) -> list[dict]:
        """joints.json entries of the motions (start -> end)."""
        return start_to_end_joints(self.motion, self.canonical, object_center(self.gaussians))

    def to_checkpoint(self) -> dict:
        return {"gaussians": checkpoint.gaussians_state(self.gaussians),
                "num_parts": self.motion.num_parts, "motion": self.motion.state_dict(),
                "canonical": self.canonical}

    @classmethod
    def from_checkpoint(cls, state: dict) -> Stage3Result:
        motion = PartMotion(state["num_parts"])
        motion.load_state_dict(state["motion"])
        return cls(checkpoint.gaussians_from_state(state["gaussians"]), motion,
                   state["canonical"])


class Refine(RefineState):
    """The per-iteration work of stage 3 on its state: which step the schedule asks for
    (E-step, M-step or joint optimisation), the joint-type decision at its iteration,
    densification outside the M-phases; and what the run loop logs and checkpoints."""

    def step(self, it: int) -> dict[str, float]:
        phase = self.phase(it)
        if it == self.config.joint_classify_iteration:
            # Stacked doors' halves start at the median along the hinge, not at the doors'
            # seam, and keep drawing apart after this: the cupboard's doors of 22.6 / 18.3
            # degrees, halves joined here at a cost of 7 % of the gain, ended at 21.1 / 18.7
            # kept apart (12 %). They may join only at the end.
            self.merge_parts_read_twice(apart=self.halves)
            classify(self)
        terms = motion_step(self, it) if phase == "M" else gaussian_step(self, it, phase)
        self.maintain(it)
        return terms

    def merge_parts_read_twice(self, apart: Sequence[tuple[int, int]] = (),
                               halves: Sequence[tuple[int, int]] = ()) -> None:
        """merge.merge_parts (no pair of `apart` joined, the pairs of `halves` held to their
        tighter share), when the config asks for it, recorded as an event."""
        if self.config.merge_redundant_parts:
            merged = merge_parts(self, apart, halves)
            self.events.append({"event": "part_merge", "merges": [m.record() for m in merged]})

    def untwist_rods(self) -> None:
        """rods.untwist_rods, when the config asks for it, recorded as an event."""
        if self.config.untwist_rods:
            self.events.append({"event": "rod_untwist", "parts": untwist_rods(self)})

    def square_axes(self) -> None:
        """square_axes.square_axes, when the config asks for it, recorded as an event."""
        if self.config.square_axes:
            self.events.append({"event": "axis_square", "parts": square_axes(self)})

    def land_hinges(self, target: Gaussians | None) -> None:
        """landing.land_hinges on the target state's stage-1 model `target`, when the config
        asks for it and there is one, recorded as an event."""
        if self.config.land_hinges and target is not None:
            self.events.append({"event": "hinge_landing", "parts": land_hinges(self, target)})

    def recall_hinge_lines(self) -> None:
        """hinge_lines.recall_hinge_lines, when the config asks for it, recorded as an event."""
        if self.config.recall_hinge_lines:
            self.events.append({"event": "hinge_lines", "parts": recall_hinge_lines(self)})

    def result(self) -> Stage3Result:
        return Stage3Result(self.gaussians, self.motion, self.canonical)

    def status(self) -> str:
        return " ".join(
            f"j{j['part']}={j['angle_deg']:.1f}°" if j["type"] == "revolute"
            else f"j{j['part']}={j['distance']:.3f}" for j in self.result().joints()
        )

    def snapshot(self) -> dict:
        return {"joints": self.result().joints()}

    def state_dict(self) -> dict:
        current = self._neighbours_generation == self.gaussians.generation
        return {
            "generator": self.generator.get_state(),
            "densifier": self.densifier.state_dict(),
            "motion": self.motion.state_dict(),
            "motion_optimizer": self.motion_optimizer.state_dict(),
            # The KNN lists in use (they are kept while the centres move between edits), so a
            # resumed run smooths the logits over the same neighbours.
            "neighbours": self._neighbours if current else None,
            # Held slides left after the merges (a merged part moves as the one it joined).
            "held_slides": self.held_slides,
        }

    def load_state_dict(self, state: dict) -> None:
        self.generator.set_state(state["generator"])
        self.densifier.load_state_dict(state["densifier"])
        self.motion.load_state_dict(state["motion"])
        self.motion_optimizer.load_state_dict(state["motion_optimizer"])
        # A checkpoint written before held slides were saved holds stage 2's.
        self.held_slides = state.get("held_slides", self.held_slides)
        if state["neighbours"] is not None:
            self._neighbours = state["neighbours"]
            self._neighbours_generation = self.gaussians.generation

    def checkpoint(self) -> dict:
        return {"current": checkpoint.gaussians_state(self.gaussians),
                "frozen": None if self.frozen is None else checkpoint.gaussians_state(self.frozen),
                "stage_state": self.state_dict()}


def refine_state(g: Gaussians, stage1: Gaussians | None, coarse: Stage2Result,
                 views: dict[str, Sequence[TrainView]], config: TrainConfig) -> Refine:
    """Stage 3's state on the canonical Gaussians `g` (with part logits), the motions starting
    from stage 2's. A frozen copy of the canonical stage-1 model `stage1` is kept only for
    anchor = "frozen": the default anchor (the canonical images) never renders it."""
    frozen = stage1.clone() if config.anchor == "frozen" and stage1 is not None else None
    return _refine(g, frozen, coarse, views, config)


def resumed_refine_state(saved: dict, coarse: Stage2Result,
                         views: dict[str, Sequence[TrainView]], config: TrainConfig) -> Refine:
    """Stage 3's state as a checkpoint taken during stage 3 (`saved`) left it (its frozen
    model, when it kept one, is a fresh copy already)."""
    frozen = saved.get("frozen")
    stage = _refine(checkpoint.gaussians_from_state(saved["current"]),
                    None if frozen is None else checkpoint.gaussians_from_state(frozen),
                    coarse, views, config)
    stage.load_state_dict(saved["stage_state"])
    return stage


def _refine(g: Gaussians, frozen: Gaussians | None, coarse: Stage2Result,
            views: dict[str, Sequence[TrainView]], config: TrainConfig) -> Refine:
    return Refine(g, PartMotion.from_rt(coarse.motions), frozen, views[coarse.canonical],
                  views[coarse.target], config, config.seed * 1000 + 7,
                  init_motions=coarse.candidates, canonical=coarse.canonical,
                  halves=coarse.halves, held_slides=coarse.held_slides)


def refine_parts(models: dict[str, Gaussians], coarse: Stage2Result,
                 views: dict[str, Sequence[TrainView]], config: TrainConfig, runner: Runner,
                 resume: dict | None) -> Stage3Result | None:
    """Stage 3 from stage 2's parts and the canonical stage-1 model (the target state's, when
    `models` holds it, lands the hinges at the end), or continued from `resume`; None when
    stage 2 found a single (static) part."""
    c = config
    if coarse.num_parts == 1:
        runner.log.say("no motion detected between the two states: one static part")
        return None
    if resume is not None and resume["stage"] == "stage3-done":
        return Stage3Result.from_checkpoint(resume["refined"])
    if resume is not None and resume["stage"] == "stage3":
        stage, start = resumed_refine_state(resume, coarse, views, c), resume["iteration"]
    else:
        base = models[coarse.canonical]
        g = base.clone()
        g.add_param("logits", coarse.logits, c.lr_logits)
        stage, start = refine_state(g, base, coarse, views, c), 0
    runner.run(stage, start, c.stage3_iterations)
    # Again at the end: a fragment's motion may reach its part's only after the merge at the
    # joint-type decision (a scissors blade's tip, given a turn of 8 degrees by an older
    # stage 2, ended within 1 degree of the blade's 34 and stayed a part).
    started = time.perf_counter()
    stage.merge_parts_read_twice(halves=stage.halves)
    stage.untwist_rods()
    stage.square_axes()
    stage.land_hinges(models.get(coarse.target))
    stage.recall_hinge_lines()
    runner.write_events(stage, when="end")
    runner.timed(stage.name, time.perf_counter() - started)
    result = stage.result()
    runner.finished("refined", result.to_checkpoint())
    runner.save("stage3-done", c.stage3_iterations)
    return result
