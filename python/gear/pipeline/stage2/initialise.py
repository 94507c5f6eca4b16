"""Stage 2's entry point: from the two stage-1 models to parts, motions and part logits
(docs/method.md, "Stage 2"). `initialise_parts` -> `Stage2Result`."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from gear.articulation import RigidMotion
from gear.config import TrainConfig
from gear.data.scene import STATES, other_state
from gear.geometry import NearestTree
from gear.pipeline.common import TrainView
from gear.pipeline.runner import Runner
from gear.pipeline.stage2.parts import coarse_init
from gear.pipeline.stage2.stacked import split_stacked
from gear.pipeline.stage2.surface import SurfaceTest
from gear.splats import Gaussians

# Stage 2 sees only the centres of Gaussians at least this opaque, unless fewer than
# STAGE2_MIN_OPAQUE_FRACTION of some state's Gaussians pass (docs/method.md, "Stage 2").
STAGE2_MIN_OPACITY = 0.5
STAGE2_MIN_OPAQUE_FRACTION = 0.5


@dataclass
class Stage2Result:
    """Canonical state, part count K, part logits of every canonical Gaussian [N, K] and, per
    movable part, its motion candidates (the initial motion first, then near-ties of the other
    joint kind, for stage 3's joint-type decision); the voxel size used, the pairs of parts
    that are halves of one part tall along its hinge (stacked.split_stacked) and notes."""

    canonical: str
    num_parts: int
    logits: torch.Tensor
    candidates: list[list[RigidMotion]]
    voxel_size: float
    notes: list[str] = field(default_factory=list)
    halves: list[tuple[int, int]] = field(default_factory=list)
    # Per movable part: the deepest shift stage 3 holds its slide to, or None (CoarseInit).
    held_slides: list[np.ndarray | None] = field(default_factory=list)

    @property
    def target(self) -> str:
        return other_state(self.canonical)

    @property
    def motions(self) -> list[RigidMotion]:
        """The initial motion of each movable part."""
        return [part[0] for part in self.candidates]

    def to_checkpoint(self) -> dict:
        return dict(vars(self))

    @classmethod
    def from_checkpoint(cls, state: dict) -> Stage2Result:
        return cls(**state)


def stage2_selection(models: dict[str, Gaussians]) -> dict[str, tuple[np.ndarray, int]]:
    """Per state, (the Gaussians stage 2 should see, how many are above STAGE2_MIN_OPACITY):
    those above it when at least STAGE2_MIN_OPAQUE_FRACTION of every state's Gaussians pass,
    else all of them, in every state. Stage 2 reads motion off the difference of the two
    states' occupancy, so one rule selects both: a real fridge's open state, just past the
    fraction (50.4 % opaque), lost its haze while its closed state (43 %) kept it, and the
    180-degree door was read as a slide with the other door lost; the same models selected
    alike gave both doors as hinges."""
    opaque = {s: torch.sigmoid(m["opacity"].detach()).numpy() > STAGE2_MIN_OPACITY
              for s, m in models.items()}
    binarised = all(o.mean() >= STAGE2_MIN_OPAQUE_FRACTION for o in opaque.values())
    return {s: (o if binarised else np.ones_like(o), int(o.sum())) for s, o in opaque.items()}


def spread_logits(points: np.ndarray, keep: np.ndarray, logits: np.ndarray) -> np.ndarray:
    """Part logits for every point [N, K] from those of the kept points `logits` [keep.sum(),
    K]: a dropped point takes the logits of its nearest kept point."""
    out = np.empty((len(points), logits.shape[1]), dtype=logits.dtype)
    out[keep] = logits
    if (~keep).any():
        _, nearest = NearestTree(points[keep]).query(points[~keep], k=1)
        out[~keep] = logits[nearest]
    return out


def initialise_parts(models: dict[str, Gaussians], views: dict[str, list[TrainView]],
                     config: TrainConfig, runner: Runner) -> Stage2Result:
    """Parts, motions and logits from the opaque centres of both states' models, each part
    confirmed by the target state's images (`views`)."""
    c = config
    t0 = time.perf_counter()
    centres = {s: models[s]["means"].detach().numpy() for s in STATES}
    selection = stage2_selection(models)
    keep = {s: selection[s][0] for s in STATES}
    init = coarse_init(
        centres["start"][keep["start"]],
        centres["end"][keep["end"]],
        c.num_parts,
        c.voxel_size,
        surfaces={s: SurfaceTest(models[s], views[s]) for s in STATES},
        dilation_radius=c.dilation_radius,
    )
    canonical = init.canonical
    logits = spread_logits(centres[canonical], keep[canonical],
                           np.asarray(init.logits, dtype=np.float32))
    candidates, notes, halves = init.candidates, list(init.notes), []
    if c.split_stacked_hinges and c.num_parts is None and c.merge_redundant_parts:
        logits, candidates, halves, cuts = split_stacked(
            logits, candidates, centres[canonical], init.voxel_size,
            centres[other_state(canonical)])
        notes += cuts
    result = Stage2Result(
        canonical=canonical,
        num_parts=int(logits.shape[1]),
        logits=torch.as_tensor(logits),
        candidates=[[(np.asarray(r), np.asarray(t)) for r, t in part]
                    for part in candidates],
        voxel_size=init.voxel_size,
        notes=notes,
        halves=halves,
        # split_stacked appends the halves' parts: hinges, held to nothing.
        held_slides=init.held_slides + [None] * (int(logits.shape[1]) - 1 - len(init.held_slides)),
    )
    runner.timings["stage2"] = time.perf_counter() - t0
    for state in STATES:
        opaque = selection[state][1]
        used = int(keep[state].sum())
        reason = "opaque" if used == opaque else (
            "all: a state is under half opaque, not yet binarised")
        runner.log.say(f"stage2: {used} of {len(keep[state])} {state} centres ({reason}; "
                       f"{opaque} above opacity {STAGE2_MIN_OPACITY})")
    for note in notes:
        runner.log.say(f"stage2: {note}")
    runner.log.say(f"stage2: canonical state '{canonical}', {result.num_parts} part(s)")
    runner.log.write({"event": "stage_done", "stage": "stage2",
                      "seconds": runner.timings["stage2"]})
    runner.finished("coarse", result.to_checkpoint())
    return result
