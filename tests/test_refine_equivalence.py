"""Stage 3's cost-saving formulation optimises exactly what the straightforward one does.

The reference below is the plain reading of the part supervision (docs/method.md): render the
canonical Gaussians with their colours and the K part logits as extra channels, and take the
logit channels of that image. Refine renders the logit channels alone (blending is per
channel, so the colours only cost time). Both run the same seeded E- and M-steps with the
deterministic torch renderer; losses and every trained tensor must agree to float rounding.
"""

import pytest
import torch

from gear.losses import region_pseudo_labels, sam_ce_loss
from gear.pipeline.stage3 import Refine
from gear.splat_reference import rasterize_dense
from gear.splats import rendering
from test_train import refine_stage

# float32 rounding of a differently shaped blend, carried through a few Adam steps (the
# differences seen are below 1e-7)
ATOL = 1e-6
RTOL = 1e-5


class ReferenceRefine(Refine):
    """Refine with the part supervision rendered the straightforward way (colour + logits)."""

    def segmentation_terms(self, logits: torch.Tensor) -> dict:
        c, g = self.config, self.gaussians
        neighbours = self.neighbours()
        # The consistency term as written: mean over every (Gaussian, neighbour) pair.
        diffs = [(logits - logits[nb]).norm(dim=1) for nb in neighbours.unbind(1)]
        terms = {"knn": c.lambda_knn * torch.stack(diffs, dim=1).mean()}
        view = self.pick(self.region_views)
        k = g.num_parts
        features = torch.cat([g.rgb().detach(), logits], dim=1)
        out = rendering.render(g, view.camera, torch.zeros(3 + k), features=features)
        logit_image = out.features[..., 3:]
        labels = region_pseudo_labels(
            torch.softmax(logit_image.detach(), dim=-1), view.regions,
            self.motion.prismatic, gamma=c.gamma_prism, min_conf=c.pseudo_min_conf,
            min_gap=c.pseudo_min_gap, min_area=c.pseudo_min_area,
        )
        terms["sam"] = c.lambda_sam * sam_ce_loss(logit_image, labels, view.alpha > 0.5,
                                                  static_weight=c.static_class_weight)
        return terms


def stage(reference: bool = False) -> Refine:
    """test_train's tiny Refine with turned, anisotropic Gaussians: on its isotropic,
    unrotated ones the rotation gradient is exactly zero, and Adam would turn the rounding
    noise left there into full learning-rate steps of either sign."""
    out = refine_stage()
    gen = torch.Generator().manual_seed(11)
    with torch.no_grad():
        g = out.gaussians
        g["quats"].copy_(torch.nn.functional.normalize(torch.randn(len(g), 4, generator=gen)))
        g["log_scales"].add_(0.4 * torch.randn(len(g), 3, generator=gen))
    if reference:
        out.__class__ = ReferenceRefine
    return out


@pytest.fixture
def torch_renderer(monkeypatch):
    # The GPU backward sums with atomics (run-to-run float reordering); the torch renderer is
    # deterministic, so any difference left is the formulation's.
    monkeypatch.setattr(rendering, "rasterizer", lambda: rasterize_dense)


def test_refine_steps_match_the_straightforward_formulation(torch_renderer):
    fast, reference = stage(), stage(reference=True)
    assert {"sam", "knn", "anchor"} <= set(fast.step(0))  # an E-step with every term
    reference.step(0)
    for it in range(1, 6):  # E, M, M, E, E (em_interval = 2)
        got, want = fast.step(it), reference.step(it)
        assert got.keys() == want.keys()
        for name in want:
            assert got[name] == pytest.approx(want[name], rel=RTOL, abs=ATOL), (it, name)
    for name, want in reference.gaussians.params.items():
        torch.testing.assert_close(fast.gaussians[name], want, atol=ATOL, rtol=RTOL, msg=name)
    torch.testing.assert_close(fast.motion.qr, reference.motion.qr, atol=ATOL, rtol=RTOL)
    torch.testing.assert_close(fast.motion.qd, reference.motion.qd, atol=ATOL, rtol=RTOL)
    # The steps did train: a vacuous comparison of untouched tensors would also "agree".
    untouched = stage()
    assert not torch.equal(untouched.gaussians["logits"], fast.gaussians["logits"])
    assert not torch.equal(untouched.motion.qd, fast.motion.qd)
