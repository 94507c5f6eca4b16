"""The per-iteration work of stage 1 (per-state reconstruction) and stage 3 (EM refinement).

Each stage is an object with `step(it) -> dict of loss terms` plus `state_dict` /
`load_state_dict`, so the loop driver in train.py can checkpoint, resume and report progress
the same way for both. All randomness (view choice, background, split offsets) comes from the
stage's own torch.Generator, whose state is checkpointed: seeded runs resume identically.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from gear.camera import Camera
from gear.config import TrainConfig
from gear.em import classify_joints, knn_consistency_loss, region_pseudo_labels, sam_ce_loss
from gear.kinematics import deform, quat_angle
from gear.losses import composite, depth_log_l1, opacity_binarisation, photometric
from gear.model import Gaussians, nearest_neighbours, render, scene_extent


class NonFiniteLoss(RuntimeError):
    def __init__(self, stage: str, iteration: int, term: str) -> None:
        super().__init__(
            f"non-finite loss in {stage} at iteration {iteration} (term '{term}'); "
            "the last good checkpoint is kept"
        )
        self.stage, self.iteration, self.term = stage, iteration, term


@dataclass
class TrainView:
    """One training image as torch tensors (converted once)."""

    camera: Camera
    rgb: torch.Tensor  # [H,W,3]
    alpha: torch.Tensor  # [H,W]
    depth: torch.Tensor | None  # [H,W], 0 = missing
    regions: np.ndarray | None  # [H,W] int

    @classmethod
    def from_view(cls, view) -> TrainView:  # noqa: ANN001 (gear.data.View)
        depth = None if view.depth is None else torch.as_tensor(view.depth, dtype=torch.float32)
        return cls(
            view.camera,
            torch.as_tensor(view.rgb, dtype=torch.float32),
            torch.as_tensor(view.alpha, dtype=torch.float32),
            depth,
            view.regions,
        )


def gaussian_lrs(config: TrainConfig, extent: float) -> dict[str, float]:
    return dict(
        means=config.lr_means * extent,
        quats=config.lr_quats,
        log_scales=config.lr_log_scales,
        opacity=config.lr_opacity,
        colors=config.lr_colors,
        logits=config.lr_logits,
    )


def means_lr(config: TrainConfig, it: int, total: int) -> float:
    """Exponential decay from lr_means to lr_means_final over the stage (times the extent)."""
    f = min(max(it / max(total, 1), 0.0), 1.0)
    return float(np.exp((1 - f) * np.log(config.lr_means) + f * np.log(config.lr_means_final)))


def check_finite(terms: dict[str, torch.Tensor], stage: str, it: int) -> None:
    for name, value in terms.items():
        if not bool(torch.isfinite(value).all()):
            raise NonFiniteLoss(stage, it, name)


def _image_terms(out, view: TrainView, background: torch.Tensor, config: TrainConfig):  # noqa: ANN001
    target = composite(view.rgb, view.alpha, background)
    terms = {"rgb": photometric(out.features[..., :3], target, config.lambda_dssim)}
    if view.depth is not None and out.depth is not None:
        terms["depth"] = config.lambda_depth * depth_log_l1(out.depth, view.depth)
    return terms


class _Stage:
    name = "stage"

    def __init__(self, config: TrainConfig, seed: int) -> None:
        self.config = config
        self.generator = torch.Generator().manual_seed(seed)
        self.events: list[dict] = []  # densify / reset / classification events for the log

    def _pick(self, views: Sequence[TrainView]) -> TrainView:
        return views[int(torch.randint(len(views), (1,), generator=self.generator))]

    def _background(self) -> torch.Tensor:
        return torch.rand(3, generator=self.generator)

    def _maintain(self, g: Gaussians, it: int, densify_until: int, allowed: bool) -> None:
        """Densify/prune and opacity reset at their configured iterations."""
        c = self.config
        if allowed and it > 0 and c.densify_from <= it < densify_until and (
            it % c.densify_interval == 0
        ):
            max_scale = c.prune_max_scale * self.extent if it > c.opacity_reset_interval else None
            info = g.densify_and_prune(
                c.densify_grad_threshold, self.extent, c.percent_dense, c.prune_opacity,
                max_scale, c.max_gaussians, self.generator,
            )
            self.events.append({"event": "densify", "iteration": it, **info})
        if it > 0 and it % c.opacity_reset_interval == 0 and it < densify_until:
            protect = g.small_part_mask(c.small_part_threshold) if g.num_parts > 1 else None
            n = g.reset_opacity(protect)
            self.events.append({"event": "opacity_reset", "iteration": it, "reset": n})

    def generator_state(self) -> torch.Tensor:
        return self.generator.get_state()


# Stage 1 on a view without depth adds this x mean |α̂ − mask| (the silhouette loss): colour
# over a random background constrains α only where the colours differ, and without depth
# nothing else does. On the fridge without depth (8 views at 32 px, quick stage-1 schedule)
# it lowered the median rendered-depth error of both states' models on every one of four
# seed/scene pairs (e.g. 0.095 -> 0.084 m and 0.134 -> 0.116 m; docs/training.md). Views
# with depth skip it: no cost there, and their results stay as they were.
MASK_WEIGHT_WITHOUT_DEPTH = 1.0


class ReconstructState(_Stage):
    """Stage 1: an ordinary Gaussian model of one state (METHOD.md §2)."""

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
        self.total = config.stage1_iterations

    def step(self, it: int) -> dict[str, float]:
        c, g = self.config, self.gaussians
        g.set_lr("means", means_lr(c, it, self.total) * self.extent)
        view = self._pick(self.views)
        bg = self._background()
        out = render(
            g["means"], g["quats"], g["log_scales"], g["opacity"], g.rgb(), view.camera, bg,
            depth=view.depth is not None,
        )
        terms = _image_terms(out, view, bg, c)
        if view.depth is None:
            terms["mask"] = MASK_WEIGHT_WITHOUT_DEPTH * (out.alpha - view.alpha).abs().mean()
        terms["opacity"] = c.lambda_opacity * opacity_binarisation(g["opacity"])
        check_finite(terms, self.name, it)
        loss = sum(terms.values())
        g.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        g.accumulate_screen_grads(g["means"], view.camera)
        g.optimizer.step()
        self._maintain(g, it + 1, c.densify_until, allowed=True)
        return {k: v.item() for k, v in terms.items()}

    def state_dict(self) -> dict:
        return {"generator": self.generator_state()}

    def load_state_dict(self, state: dict) -> None:
        self.generator.set_state(state["generator"])


def phase_at(schedule: str, it: int, interval: int, refine_joint: int) -> str:
    """'E', 'M' (alternation, E first) or 'J' (joint optimisation) at stage-3 iteration `it`."""
    if schedule == "joint":
        return "J"
    if schedule == "em-refine":
        if it < refine_joint:
            return "J"
        it -= refine_joint
    return "E" if (it // interval) % 2 == 0 else "M"


class Refine(_Stage):
    """Stage 3: canonical Gaussians + part logits + per-part motion (METHOD.md §4)."""

    name = "stage3"

    def __init__(
        self,
        gaussians: Gaussians,
        motion,  # noqa: ANN001 (gear.kinematics.PartMotion)
        frozen: Gaussians,
        canonical_views: Sequence[TrainView],
        target_views: Sequence[TrainView],
        config: TrainConfig,
        seed: int,
        init_motions: Sequence = (),  # stage-2 guesses per movable part (see classify_joints)
    ) -> None:
        super().__init__(config, seed)
        self.gaussians, self.motion, self.frozen = gaussians, motion, frozen
        self.init_motions = list(init_motions)
        self.canonical_views = list(canonical_views)
        self.region_views = [v for v in self.canonical_views if v.regions is not None]
        self.target_views = list(target_views)
        self.extent = scene_extent([v.camera for v in self.canonical_views + self.target_views])
        if gaussians.optimizer is None:
            gaussians.setup_optimizer(gaussian_lrs(config, self.extent))
        self.motion_optimizer = self._make_motion_optimizer()
        self.total = config.stage3_iterations
        self._neighbours: torch.Tensor | None = None
        self._neighbours_generation = -1  # Gaussians.generation the lists were built for
        self._anchor_cache: dict[int, tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]] = {}

    def _make_motion_optimizer(self, motion=None) -> torch.optim.Adam:  # noqa: ANN001
        """Adam over the rotation and translation halves of `motion` (default: the run's)."""
        c, motion = self.config, motion if motion is not None else self.motion
        return torch.optim.Adam(
            [
                {"params": [motion.qr], "lr": c.lr_motion_rot},
                {"params": [motion.qd], "lr": c.lr_motion_trans * self.extent},
            ],
            eps=1e-15,
        )

    def neighbours(self) -> torch.Tensor:
        """KNN of the canonical centres, rebuilt lazily whenever the set of Gaussians changed
        (densify/prune, even when the count stays the same). Between two such edits the lists
        are reused while the centres move a little."""
        g = self.gaussians
        if self._neighbours is None or self._neighbours_generation != g.generation:
            pts = g["means"].detach().numpy()
            self._neighbours = torch.as_tensor(nearest_neighbours(pts, self.config.knn_neighbors))
            self._neighbours_generation = g.generation
        return self._neighbours

    def _anchor(self, view_index: int, view: TrainView):
        """The frozen stage-1 canonical model seen from a target camera (zero background)."""
        if view_index not in self._anchor_cache:
            f = self.frozen
            with torch.no_grad():
                out = render(
                    f["means"], f["quats"], f["log_scales"], f["opacity"], f.rgb(), view.camera,
                    torch.zeros(3), depth=True,
                )
            # Depth supervision only where the frozen model is solid (as 0 = missing in data).
            depth = torch.where(out.alpha > 0.5, out.depth, 0.0)
            self._anchor_cache[view_index] = (out.features, out.alpha, depth)
        return self._anchor_cache[view_index]

    def phase(self, it: int) -> str:
        c = self.config
        return phase_at(c.schedule, it, c.em_interval, c.em_refine_joint_iterations)

    def step(self, it: int) -> dict[str, float]:
        c, g = self.config, self.gaussians
        phase = self.phase(it)
        if it == c.joint_classify_iteration:
            self.classify()
        terms = self._motion_step(it) if phase == "M" else self._gaussian_step(it, phase)
        self._maintain(g, it + 1, c.stage3_densify_until, allowed=self.phase(it + 1) != "M")
        return terms

    def _target_view(self) -> tuple[int, TrainView, torch.Tensor]:
        """A random target-state training view (with its index) and background colour."""
        index = int(torch.randint(len(self.target_views), (1,), generator=self.generator))
        return index, self.target_views[index], self._background()

    def _motion_step(self, it: int) -> dict[str, float]:
        """M-step: only the motion trains, under hard assignment, on `m_step_views` target
        views.

        The Gaussians (geometry, colour, opacity, logits) are held fixed, so the motion alone
        has to explain the target view. With them co-training, the M-phases of the quick
        fridge turned the door further from the truth; held, and with 4 views per step, the
        final angle error over four seeds fell from 4.9° to 4.0° on average, lower on every
        seed (docs/training.md). Holding them also saves the anchor render and the Gaussians'
        backward, and leaves the densification statistics to the E-steps, where
        densification happens."""
        drawn = [self._target_view()[1:] for _ in range(self.config.m_step_views)]
        terms = self._held_image_terms(self.motion, *zip(*drawn, strict=True))
        check_finite(terms, self.name, it)
        self.motion_optimizer.zero_grad(set_to_none=True)
        sum(terms.values()).backward()
        self.motion_optimizer.step()
        return {k: v.item() for k, v in terms.items()}

    def _held_image_terms(
        self, motion, views: Sequence[TrainView], backgrounds: Sequence[torch.Tensor],  # noqa: ANN001
    ) -> dict[str, torch.Tensor]:
        """Image terms (photometric + depth), averaged over `views`, of the canonical model
        moved by `motion` under hard (argmax) assignment with every Gaussian parameter held:
        only `motion` receives gradients. The M-step, the hypothesis scoring and its
        fine-tuning all judge a motion this way."""
        c, g = self.config, self.gaussians
        qr, qd = motion.motion(1.0)
        weights = F.one_hot(g.part_ids(), g.num_parts).float()
        means_d, quats_d = deform(g["means"].detach(), g["quats"].detach(), weights, qr, qd)
        log_scales, opacity, rgb = g["log_scales"].detach(), g["opacity"].detach(), g.rgb().detach()
        terms: dict[str, torch.Tensor] = {}
        for view, bg in zip(views, backgrounds, strict=True):
            out = render(means_d, quats_d, log_scales, opacity, rgb, view.camera, bg,
                         depth=view.depth is not None)
            for name, value in _image_terms(out, view, bg, c).items():
                terms[name] = terms.get(name, 0.0) + value / len(views)
        return terms

    def _gaussian_step(self, it: int, phase: str) -> dict[str, float]:
        """E-step (motion frozen, soft assignment, part supervision) or a joint-optimisation
        step ('J': motion, Gaussians and logits all train)."""
        c, g, motion = self.config, self.gaussians, self.motion
        g.set_lr("means", means_lr(c, it, self.total) * self.extent)
        qr, qd = motion.motion(1.0)
        if phase == "E":
            qr, qd = qr.detach(), qd.detach()
        logits = g["logits"]
        weights = torch.softmax(logits, dim=1)
        index, view, bg = self._target_view()
        means_d, quats_d = deform(g["means"], g["quats"], weights, qr, qd)
        means_d.retain_grad()
        rgb = g.rgb()
        out = render(means_d, quats_d, g["log_scales"], g["opacity"], rgb, view.camera, bg,
                     depth=view.depth is not None)
        terms = _image_terms(out, view, bg, c)

        anchor = render(g["means"], g["quats"], g["log_scales"], g["opacity"], rgb, view.camera,
                        bg, depth=True)
        frozen_rgb, frozen_alpha, frozen_depth = self._anchor(index, view)
        anchor_target = frozen_rgb + (1 - frozen_alpha)[..., None] * bg
        terms["anchor"] = c.lambda_anchor * (
            photometric(anchor.features, anchor_target, c.lambda_dssim)
            + c.lambda_depth * depth_log_l1(anchor.depth, frozen_depth)
        )
        terms["opacity"] = c.lambda_opacity * opacity_binarisation(g["opacity"])
        terms.update(self._segmentation_terms(logits))
        check_finite(terms, self.name, it)
        loss = sum(terms.values())
        g.optimizer.zero_grad(set_to_none=True)
        self.motion_optimizer.zero_grad(set_to_none=True)
        loss.backward()
        g.accumulate_screen_grads(means_d, view.camera)
        g.optimizer.step()
        if phase == "J":
            self.motion_optimizer.step()
        return {k: v.item() for k, v in terms.items()}

    def _segmentation_terms(self, logits: torch.Tensor) -> dict:
        """E-step: region-voted pseudo-labels on a rendered logit image (CE) + KNN smoothness."""
        c, g = self.config, self.gaussians
        terms = {"knn": c.lambda_knn * knn_consistency_loss(logits, self.neighbours())}
        if not self.region_views:
            return terms
        view = self._pick(self.region_views)
        # Only the K logit channels: blending is per channel, so the colour channels the
        # image used to carry along changed nothing but the cost of the render.
        logit_image = render(
            g["means"], g["quats"], g["log_scales"], g["opacity"], logits, view.camera,
            torch.zeros(g.num_parts),
        ).features
        prob = torch.softmax(logit_image.detach(), dim=-1).numpy()
        labels = region_pseudo_labels(
            prob, view.regions, self.motion.prismatic.numpy(), gamma=c.gamma_prism,
            min_conf=c.pseudo_min_conf, min_gap=c.pseudo_min_gap, min_area=c.pseudo_min_area,
        )
        fg = view.alpha > 0.5
        terms["sam"] = c.lambda_sam * sam_ce_loss(
            logit_image, torch.as_tensor(labels), fg, static_weight=c.static_class_weight
        )
        return terms

    def classify(self) -> None:
        """Revolute joints below ε become prismatic; the motion optimizer is rebuilt. The
        log event lists every scored reading's loss (in scoring order) and, per movable
        part, the joint type and angle that came out."""
        c = self.config
        resolve = c.resolve_ambiguous_joints
        scores: list[float] = []

        def score(candidate) -> float:  # noqa: ANN001 (PartMotion)
            scores.append(self.motion_loss(candidate))
            return scores[-1]

        switched = classify_joints(
            self.motion,
            eps_deg=c.revolute_eps_deg,
            score=score if resolve else None,
            init_motions=self.init_motions if resolve and self.init_motions else None,
            small_hinge_margin=c.small_hinge_margin,
        )
        qr, _ = self.motion.motion()
        angles = [round(math.degrees(float(a)), 3) for a in quat_angle(qr.detach())[1:]]
        types = ["prismatic" if p else "revolute" for p in self.motion.prismatic[1:].tolist()]
        self.events.append({"event": "joint_classification", "prismatic": list(switched),
                            "scores": scores, "types": types, "angles_deg": angles})
        # Any part below ε may have been rewritten (slide or initial hinge): fresh Adam moments.
        self.motion_optimizer = self._make_motion_optimizer()

    def _scoring_views(self) -> list[TrainView]:
        """Up to 8 target training views, evenly spaced: the fixed set hypotheses are judged on."""
        return self.target_views[:: max(1, len(self.target_views) // 8)]

    def motion_loss(self, candidate) -> float:  # noqa: ANN001 (PartMotion)
        """Photometric + depth loss of the hard-assigned model moved by `candidate`, over the
        scoring views on a black background, after `classify_tune_steps` motion-only steps
        on the candidate (tune_motion): how well a joint hypothesis explains the target
        images once it has had the same short chance to settle as every other one. No
        ground truth is involved. `candidate` is the caller's copy and is tuned in place."""
        self.tune_motion(candidate, self.config.classify_tune_steps)
        views = self._scoring_views()
        black = [torch.zeros(3)] * len(views)
        with torch.no_grad():
            terms = self._held_image_terms(candidate, views, black)
        return float(sum(terms.values()))

    def tune_motion(self, candidate, steps: int) -> None:  # noqa: ANN001 (PartMotion)
        """`steps` Adam steps on the motion of `candidate` alone (the Gaussians held, hard
        assignment, as in the M-step), each on the next of the scoring views in turn over a
        black background: deterministic, and the same budget for every joint hypothesis. One
        view per step keeps it cheap (a few readings x 30 renders); Adam's moments average
        over the cycle. A fresh optimizer with the M-step's learning rates; `self.motion`
        and its optimizer are untouched."""
        if steps <= 0:
            return
        optimizer = self._make_motion_optimizer(candidate)
        views = self._scoring_views()
        with torch.enable_grad():
            for step in range(steps):
                terms = self._held_image_terms(candidate, [views[step % len(views)]],
                                               [torch.zeros(3)])
                check_finite(terms, f"{self.name} joint scoring", step)
                optimizer.zero_grad(set_to_none=True)
                sum(terms.values()).backward()
                optimizer.step()

    def state_dict(self) -> dict:
        return {
            "generator": self.generator_state(),
            "motion": self.motion.state_dict(),
            "motion_optimizer": self.motion_optimizer.state_dict(),
        }

    def load_state_dict(self, state: dict) -> None:
        self.generator.set_state(state["generator"])
        self.motion.load_state_dict(state["motion"])
        self.motion_optimizer.load_state_dict(state["motion_optimizer"])
