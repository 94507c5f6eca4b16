"""Stage 3's E-step (and the joint-optimisation step): the motion held (or, in 'J', trained
too), the Gaussians and their part logits learn under soft assignment, anchored to the
canonical images (or the frozen stage-1 model) and supervised by region pseudo-labels and KNN
smoothness (docs/method.md, "Stage 3: E-step").

A step's loss has two halves that share only the Gaussians' parameters: the target view's
render of the deformed model (with the opacity and KNN terms), and the anchor's render of the
undeformed model (with the part supervision on its logit channels). Each half builds and
differentiates its own graph, one beside the other (common.map_beside); the anchor half's
gradients are then added to the target half's, always in that order, so a step's result does
not depend on which thread finished first."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch

from gear.fused_consistency import fused_knn_consistency
from gear.fused_deform import fused_deform
from gear.losses import (
    depth_log_l1,
    opacity_binarisation,
    photometric,
    region_pseudo_labels,
    sam_ce_loss,
)
from gear.pipeline.common import TrainView, check_finite, image_terms, map_beside, means_lr
from gear.pipeline.stage3.shared import RefineState
from gear.splats import render
from gear.splats.sh import SH_PARAM

Terms = dict[str, torch.Tensor]


@dataclass(frozen=True)
class AnchorViews:
    """The views a step's anchor half renders, drawn before either half starts (so that the
    state's generator draws them in one order): `own`, the canonical image the anchor renders
    (None: the frozen stage-1 model's render from the target camera anchors), and `regions`,
    the view whose rendered logits the region pseudo-labels supervise (None: no view has
    regions). When `regions` is `own`, one render serves both terms."""

    own: TrainView | None
    regions: TrainView | None

    @classmethod
    def draw(cls, state: RefineState) -> AnchorViews:
        own = None if state.config.anchor == "frozen" else state.pick(state.canonical_views)
        if own is not None and own.regions is not None:
            return cls(own, own)
        return cls(own, state.pick(state.region_views) if state.region_views else None)


def gaussian_step(state: RefineState, it: int, phase: str) -> dict[str, float]:
    """E-step (motion frozen, soft assignment, part supervision) or a joint-optimisation step
    ('J': motion, Gaussians and logits all train) on `state`."""
    c, g, motion = state.config, state.gaussians, state.motion
    g.set_lr("means", means_lr(c, it, state.total) * state.extent)
    qr, qd = motion.motion(1.0)
    if phase == "E":
        qr, qd = qr.detach(), qd.detach()
    index, view, bg = state.target_view()
    anchor_views = AnchorViews.draw(state)
    g.optimizer.zero_grad(set_to_none=True)
    state.motion_optimizer.zero_grad(set_to_none=True)
    halves: list[Callable[[], tuple]] = [
        lambda: target_half(state, it, view, bg, qr, qd),
        lambda: anchor_half(state, it, index, view, bg, anchor_views),
    ]
    (terms, means_d), (anchor_terms, anchor_grads) = map_beside(lambda half: half(), halves)
    add_gradients(list(g.params.values()), anchor_grads)
    state.densifier.accumulate(means_d, view.camera, it + 1, c.stage3_densify_until)
    g.optimizer.step()
    if phase == "J":
        state.step_motion()
    return {k: v.item() for k, v in {**terms, **anchor_terms}.items()}


def target_half(state: RefineState, it: int, view: TrainView, bg: torch.Tensor,
                qr: torch.Tensor, qd: torch.Tensor) -> tuple[Terms, torch.Tensor]:
    """The deformed model against the target view, the opacity and KNN terms; backpropagated
    into the parameters' (and, in 'J', the motion's) gradients. Returns its terms and the
    deformed means, whose gradient the densification statistics read."""
    c, g = state.config, state.gaussians
    logits = g["logits"]
    # Soft assignment: each Gaussian's part weights are the softmax of its logits.
    means_d, quats_d = fused_deform(g["means"], g["quats"], logits, qr, qd, softmax=True)
    means_d.retain_grad()
    # With spherical harmonics the colours depend on the camera and the pose: the render
    # computes them.
    rgb = None if SH_PARAM in g.params else g.rgb()
    out = render(g, view.camera, bg, pose=(means_d, quats_d), features=rgb,
                 depth=view.depth is not None)
    terms = image_terms(out, view, bg, c)
    terms["opacity"] = c.lambda_opacity * opacity_binarisation(g["opacity"])
    terms["knn"] = c.lambda_knn * fused_knn_consistency(logits, state.neighbours())
    check_finite(terms, state.name, it)
    sum(terms.values()).backward()
    return terms, means_d


def anchor_half(state: RefineState, it: int, index: int, view: TrainView, bg: torch.Tensor,
                views: AnchorViews) -> tuple[Terms, Sequence[torch.Tensor | None]]:
    """The anchor and part-supervision terms and their gradients with respect to the
    Gaussians' parameters (in `params` order; None for one they do not reach), left for the
    caller to add: this half runs beside the target half, which writes the gradients."""
    c, g = state.config, state.gaussians
    rgb = None if SH_PARAM in g.params else g.rgb()
    anchor, part_image = anchor_term(state, index, view, bg, rgb, views)
    terms = {"anchor": c.lambda_anchor * anchor}
    if views.regions is not None:
        terms["sam"] = c.lambda_sam * part_supervision(state, views.regions, part_image)
    check_finite(terms, state.name, it)
    params = list(g.params.values())
    return terms, torch.autograd.grad(sum(terms.values()), params, allow_unused=True)


def add_gradients(params: Sequence[torch.Tensor], grads: Sequence[torch.Tensor | None]) -> None:
    """params[i].grad += grads[i] (None: nothing to add)."""
    for param, grad in zip(params, grads, strict=True):
        if grad is None:
            continue
        if param.grad is None:
            param.grad = grad
        else:
            param.grad.add_(grad)


def anchor_term(state: RefineState, index: int, view: TrainView, bg: torch.Tensor,
                rgb: torch.Tensor | None, views: AnchorViews,
                ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """What holds the undeformed canonical model: the frozen stage-1 model seen from the
    target camera `view`, or (anchor = "images") the canonical-state training image
    `views.own`, so that the canonical geometry answers to both states' images rather than to
    stage 1's reading of one.

    When `views.own` is also the region view, the same render blends the part logits too and
    returns them as the part supervision's image: one projection and sort serve both terms
    (blending is per channel, so each channel's gradient is what a render of its own would
    give)."""
    c, g = state.config, state.gaussians
    own = views.own
    if own is None:
        return frozen_anchor_term(state, index, view, bg, rgb), None
    logits = g["logits"]
    with_logits = views.regions is own
    out = render(g, own.camera, bg, features=rgb, extra=logits if with_logits else None,
                 depth=own.depth is not None)
    term = sum(image_terms(out, own, bg, c).values())
    # The extra channels come last.
    return term, out.features[..., -logits.shape[1]:] if with_logits else None


def frozen_anchor_term(state: RefineState, index: int, view: TrainView, bg: torch.Tensor,
                       rgb: torch.Tensor | None) -> torch.Tensor:
    """The paper's anchor: the frozen stage-1 model's render from the target camera."""
    c, g = state.config, state.gaussians
    out = render(g, view.camera, bg, features=rgb, depth=True)
    frozen_rgb, frozen_alpha, frozen_depth = state.anchor(index, view)
    target = frozen_rgb + (1 - frozen_alpha)[..., None] * bg
    return (photometric(out.features, target, c.lambda_dssim)
            + c.lambda_depth * depth_log_l1(out.depth, frozen_depth))


def part_supervision(state: RefineState, view: TrainView,
                     logit_image: torch.Tensor | None) -> torch.Tensor:
    """Cross-entropy of the logits rendered from region view `view` (`logit_image`, when the
    anchor rendered it already) against the pseudo-labels its regions vote for."""
    c, g = state.config, state.gaussians
    if logit_image is None:
        # Only the K logit channels: blending is per channel, so colour channels carried
        # along would change nothing but the cost of the render.
        logit_image = render(g, view.camera, features=g["logits"]).features
    prob = torch.softmax(logit_image.detach(), dim=-1).numpy()
    labels = region_pseudo_labels(
        prob, view.regions, state.motion.prismatic.numpy(), gamma=c.gamma_prism,
        min_conf=c.pseudo_min_conf, min_gap=c.pseudo_min_gap, min_area=c.pseudo_min_area,
    )
    fg = view.alpha > 0.5
    return sam_ce_loss(logit_image, torch.as_tensor(labels), fg,
                       static_weight=c.static_class_weight)
