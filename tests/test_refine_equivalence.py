"""Stage 3's cost-saving formulation optimises exactly what the straightforward one does.

The reference below is the plain reading of the E-step's canonical terms (docs/method.md):
the anchor renders a canonical image's colours; the part supervision renders the same view's
colours with the K part logits as extra channels and takes the logit channels. Refine blends
the colours and the logits in the anchor's one render (blending is per channel, so each
channel's gradient is what its own render gives), or the logit channels alone when no anchor
render has them. Both run the same seeded E- and M-steps with the deterministic torch
renderer; losses and every trained tensor must agree to float rounding.
"""

from dataclasses import replace

import pytest
import torch

from gear.losses import region_pseudo_labels, sam_ce_loss
from gear.pipeline.common import TrainView, image_terms
from gear.pipeline.stage3 import Refine, estep
from gear.pipeline.stage3.shared import RefineState
from gear.splat_reference import rasterize_dense
from gear.splats import rendering
from test_train import refine_stage

# float32 rounding of a differently shaped blend, carried through a few Adam steps (the
# differences seen: below 1e-7 with torch's per-tensor Adam, one logit 1.3e-6 apart with the
# fused kernel, whose step divides a rounding difference in a small gradient by its own size)
ATOL = 2e-6
RTOL = 1e-5


def reference_anchor_term(state: RefineState, index: int, view: TrainView, bg: torch.Tensor,
                           rgb: torch.Tensor | None, logits: torch.Tensor | None = None):
    """estep.anchor_term (images) with its colours and the part logits in renders of their
    own: the colours over the background, the colours (no gradient) + logits over black."""
    c, g = state.config, state.gaussians
    own = state.pick(state.canonical_views)
    out = rendering.render(g, own.camera, bg, features=rgb, depth=own.depth is not None)
    term = sum(image_terms(out, own, bg, c).values())
    if logits is None or own.regions is None:
        return term, None
    features = torch.cat([g.rgb().detach(), logits], dim=1)
    both = rendering.render(g, own.camera, torch.zeros(3 + g.num_parts), features=features)
    return term, (own, both.features[..., 3:])


def reference_segmentation_terms(state: RefineState, logits: torch.Tensor,
                                 part_image: estep.PartImage | None = None) -> dict:
    """estep.segmentation_terms with the consistency term as written."""
    c = state.config
    neighbours = state.neighbours()
    # The consistency term as written: mean over every (Gaussian, neighbour) pair.
    diffs = [(logits - logits[nb]).norm(dim=1) for nb in neighbours.unbind(1)]
    terms = {"knn": c.lambda_knn * torch.stack(diffs, dim=1).mean()}
    if part_image is None:  # the anchor's view has no regions: one that has them, rendered
        view = state.pick(state.region_views)
        features = torch.cat([state.gaussians.rgb().detach(), logits], dim=1)
        out = rendering.render(state.gaussians, view.camera,
                               torch.zeros(3 + state.gaussians.num_parts), features=features)
        part_image = view, out.features[..., 3:]
    view, logit_image = part_image
    labels = region_pseudo_labels(
        torch.softmax(logit_image.detach(), dim=-1), view.regions,
        state.motion.prismatic, gamma=c.gamma_prism, min_conf=c.pseudo_min_conf,
        min_gap=c.pseudo_min_gap, min_area=c.pseudo_min_area,
    )
    terms["sam"] = c.lambda_sam * sam_ce_loss(logit_image, labels, view.alpha > 0.5,
                                              static_weight=c.static_class_weight)
    return terms


def reference_step(stage: Refine, it: int, monkeypatch: pytest.MonkeyPatch) -> dict:
    """One step of `stage` with the reference canonical terms in place of the fast ones."""
    with monkeypatch.context() as patched:
        patched.setattr(estep, "anchor_term", reference_anchor_term)
        patched.setattr(estep, "segmentation_terms", reference_segmentation_terms)
        return stage.step(it)


def stage(regions_on: str = "every view") -> Refine:
    """test_train's tiny Refine with turned, anisotropic Gaussians: on its isotropic,
    unrotated ones the rotation gradient is exactly zero, and Adam would turn the rounding
    noise left there into full learning-rate steps of either sign. `regions_on`: "every
    view", or "the first view" (the other canonical views carry no region masks)."""
    out = refine_stage()
    gen = torch.Generator().manual_seed(11)
    with torch.no_grad():
        g = out.gaussians
        g["quats"].copy_(torch.nn.functional.normalize(torch.randn(len(g), 4, generator=gen)))
        g["log_scales"].add_(0.4 * torch.randn(len(g), 3, generator=gen))
    if regions_on == "the first view":
        out.canonical_views[1:] = [replace(v, regions=None) for v in out.canonical_views[1:]]
        out.region_views = out.canonical_views[:1]
    return out


@pytest.fixture
def torch_renderer(monkeypatch):
    # The GPU backward sums with atomics (run-to-run float reordering); the torch renderer is
    # deterministic, so any difference left is the formulation's.
    monkeypatch.setattr(rendering, "rasterizer", lambda: rasterize_dense)


@pytest.mark.parametrize("regions_on", ["every view", "the first view"])
def test_refine_steps_match_the_straightforward_formulation(torch_renderer, monkeypatch,
                                                            regions_on):
    fast, reference = stage(regions_on), stage(regions_on)
    shared = []  # per E-step of `fast`: did the anchor's render carry the part logits?
    segmentation_terms = estep.segmentation_terms

    def spy(state, logits, part_image=None):
        shared.append(part_image is not None)
        return segmentation_terms(state, logits, part_image)

    monkeypatch.setattr(estep, "segmentation_terms", spy)
    assert {"sam", "knn", "anchor"} <= set(fast.step(0))  # an E-step with every term
    reference_step(reference, 0, monkeypatch)
    for it in range(1, 6):  # E, M, M, E, E (em_interval = 2)
        got, want = fast.step(it), reference_step(reference, it, monkeypatch)
        assert got.keys() == want.keys()
        for name in want:
            assert got[name] == pytest.approx(want[name], rel=RTOL, abs=ATOL), (it, name)
    for name, want in reference.gaussians.params.items():
        torch.testing.assert_close(fast.gaussians[name], want, atol=ATOL, rtol=RTOL, msg=name)
    torch.testing.assert_close(fast.motion.qr, reference.motion.qr, atol=ATOL, rtol=RTOL)
    torch.testing.assert_close(fast.motion.qd, reference.motion.qd, atol=ATOL, rtol=RTOL)
    # Both ways of rendering the part logits were taken where the views allow them.
    assert all(shared) if regions_on == "every view" else not all(shared), shared
    # The steps did train: a vacuous comparison of untouched tensors would also "agree".
    untouched = stage()
    assert not torch.equal(untouched.gaussians["logits"], fast.gaussians["logits"])
    assert not torch.equal(untouched.motion.qd, fast.motion.qd)
