"""Stage 3's E-step (and the joint-optimisation step): the motion held (or, in 'J', trained
too), the Gaussians and their part logits learn under soft assignment, anchored to the
canonical images (or the frozen stage-1 model) and supervised by region pseudo-labels and KNN
smoothness (docs/method.md, "Stage 3: E-step")."""

from __future__ import annotations

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
from gear.pipeline.common import TrainView, check_finite, image_terms, means_lr
from gear.pipeline.stage3.shared import RefineState
from gear.splats import render
from gear.splats.sh import SH_PARAM

# A region view and the part logits rendered from it [H,W,K].
PartImage = tuple[TrainView, torch.Tensor]


def gaussian_step(state: RefineState, it: int, phase: str) -> dict[str, float]:
    """E-step (motion frozen, soft assignment, part supervision) or a joint-optimisation step
    ('J': motion, Gaussians and logits all train) on `state`."""
    c, g, motion = state.config, state.gaussians, state.motion
    g.set_lr("means", means_lr(c, it, state.total) * state.extent)
    qr, qd = motion.motion(1.0)
    if phase == "E":
        qr, qd = qr.detach(), qd.detach()
    logits = g["logits"]
    index, view, bg = state.target_view()
    # Soft assignment: each Gaussian's part weights are the softmax of its logits.
    means_d, quats_d = fused_deform(g["means"], g["quats"], logits, qr, qd, softmax=True)
    means_d.retain_grad()
    # Shared by both renders; with spherical harmonics the colours depend on the camera and
    # the pose, so each render computes its own.
    rgb = None if SH_PARAM in g.params else g.rgb()
    out = render(g, view.camera, bg, pose=(means_d, quats_d), features=rgb,
                 depth=view.depth is not None)
    terms = image_terms(out, view, bg, c)

    anchor, part_image = anchor_term(state, index, view, bg, rgb, logits)
    terms["anchor"] = c.lambda_anchor * anchor
    terms["opacity"] = c.lambda_opacity * opacity_binarisation(g["opacity"])
    terms.update(segmentation_terms(state, logits, part_image))
    check_finite(terms, state.name, it)
    loss = sum(terms.values())
    g.optimizer.zero_grad(set_to_none=True)
    state.motion_optimizer.zero_grad(set_to_none=True)
    loss.backward()
    state.densifier.accumulate(means_d, view.camera, it + 1, c.stage3_densify_until)
    g.optimizer.step()
    if phase == "J":
        state.motion_optimizer.step()
    return {k: v.item() for k, v in terms.items()}


def anchor_term(state: RefineState, index: int, view: TrainView, bg: torch.Tensor,
                rgb: torch.Tensor | None, logits: torch.Tensor | None = None,
                ) -> tuple[torch.Tensor, PartImage | None]:
    """What holds the undeformed canonical model: the frozen stage-1 model seen from the
    target camera `view`, or (anchor = "images") a canonical-state training image, so that the
    canonical geometry answers to both states' images rather than to stage 1's reading of one.

    With the images, when that image has regions and `logits` are given, the same render
    blends the logits too and returns them as the part supervision's image: one projection
    and sort serve both terms (blending is per channel, so each channel's gradient is what a
    render of its own would give)."""
    c, g = state.config, state.gaussians
    if c.anchor == "frozen":
        return frozen_anchor_term(state, index, view, bg, rgb), None
    own = state.pick(state.canonical_views)
    with_logits = logits is not None and own.regions is not None
    out = render(g, own.camera, bg, features=rgb, extra=logits if with_logits else None,
                 depth=own.depth is not None)
    term = sum(image_terms(out, own, bg, c).values())
    if not with_logits:
        return term, None
    return term, (own, out.features[..., -logits.shape[1]:])  # the extra channels come last


def frozen_anchor_term(state: RefineState, index: int, view: TrainView, bg: torch.Tensor,
                       rgb: torch.Tensor | None) -> torch.Tensor:
    """The paper's anchor: the frozen stage-1 model's render from the target camera."""
    c, g = state.config, state.gaussians
    out = render(g, view.camera, bg, features=rgb, depth=True)
    frozen_rgb, frozen_alpha, frozen_depth = state.anchor(index, view)
    target = frozen_rgb + (1 - frozen_alpha)[..., None] * bg
    return (photometric(out.features, target, c.lambda_dssim)
            + c.lambda_depth * depth_log_l1(out.depth, frozen_depth))


def segmentation_terms(state: RefineState, logits: torch.Tensor,
                       part_image: PartImage | None = None) -> dict:
    """Region-voted pseudo-labels on a rendered logit image (CE) + KNN smoothness.
    `part_image`: a region view and its logit image rendered already (by the anchor), else
    a region view is drawn and its logits rendered here."""
    c, g = state.config, state.gaussians
    terms = {"knn": c.lambda_knn * fused_knn_consistency(logits, state.neighbours())}
    if part_image is None:
        if not state.region_views:
            return terms
        view = state.pick(state.region_views)
        # Only the K logit channels: blending is per channel, so colour channels carried
        # along would change nothing but the cost of the render.
        part_image = view, render(g, view.camera, features=logits).features
    view, logit_image = part_image
    prob = torch.softmax(logit_image.detach(), dim=-1).numpy()
    labels = region_pseudo_labels(
        prob, view.regions, state.motion.prismatic.numpy(), gamma=c.gamma_prism,
        min_conf=c.pseudo_min_conf, min_gap=c.pseudo_min_gap, min_area=c.pseudo_min_area,
    )
    fg = view.alpha > 0.5
    terms["sam"] = c.lambda_sam * sam_ce_loss(
        logit_image, torch.as_tensor(labels), fg, static_weight=c.static_class_weight
    )
    return terms
