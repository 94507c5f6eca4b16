"""The runner's checkpoints across stage boundaries: a run interrupted (Ctrl-C) inside stage 1,
and another inside stage 3 (both inside a densification interval, whose statistics the
checkpoint must carry), continued with `resume=True`, ends with the same joints, Gaussians and
part ids as the uninterrupted run. Rendered with the deterministic torch reference, where
continuing must reproduce the run exactly; each stage result's checkpoint form round-trips."""

from __future__ import annotations

import json
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import pytest
import torch

from gear.articulation import PartMotion
from gear.config import make_config
from gear.pipeline import runner as runner_mod
from gear.pipeline.stage1 import Stage1Result
from gear.pipeline.stage2 import Stage2Result
from gear.pipeline.stage3 import Stage3Result
from gear.splat_reference import rasterize_dense
from gear.splats import Gaussians, rendering
from gear.synth import generate
from gear.train import train

CONFIG = dict(stage1_iterations=12, stage3_iterations=12, em_interval=3, densify_from=4,
              densify_until=10, densify_interval=4, stage3_densify_until=8,
              joint_classify_iteration=6, classify_tune_steps=2, opacity_reset_interval=9,
              checkpoint_every=5, init_max_points=400, max_gaussians=800, num_parts=2,
              mesh_voxel=0.08, mesh_trunc=0.24)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return generate("fridge", tmp_path_factory.mktemp("scene"), res=16, views=4, test_views=1)


@pytest.fixture(autouse=True)
def torch_renderer(monkeypatch):
    monkeypatch.setattr(rendering, "rasterizer", lambda: rasterize_dense)


@contextmanager
def interrupted_at(stage: str, iteration: int) -> Iterator[None]:
    """Ctrl-C as the runner sees it: its flag goes up after `iteration` of `stage`."""
    run, flag = runner_mod.Runner.run, runner_mod._Interrupt

    def run_until(self, stage_obj, start: int, total: int) -> None:
        class Raised(flag):
            checks = start

            @property
            def requested(self) -> bool:
                Raised.checks += 1
                return Raised.checks == iteration

            @requested.setter
            def requested(self, _value: bool) -> None:
                pass

        runner_mod._Interrupt = Raised if stage_obj.name == stage else flag
        try:
            return run(self, stage_obj, start, total)
        finally:
            runner_mod._Interrupt = flag

    runner_mod.Runner.run = run_until
    try:
        yield
    finally:
        runner_mod.Runner.run = run


def outputs(out) -> tuple:
    joints = json.loads((out / "joints.json").read_text())
    return joints, np.load(out / "parts.npy"), (out / "gaussians_canonical.ply").read_bytes()


@pytest.mark.parametrize("stage,iteration", [("stage1", 7), ("stage3", 7)])
def test_interrupted_run_resumes_to_the_same_result(scene, tmp_path, stage, iteration):
    config = make_config("quick", CONFIG)
    train(scene, tmp_path / "straight", config, quiet=True)
    with interrupted_at(stage, iteration), pytest.raises(KeyboardInterrupt):
        train(scene, tmp_path / "resumed", config, quiet=True)
    saved = torch.load(tmp_path / "resumed" / "checkpoints" / "last.pt", weights_only=False)
    assert (saved["stage"], saved["iteration"]) == (stage, iteration)
    train(scene, tmp_path / "resumed", config, resume=True, quiet=True)
    straight, resumed = outputs(tmp_path / "straight"), outputs(tmp_path / "resumed")
    assert straight[0] == resumed[0]
    assert np.array_equal(straight[1], resumed[1])
    assert straight[2] == resumed[2]


def test_a_checkpoint_of_the_states_trained_one_by_one_resumes_to_the_same_result(scene, tmp_path):
    """A run that trained the two states' stage 1 one after the other checkpointed only the
    state in training ("stage1-start" here). Resumed, that state continues from its iteration
    and the other starts afresh beside it; as the states share nothing, the result is the
    uninterrupted run's."""
    config = make_config("quick", CONFIG)
    train(scene, tmp_path / "straight", config, quiet=True)
    with interrupted_at("stage1", 7), pytest.raises(KeyboardInterrupt):
        train(scene, tmp_path / "resumed", config, quiet=True)
    path = tmp_path / "resumed" / "checkpoints" / "last.pt"
    saved = torch.load(path, weights_only=False)
    assert saved["iterations"] == {"start": 7, "end": 7}
    saved.update(stage="stage1-start", current=saved["current"]["start"],
                 stage_state=saved["stage_state"]["start"])
    del saved["iterations"]
    torch.save(saved, path)
    train(scene, tmp_path / "resumed", config, resume=True, quiet=True)
    straight, resumed = outputs(tmp_path / "straight"), outputs(tmp_path / "resumed")
    assert straight[0] == resumed[0]
    assert np.array_equal(straight[1], resumed[1])
    assert straight[2] == resumed[2]


def test_stage_results_round_trip_through_their_checkpoint_form():
    g = Gaussians(dict(means=torch.randn(5, 3), quats=torch.randn(5, 4),
                       log_scales=torch.randn(5, 3), opacity=torch.randn(5),
                       colors=torch.randn(5, 3)))
    g.setup_optimizer(dict(means=0.1, quats=0.1, log_scales=0.1, opacity=0.1, colors=0.1))
    back = Stage1Result.from_checkpoint(Stage1Result({"start": g}).to_checkpoint())
    assert set(back.models) == {"start"}
    for name, value in g.params.items():
        assert torch.equal(back.models["start"][name], value.detach())
    assert back.models["start"].optimizer is not None
    coarse = Stage2Result("end", 2, torch.randn(5, 2), [[(np.eye(3), np.ones(3))]], 0.1, ["n"])
    again = Stage2Result.from_checkpoint(coarse.to_checkpoint())
    assert (again.canonical, again.target, again.num_parts) == ("end", "start", 2)
    assert torch.equal(again.logits, coarse.logits) and again.notes == ["n"]
    assert np.array_equal(again.motions[0][1], np.ones(3))


def test_stage3_result_round_trips_through_its_checkpoint_form():
    g = Gaussians(dict(means=torch.randn(6, 3), quats=torch.randn(6, 4),
                       log_scales=torch.randn(6, 3), opacity=torch.randn(6),
                       colors=torch.randn(6, 3), logits=torch.randn(6, 3)))
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    motion = PartMotion.from_rt([(turn, np.array([0.1, 0.0, 0.0])),
                                 (np.eye(3), np.array([0.0, 0.2, 0.0]))])
    motion.set_prismatic(2)
    refined = Stage3Result(g, motion, "end")
    back = Stage3Result.from_checkpoint(refined.to_checkpoint())
    assert back.canonical == "end" and back.motion.num_parts == 3
    for name, value in g.params.items():
        assert torch.equal(back.gaussians[name], value.detach()), name
    assert torch.equal(back.motion.prismatic, motion.prismatic)
    for got, want in zip(back.motion.motion(), motion.motion(), strict=True):
        assert torch.equal(got, want)
    assert back.joints() == refined.joints()
    assert [j["type"] for j in back.joints()] == ["revolute", "prismatic"]
