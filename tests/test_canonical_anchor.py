"""What stage 3 holds the undeformed canonical model to (config `anchor`): the frozen stage-1
model, or the canonical state's own images. A stage-1 error is invisible to the first (the
model agrees with the frozen one) and is pulled back by the second. Rendered with the
deterministic torch reference on a tiny scene: a wall (part 0) and a plank in front (part 1)."""

import numpy as np
import pytest
import torch

from gear.articulation import PartMotion
from gear.config import make_config
from gear.pipeline.stage2 import Stage2Result
from gear.pipeline.stage3 import Refine
from gear.pipeline.stage3.estep import AnchorViews, anchor_term
from gear.pipeline.stage3.refine import refine_state, resumed_refine_state
from gear.splat_reference import rasterize_dense
from gear.splats import rendering
from stage3_scenes import grid_gaussians, plank, views_of, wall

STAGE1_ERROR = torch.tensor([0.06, 0.0, 0.0])  # how far stage 1 put the plank off


@pytest.fixture(autouse=True)
def torch_renderer(monkeypatch):
    monkeypatch.setattr(rendering, "rasterizer", lambda: rasterize_dense)


def stage_with_a_stage1_error(anchor: str) -> tuple[Refine, torch.Tensor]:
    """A stage-3 state whose frozen stage-1 model (and the model it starts from) has the
    plank shifted by STAGE1_ERROR, while the canonical images show it where it is."""
    truth = grid_gaussians([(wall(), 0), (plank(-0.3, 0.0), 1)])
    images = views_of(truth, PartMotion(truth.num_parts))
    plank_ids = truth.part_ids() == 1
    read = truth.clone()
    read.params["means"] = read["means"] + plank_ids[:, None] * STAGE1_ERROR
    cfg = make_config("quick", dict(anchor=anchor, stage3_densify_until=0))
    state = Refine(read.clone(), PartMotion(truth.num_parts), read, images, images, cfg, seed=0)
    return state, plank_ids


@pytest.mark.parametrize("view_index", [0, 1, 2])
def test_a_stage1_error_costs_nothing_against_the_frozen_model(view_index):
    state, _ = stage_with_a_stage1_error("frozen")
    view = state.target_views[view_index]
    term, _ = anchor_term(state, view_index, view, torch.zeros(3), state.gaussians.rgb(),
                          AnchorViews.draw(state))
    assert term.item() < 1e-5


def test_the_canonical_images_pull_a_stage1_error_back():
    state, plank_ids = stage_with_a_stage1_error("images")
    g = state.gaussians
    pulls = []
    for _ in range(3):  # each call draws one canonical image
        g.optimizer.zero_grad(set_to_none=True)
        view = state.target_views[0]
        term, _ = anchor_term(state, 0, view, torch.zeros(3), g.rgb(), AnchorViews.draw(state))
        assert term.item() > 1e-3  # the images see the plank elsewhere
        term.backward()
        grad = g["means"].grad[plank_ids].sum(0)
        assert torch.isfinite(g["means"].grad).all()
        # a gradient step moves the plank against its error
        pulls.append(float(grad @ STAGE1_ERROR) / float(np.linalg.norm(STAGE1_ERROR)))
    assert min(pulls) > 0, pulls


@pytest.mark.parametrize("anchor", ["frozen", "images"])
def test_only_the_frozen_anchor_keeps_and_checkpoints_a_copy_of_stage_1(anchor):
    """The default anchor costs no copy of the stage-1 model, in memory or in checkpoints."""
    truth = grid_gaussians([(wall(), 0), (plank(-0.3, 0.0), 1)])
    views = views_of(truth, PartMotion(truth.num_parts))
    coarse = Stage2Result("start", 2, truth["logits"], [[(np.eye(3), np.zeros(3))]], 0.05)
    cfg = make_config("quick", dict(anchor=anchor))
    g = truth.clone()
    stage = refine_state(g, truth, coarse, {"start": views, "end": views}, cfg)
    saved = stage.checkpoint()
    if anchor == "frozen":
        assert stage.frozen is not None and stage.frozen is not truth
        assert saved["frozen"] is not None
    else:
        assert stage.frozen is None and saved["frozen"] is None
    resumed = resumed_refine_state(saved, coarse, {"start": views, "end": views}, cfg)
    assert (resumed.frozen is None) == (anchor == "images")
    index, view, bg = resumed.target_view()
    views = AnchorViews.draw(resumed)
    assert torch.isfinite(anchor_term(resumed, index, view, bg, resumed.gaussians.rgb(), views)[0])


def test_an_unknown_anchor_is_refused_by_name():
    with pytest.raises(ValueError, match="anchor"):
        make_config("quick", dict(anchor="stage1"))
