"""What stage 3's E-step, M-step and joint-type decision share: the refinement's state (the
canonical Gaussians with part logits, the part motions, the frozen stage-1 model, the views),
the phase schedule, the motion optimiser, the anchor renders and the image terms of the model
posed under hard assignment (docs/method.md, "Stage 3")."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from gear.articulation import PartMotion
from gear.config import TrainConfig
from gear.geometry import nearest_neighbours
from gear.kinematics import dq_from_rt, dq_to_rt, quat_identity, quat_mul, quat_rotate
from gear.pipeline.common import Stage, TrainView, gaussian_lrs, image_terms, map_beside
from gear.splats import Densifier, Gaussians, StaticLayers, gaussian_budget, render
from gear.splats.init import scene_extent
from gear.splats.sh import SH_PARAM


def phase_at(schedule: str, it: int, interval: int, refine_joint: int) -> str:
    """'E', 'M' (alternation, E first) or 'J' (joint optimisation) at stage-3 iteration `it`."""
    if schedule == "joint":
        return "J"
    if schedule == "em-refine":
        if it < refine_joint:
            return "J"
        it -= refine_joint
    return "E" if (it // interval) % 2 == 0 else "M"


def motion_optimizer(motion: PartMotion, config: TrainConfig, extent: float) -> torch.optim.Adam:
    """Adam over the rotation and translation halves of `motion`."""
    return torch.optim.Adam(
        [
            {"params": [motion.qr], "lr": config.lr_motion_rot},
            {"params": [motion.qd], "lr": config.lr_motion_trans * extent},
        ],
        eps=1e-15,
    )


class HeldModel:
    """The canonical Gaussians as the motion-only steps see them (M-step, joint scoring and its
    tuning): every parameter detached and the Gaussians sorted by hard part (argmax of the
    logits), so posing them is one 3x3 and one 4x4 matrix product per part, not a
    dual-quaternion blend of one-hot weights per Gaussian (the same rigid motion; the render
    does not depend on the order of its Gaussians). Built once and reused while the Gaussians
    are unchanged, i.e. for a whole M-phase or one joint-type decision."""

    def __init__(self, g: Gaussians) -> None:
        self.key = held_key(g)
        ids = g.part_ids()
        order = torch.argsort(ids, stable=True)
        self.counts = torch.bincount(ids, minlength=g.num_parts).tolist()
        means, quats, log_scales, opacity, rgb = (t.detach()[order] for t in g.splat_arrays())
        self.means, self.quats = means, quats
        self._drawn = (log_scales, opacity, rgb)
        # The view-dependent colour's coefficients, in the same order (gear.splats.sh reads
        # them from `params` like a Gaussians' own).
        self.params = {SH_PARAM: g[SH_PARAM].detach()[order]} if SH_PARAM in g.params else {}
        # The static part comes first and never moves: its render from each camera is kept
        # (None: every render in full).
        self.layers: StaticLayers | None = StaticLayers(self.counts[0])

    def pose(self, qr: torch.Tensor, qd: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(means, quats) [N, 3], [N, 4] of the held Gaussians moved rigidly with their parts by
        the unit dual quaternions qr, qd [K, 4] (part 0's the identity: the static part stays
        as it is, bit for bit what its layers were made of); differentiable in qr and qd."""
        # Row j of rot_t[k] is R_k e_j (so x R_k^T = x @ rot_t[k]); row i of turn[k] is
        # qr_k * e_i (so qr_k * q = q @ turn[k]).
        rot_t = quat_rotate(qr[:, None, :], torch.eye(3, dtype=qr.dtype))
        turn = quat_mul(qr[:, None, :], torch.eye(4, dtype=qr.dtype))
        shift = dq_to_rt(qr, qd)[1]
        static_means, *means = self.means.split(self.counts)
        static_quats, *quats = self.quats.split(self.counts)
        means = [m @ rot_t[k] + shift[k] for k, m in enumerate(means, start=1)]
        quats = [q @ turn[k] for k, q in enumerate(quats, start=1)]
        return torch.cat([static_means, *means]), torch.cat([static_quats, *quats])

    def splat_arrays(self) -> tuple[torch.Tensor, ...]:
        return (self.means, self.quats, *self._drawn)


def held_key(g: Gaussians) -> tuple:
    """Changes whenever the set of Gaussians is edited (densify/prune: `generation`, since a
    freed tensor's id can be reused) or a parameter is updated in place: by an edit of its
    values (torch's in-place version counter) or by an optimizer step (the step counts of its
    Adam state: the fused Adam kernel writes the parameters without bumping their version)."""
    state = g.optimizer.state if g.optimizer is not None else {}
    return (g.generation, *((id(t), t._version, _adam_steps(state.get(t)))
                            for t in g.params.values()))


def _adam_steps(moments: dict | None) -> float:
    """How many Adam steps a parameter has taken (0 before its first)."""
    return float(moments["step"]) if moments and "step" in moments else 0.0


class RefineState(Stage):
    """Stage 3's state: canonical Gaussians + part logits + per-part motion, the frozen
    stage-1 model of the canonical state (None unless the anchor is "frozen"), and the views
    of both states. `halves`: pairs of parts that stage 2 cut from one part tall along its hinge
    (stage2.stacked), kept apart until the end of stage 3. `held_slides`: per movable part, the
    deepest shift its slide is held to (stage 2 pushed it along the body's frame), or None:
    such a part slides along that line from the start, no deeper, and trains its travel alone
    (hold_slides)."""

    name = "stage3"

    def __init__(
        self,
        gaussians: Gaussians,
        motion: PartMotion,
        frozen: Gaussians | None,
        canonical_views: Sequence[TrainView],
        target_views: Sequence[TrainView],
        config: TrainConfig,
        seed: int,
        init_motions: Sequence = (),  # stage-2 candidates per movable part (joint_types)
        canonical: str = "start",
        halves: Sequence[tuple[int, int]] = (),
        held_slides: Sequence[np.ndarray | None] = (),
    ) -> None:
        super().__init__(config, seed)
        self.gaussians, self.motion, self.frozen = gaussians, motion, frozen
        self.init_motions = list(init_motions)
        self.canonical = canonical
        self.halves = [tuple(pair) for pair in halves]
        self.held_slides = {k: np.asarray(deepest, dtype=np.float64)
                            for k, deepest in enumerate(held_slides, start=1)
                            if deepest is not None}
        self.canonical_views = list(canonical_views)
        self.region_views = [v for v in self.canonical_views if v.regions is not None]
        self.target_views = list(target_views)
        self.extent = scene_extent([v.camera for v in self.canonical_views + self.target_views])
        if gaussians.optimizer is None:
            gaussians.setup_optimizer(gaussian_lrs(config, self.extent))
        self.densifier = Densifier(
            gaussians, gaussian_budget(config, [v.camera for v in self.canonical_views]))
        self.motion_optimizer = motion_optimizer(motion, config, self.extent)
        self.hold_slides()
        self.total = config.stage3_iterations
        self._neighbours: torch.Tensor | None = None
        self._neighbours_generation = -1  # Gaussians.generation the lists were built for
        self._anchor_cache: dict[int, tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = {}
        self._held: HeldModel | None = None

    def phase(self, it: int) -> str:
        c = self.config
        return phase_at(c.schedule, it, c.em_interval, c.em_refine_joint_iterations)

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

    def cache_anchor_renders(self) -> None:
        """Every target view's frozen-anchor render, as late in a run (none without a frozen
        model: the images anchor renders nothing ahead)."""
        if self.frozen is not None:
            for index, view in enumerate(self.target_views):
                self.anchor(index, view)

    def anchor(self, view_index: int, view: TrainView) -> tuple[torch.Tensor, ...]:
        """The frozen stage-1 canonical model seen from a target camera (zero background):
        (features, alpha, depth where solid), rendered once per view."""
        if self.frozen is None:
            raise ValueError('anchor = "frozen" needs the frozen stage-1 model; none was kept')
        if view_index not in self._anchor_cache:
            with torch.no_grad():
                out = render(self.frozen, view.camera, torch.zeros(3), depth=True)
            # Depth supervision only where the frozen model is solid (as 0 = missing in data).
            depth = torch.where(out.alpha > 0.5, out.depth, 0.0)
            self._anchor_cache[view_index] = (out.features, out.alpha, depth)
        return self._anchor_cache[view_index]

    def target_view(self) -> tuple[int, TrainView, torch.Tensor]:
        """A random target-state training view (with its index) and background colour."""
        index = self.pick_index(len(self.target_views))
        return index, self.target_views[index], self.background()

    def scoring_views(self) -> list[TrainView]:
        """Up to 8 target training views, evenly spaced: the fixed set hypotheses are judged on."""
        return self.target_views[:: max(1, len(self.target_views) // 8)]

    def held_image_terms(
        self, motion: PartMotion, views: Sequence[TrainView], backgrounds: Sequence[torch.Tensor],
    ) -> dict[str, torch.Tensor]:
        """Image terms (photometric + depth), averaged over `views`, of the canonical model
        moved by `motion` under hard (argmax) assignment with every Gaussian parameter held:
        only `motion` receives gradients. The M-step, the hypothesis scoring and its
        fine-tuning all judge a motion this way."""
        held = self.held()
        pose = held.pose(*motion.motion(1.0))  # once for every view
        pairs = list(zip(views, backgrounds, strict=True))

        def view_terms(pair: tuple[TrainView, torch.Tensor]) -> dict[str, torch.Tensor]:
            return self._held_view_terms(held, pose, *pair, len(views))

        # Without gradients the views render beside each other (map_beside); a graph that
        # torch's autograd builds on two threads would order its sums by thread.
        if torch.is_grad_enabled():
            return _summed([view_terms(pair) for pair in pairs])
        return _summed(map_beside(view_terms, pairs))

    def held_image_step(self, motion: PartMotion, views: Sequence[TrainView],
                        backgrounds: Sequence[torch.Tensor]) -> dict[str, torch.Tensor]:
        """held_image_terms, with the gradient of their sum added to `motion`'s tensors: each
        view is rendered and differentiated on its own, beside the others (map_beside), and
        its gradients in the posed Gaussians are summed last view first, as torch's autograd
        adds them up in one graph of all the views, then passed through the posing once: the
        motion's gradients are bit for bit those of backward() on held_image_terms."""
        held = self.held()
        pose = held.pose(*motion.motion(1.0))

        def view_step(pair: tuple[TrainView, torch.Tensor]) -> tuple[dict, tuple]:
            leaves = tuple(p.detach().requires_grad_() for p in pose)
            terms = self._held_view_terms(held, leaves, *pair, len(views))
            return terms, torch.autograd.grad(sum(terms.values()), leaves)

        per_view = map_beside(view_step, list(zip(views, backgrounds, strict=True)))
        grads = [sum(g[1][i] for g in reversed(per_view)) for i in range(len(pose))]
        torch.autograd.backward(pose, grads)
        return _summed([terms for terms, _ in per_view])

    def _held_view_terms(self, held: HeldModel, pose: tuple[torch.Tensor, torch.Tensor],
                         view: TrainView, bg: torch.Tensor, count: int) -> dict[str, torch.Tensor]:
        """One view's image terms of the held model at `pose`, divided by the `count` views
        they are averaged over."""
        # The static part comes first and never moves (part 0's motion is the identity): its
        # Gaussians pass no gradient, the rasterizer's backward skips their work, and its
        # forward starts from their layer for this camera (only what moves is binned, and
        # only where it lands is blended).
        out = render(held, view.camera, bg, pose=pose, depth=view.depth is not None,
                     held=held.counts[0], layers=held.layers)
        terms = image_terms(out, view, bg, self.config)
        return {name: value / count for name, value in terms.items()}

    def step_motion(self) -> None:
        """One step of the motion optimizer, the held slides kept on their lines."""
        self.motion_optimizer.step()
        self.hold_slides()

    def hold_slides(self) -> None:
        """Each held slide's translation projected onto its line and kept between no shift and
        its deepest, its rotation the identity: what Adam adds across the line or beyond the
        reach is taken back after every step. A drawer pushed into its cabinet is hidden and
        looks like its neighbours, so the images pull on it little, and Adam's steps,
        normalised per coordinate, turn a small steady pull into full-sized ones: a real
        kitchen island's trays drifted 0.2-0.3 along the island in 100 M-steps, and, held to
        their lines, one went on into its cabinet to 2.4 times its travel. Projecting the
        gradient instead would not do: Adam would still step each coordinate at full size."""
        if not self.held_slides:
            return
        with torch.no_grad():
            qr, qd = self.motion.motion()
            _, trans = dq_to_rt(qr, qd)
            identity = quat_identity((), qr.dtype, qr.device)
            for k, deepest in self.held_slides.items():
                reach = float(np.linalg.norm(deepest))
                direction = torch.as_tensor(deepest / reach, dtype=trans.dtype,
                                            device=trans.device)
                kept = torch.clamp(trans[k] @ direction, 0.0, reach) * direction
                self.motion.set_part(k, identity, dq_from_rt(identity, kept)[1], prismatic=True)

    def live_parts(self) -> list[int]:
        """The movable parts some Gaussian belongs to (argmax of its logits)."""
        counts = torch.bincount(self.gaussians.part_ids(), minlength=self.motion.num_parts)
        return [k for k in range(1, self.motion.num_parts) if int(counts[k]) > 0]

    def held(self) -> HeldModel:
        """The held model of the current Gaussians (rebuilt only after they changed)."""
        if self._held is None or self._held.key != held_key(self.gaussians):
            self._held = HeldModel(self.gaussians)
        return self._held

    def maintain(self, it: int) -> None:
        """Densify/prune and opacity reset at their iterations, never inside an M-phase (the
        M-step leaves the densification statistics alone)."""
        c = self.config
        self.events += self.densifier.maintain(
            self.gaussians, it + 1, c, self.extent, c.stage3_densify_until,
            self.phase(it + 1) != "M", self.generator,
        )


def _summed(per_view: Sequence[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """Each term summed over the views, in their order."""
    terms: dict[str, torch.Tensor] = {}
    for view_terms in per_view:
        for name, value in view_terms.items():
            terms[name] = terms.get(name, 0.0) + value
    return terms
