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
from gear.pipeline.common import TrainView, image_terms, in_turn
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
                           rgb: torch.Tensor | None, views: estep.AnchorViews):
    """estep.anchor_term (images) with its colours and the part logits in renders of their
    own: the colours over the background, the colours (no gradient) + logits over black."""
    c, g = state.config, state.gaussians
    own = views.own
    out = rendering.render(g, own.camera, bg, features=rgb, depth=own.depth is not None)
    term = sum(image_terms(out, own, bg, c).values())
    if views.regions is not own:
        return term, None
    return term, reference_logit_image(state, own)


def reference_logit_image(state: RefineState, view: TrainView) -> torch.Tensor:
    """The part logits rendered from `view` with the colours (no gradient) as the first
    channels, over black."""
    g = state.gaussians
    features = torch.cat([g.rgb().detach(), g["logits"]], dim=1)
    out = rendering.render(g, view.camera, torch.zeros(3 + g.num_parts), features=features)
    return out.features[..., 3:]


def reference_part_supervision(state: RefineState, view: TrainView,
                               logit_image: torch.Tensor | None) -> torch.Tensor:
    """estep.part_supervision with the logits rendered beside the colours when the anchor
    did not render them."""
    c = state.config
    if logit_image is None:  # the anchor's view has no regions: one that has them, rendered
        logit_image = reference_logit_image(state, view)
    labels = region_pseudo_labels(
        torch.softmax(logit_image.detach(), dim=-1), view.regions,
        state.motion.prismatic, gamma=c.gamma_prism, min_conf=c.pseudo_min_conf,
        min_gap=c.pseudo_min_gap, min_area=c.pseudo_min_area,
    )
    return sam_ce_loss(logit_image, labels, view.alpha > 0.5,
                       static_weight=c.static_class_weight)


def reference_knn_consistency(logits: torch.Tensor, neighbours: torch.Tensor) -> torch.Tensor:
    """The consistency term as written: mean over every (Gaussian, neighbour) pair."""
    diffs = [(logits - logits[nb]).norm(dim=1) for nb in neighbours.unbind(1)]
    return torch.stack(diffs, dim=1).mean()


def reference_step(stage: Refine, it: int, monkeypatch: pytest.MonkeyPatch) -> dict:
    """One step of `stage` with the reference canonical terms in place of the fast ones."""
    with monkeypatch.context() as patched:
        patched.setattr(estep, "anchor_term", reference_anchor_term)
        patched.setattr(estep, "part_supervision", reference_part_supervision)
        patched.setattr(estep, "fused_knn_consistency", reference_knn_consistency)
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
    part_supervision = estep.part_supervision

    def spy(state, view, logit_image):
        shared.append(logit_image is not None)
        return part_supervision(state, view, logit_image)

    monkeypatch.setattr(estep, "part_supervision", spy)
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


def test_the_halves_of_a_step_give_the_same_bits_beside_each_other_as_in_turn():
    """An E-step's target and anchor halves run on two threads (common.map_beside) and the
    anchor's gradients are added after the target's: the same bits as running them in turn,
    on the native executor (which gives the same bits on any thread)."""
    beside, in_order = stage(), stage()
    for it in range(6):  # E, E, M, M, E, E (em_interval = 2)
        got = beside.step(it)
        with in_turn():
            want = in_order.step(it)
        assert got == want, it
    for name, want in in_order.gaussians.params.items():
        assert torch.equal(beside.gaussians[name], want), name
    assert not torch.equal(stage().gaussians["logits"], beside.gaussians["logits"])
