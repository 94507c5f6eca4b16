"""Training loop tests on tiny scenes (the dense torch renderer is enough for these), plus the
end-to-end quick run on a built-in fridge, which needs the GPU rasterizer."""

import json

import numpy as np
import pytest
import torch

from gear import _core
from gear.camera import Camera
from gear.config import make_config
from gear.data import View
from gear.pipeline.common import NonFiniteLoss, TrainView
from gear.pipeline.stage1 import ReconstructState
from gear.pipeline.stage3.shared import phase_at
from gear.splat_reference import rasterize_dense
from gear.splats import Gaussians

RES = 16


def tiny_views(n_views: int = 4, seed: int = 0) -> list[View]:
    """A small coloured blob of Gaussians seen from a ring of cameras (z up)."""
    g = torch.Generator().manual_seed(seed)
    n = 40
    means = 0.25 * torch.randn(n, 3, generator=g)
    colours = torch.rand(n, 3, generator=g)
    views = []
    for i in range(n_views):
        a = 2 * np.pi * i / n_views
        eye = np.array([2 * np.cos(a), 2 * np.sin(a), 0.6])
        cam = Camera.look_at(eye, np.zeros(3), np.array([0, 0, 1.0]), 0.9, RES, RES)
        out = rasterize_dense(means, torch.tensor([1.0, 0, 0, 0]).repeat(n, 1),
                              torch.full((n, 3), -2.5), torch.full((n,), 3.0), colours, cam,
                              depth=True)
        alpha = out.alpha.numpy()
        rgb = out.features.numpy() / np.maximum(alpha, 1e-6)[..., None]
        depth = np.where(alpha > 0.5, out.depth.numpy() / np.maximum(alpha, 1e-6), 0.0)
        views.append(View(f"start/train/{i:04d}", cam, np.clip(rgb, 0, 1).astype(np.float32),
                          alpha.astype(np.float32), depth.astype(np.float32)))
    return views


def start_gaussians(seed: int = 1) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    n = 60
    return Gaussians(dict(
        means=0.3 * torch.randn(n, 3, generator=g),
        quats=torch.tensor([1.0, 0, 0, 0]).repeat(n, 1),
        log_scales=torch.full((n, 3), -2.5),
        opacity=torch.zeros(n),
        colors=torch.zeros(n, 3),
    ))


def tiny_config(**kw):
    base = dict(stage1_iterations=8, densify_from=2, densify_interval=3, densify_until=7,
                opacity_reset_interval=5, lr_means=1e-2)
    return make_config("quick", {**base, **kw})


def params_of(stage):
    return {k: v.detach().clone() for k, v in stage.gaussians.params.items()}


def test_phase_schedules():
    em = [phase_at("em", i, 2, 0) for i in range(6)]
    assert em == ["E", "E", "M", "M", "E", "E"]
    assert {phase_at("joint", i, 2, 0) for i in range(6)} == {"J"}
    refine = [phase_at("em-refine", i, 2, 3) for i in range(7)]
    assert refine == ["J", "J", "J", "E", "E", "M", "M"]


def test_stage1_reduces_the_photometric_loss():
    views = [TrainView.from_view(v) for v in tiny_views()]
    config = tiny_config(densify_from=1000, opacity_reset_interval=1000)
    stage = ReconstructState(start_gaussians(), views, config, seed=0, state="start")
    first = stage.step(0)["rgb"]
    for i in range(1, 22):
        stage.step(i)
    last = np.mean([stage.step(i)["rgb"] for i in range(22, 25)])
    assert last < 0.8 * first


def test_resumed_stage_reproduces_the_uninterrupted_run(monkeypatch):
    from gear import checkpoint
    from gear.splat_reference import rasterize_dense
    from gear.splats import rendering

    # The GPU backward sums with atomics, so two identical runs differ by float reordering,
    # which a few optimizer steps amplify past any fixed tolerance. This test is about the
    # checkpoint bookkeeping (parameters, Adam moments, RNG state), so it renders with the
    # deterministic torch reference, where resuming must reproduce the run exactly.
    monkeypatch.setattr(rendering, "rasterizer", lambda: rasterize_dense)

    views = [TrainView.from_view(v) for v in tiny_views()]
    config = tiny_config()
    straight = ReconstructState(start_gaussians(), views, config, seed=3, state="start")
    for i in range(8):
        straight.step(i)
    first = ReconstructState(start_gaussians(), views, config, seed=3, state="start")
    for i in range(4):
        first.step(i)
    saved = (checkpoint.gaussians_state(first.gaussians), first.state_dict())
    torch.save(saved, "/dev/null")  # the payload must be serialisable
    g = checkpoint.gaussians_from_state(saved[0])
    resumed = ReconstructState(g, views, config, seed=99, state="start")
    resumed.load_state_dict(saved[1])
    for i in range(4, 8):
        resumed.step(i)
    a, b = params_of(straight), params_of(resumed)
    assert a.keys() == b.keys()
    for name in a:
        assert a[name].shape == b[name].shape
        assert torch.allclose(a[name], b[name], rtol=0, atol=1e-7), name


def test_non_finite_loss_names_stage_iteration_and_term():
    views = tiny_views()
    views[0].rgb[:] = np.nan
    tv = [TrainView.from_view(v) for v in views[:1]]
    stage = ReconstructState(start_gaussians(), tv, tiny_config(), seed=0, state="start")
    before = params_of(stage)
    with pytest.raises(NonFiniteLoss, match=r"stage1-start at iteration 0 \(term 'rgb'\)"):
        stage.step(0)
    after = params_of(stage)
    assert all(torch.equal(before[k], after[k]) for k in before)  # no update was applied


GPU_RASTERIZER = hasattr(_core, "rasterize_forward")


@pytest.mark.skipif(not GPU_RASTERIZER, reason="needs the GPU rasterizer in gear._core")
def test_quick_profile_recovers_the_fridge_door_axis(tmp_path):
    from gear.data import load_scene
    from gear.metrics import match_parts
    from gear.synth import generate
    from gear.train import train

    scene = generate("fridge", tmp_path / "scene", res=64, views=16, test_views=2, seed=0)
    out = tmp_path / "out"
    result = train(scene, out, make_config("quick"), quiet=True)
    gt = load_scene(scene, splits=("train",)).gt
    matching = match_parts(result.joints, gt.joints)
    assert len(matching.pairs) == 1 and not matching.type_mismatches
    assert matching.errors[0]["axis_ang"] < 5.0
    saved = json.loads((out / "joints.json").read_text())
    assert saved["joints"] == json.loads(json.dumps(result.joints))
    for name in ("gaussians_canonical.ply", "parts.npy", "config.json", "log.jsonl",
                 "meshes/start/whole.ply", "meshes/end/part_0.ply", "parts/end/test/0001.png",
                 "renders/start/test/0000.png"):
        assert (out / name).exists(), name


def test_cli_stops_on_an_invalid_scene_with_its_problems(tmp_path, capsys):
    from gear.cli import main

    (tmp_path / "scene").mkdir()
    code = main(["train", str(tmp_path / "scene"), "--out", str(tmp_path / "out"), "--quiet"])
    assert code == 1
    err = capsys.readouterr().err
    assert "invalid scene" in err and "transforms_train_start.json" in err
    assert not (tmp_path / "out" / "checkpoints").exists()


def refine_stage(**config):
    from gear.articulation import PartMotion
    from gear.pipeline.stage3 import Refine

    views = tiny_views()
    for v in views:  # one region per view: the object
        v.regions = (v.alpha > 0.5).astype(np.int32)
    tv = [TrainView.from_view(v) for v in views]
    g = start_gaussians()
    g.add_param("logits", 0.1 * torch.randn(len(g), 2, generator=torch.Generator().manual_seed(5)),
                lr=0.05)
    angle = np.deg2rad(4.0)  # a small hinge: below ε = 10°
    rot = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0],
                    [0, 0, 1]])
    motion = PartMotion.from_rt([(rot, np.array([0.01, 0.0, 0.0]))])
    base = dict(em_interval=2, stage3_densify_until=0, joint_classify_iteration=10**6,
                pseudo_min_area=1)
    return Refine(g, motion, g.clone(), tv, tv, tiny_config(**{**base, **config}), seed=0)


def test_e_steps_train_gaussians_not_motion_and_m_steps_only_the_motion():
    stage = refine_stage()
    motion = stage.motion
    qr, qd = motion.qr.detach().clone(), motion.qd.detach().clone()
    before = params_of(stage)
    terms = [stage.step(0), stage.step(1)]  # E
    assert {"sam", "knn", "anchor"} <= set(terms[0])
    assert torch.equal(motion.qr.detach(), qr) and torch.equal(motion.qd.detach(), qd)
    after_e = params_of(stage)
    for name in ("logits", "means", "colors"):
        assert not torch.equal(after_e[name], before[name]), name
    terms = [stage.step(2), stage.step(3)]  # M
    assert not {"sam", "knn", "anchor"} & set(terms[0])
    after_m = params_of(stage)
    for name in after_e:  # the Gaussians are held: the motion alone explains the target
        assert torch.equal(after_m[name], after_e[name]), name
    assert not torch.equal(motion.qd.detach(), qd)
    assert not torch.equal(motion.qr.detach(), qr)


def test_joint_classification_makes_a_small_hinge_prismatic():
    from gear.pipeline.stage3.joint_types import classify

    stage = refine_stage(resolve_ambiguous_joints=False)
    classify(stage)
    assert bool(stage.motion.prismatic[1])
    qr, _ = stage.motion.motion()
    assert torch.allclose(qr[1], torch.tensor([1.0, 0.0, 0.0, 0.0]))
    # the [beyond] rule scores the readings on the target views and keeps a valid one
    stage = refine_stage(resolve_ambiguous_joints=True)
    classify(stage)
    assert stage.events[-1]["event"] == "joint_classification"
    assert torch.isfinite(torch.cat(stage.motion.motion())).all()


def test_knn_lists_follow_a_prune_and_densify_that_keeps_the_count():
    from gear.geometry import nearest_neighbours

    stage = refine_stage()
    g = stage.gaussians
    before = stage.neighbours().clone()
    assert stage.neighbours() is stage.neighbours()  # reused while the set is unchanged
    # Prune Gaussian 0 and add a far-away one: same count, different set.
    keep = torch.ones(len(g), dtype=torch.bool)
    keep[0] = False
    g.keep(keep)
    extra = {name: t.detach()[:1].clone() for name, t in g.params.items()}
    extra["means"] = torch.tensor([[5.0, 5.0, 5.0]])
    g.append(extra)
    assert len(g) == len(before)
    expected = torch.as_tensor(nearest_neighbours(g["means"].detach().numpy(),
                                                  stage.config.knn_neighbors))
    assert not torch.equal(expected, before)
    assert torch.equal(stage.neighbours(), expected)


@pytest.mark.skipif(not GPU_RASTERIZER, reason="needs the GPU rasterizer in gear._core")
def test_identical_states_give_one_static_part_and_no_joint(tmp_path):
    """The train.py branch for a scene without motion: stage 2 finds one part, the run says
    so, skips stage 3 and writes the canonical stage-1 model as one static part."""
    import dataclasses

    from gear.data import load_scene
    from gear.data.write import write_scene
    from gear.synth import generate
    from gear.train import train

    rendered = load_scene(generate("fridge", tmp_path / "fridge", res=32, views=4, test_views=1))
    # The start state's images (same cameras) serve as both states.
    same = {state: {split: [dataclasses.replace(v, name=v.name.replace("start", state, 1))
                            for v in views] for split, views in rendered.views["start"].items()}
            for state in ("start", "end")}
    scene = write_scene(tmp_path / "scene", same)
    out = tmp_path / "out"
    # Centres frozen in stage 1: both models stay the same depth back-projection, so stage 2
    # sees the identical states (a few free iterations add centre noise that the fine voxel
    # grid of K estimation may read as a small moving part).
    config = make_config("quick", dict(stage1_iterations=2, lr_means=1e-7, lr_means_final=1e-8,
                                       mesh_voxel=0.04, mesh_trunc=0.16))
    result = train(scene, out, config, quiet=True)
    assert result.joints == []
    assert json.loads((out / "joints.json").read_text())["joints"] == []
    parts = np.load(out / "parts.npy")
    assert len(parts) > 0 and not parts.any()
    log = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert any("no motion detected" in r.get("message", "") for r in log)
    assert not any(r.get("stage") == "stage3" for r in log)  # stage 3 never ran
    assert (out / "meshes/end/static.ply").exists()
    assert not list((out / "meshes/end").glob("part_*.ply"))


@pytest.mark.parametrize("views", [1, 3])
def test_m_step_averages_the_configured_number_of_target_views(monkeypatch, views):
    import copy

    import torch.nn.functional as F

    from gear.kinematics import deform
    from gear.pipeline import common
    from gear.pipeline.stage3 import shared
    from gear.splats.rendering import rasterizer

    stage = refine_stage(m_step_views=views)
    cameras = []
    render = shared.render

    def counting_render(*args, **kwargs):
        cameras.append(args[1])
        return render(*args, **kwargs)

    monkeypatch.setattr(shared, "render", counting_render)
    rng_state, motion = stage.generator.get_state(), copy.deepcopy(stage.motion)
    terms = stage.step(2)  # an M-step (em_interval 2, E first)
    assert len(cameras) == views
    # Reference: the same draws (view index, then background, per view), the hard-assigned
    # model moved by the motion before the step, the image terms averaged over the views.
    g, replay = stage.gaussians, torch.Generator().manual_seed(0)
    replay.set_state(rng_state)
    expected = {"rgb": 0.0, "depth": 0.0}
    with torch.no_grad():
        qr, qd = motion.motion()
        weights = F.one_hot(g.part_ids(), g.num_parts).float()
        means, quats = deform(g["means"], g["quats"], weights, qr, qd)
        drawn = []
        for _ in range(views):
            view = stage.target_views[int(torch.randint(len(stage.target_views), (1,),
                                                        generator=replay))]
            drawn.append(view.camera)
            bg = torch.rand(3, generator=replay)
            out = rasterizer()(means, quats, g["log_scales"], g["opacity"], g.rgb(),
                               view.camera, background=bg, depth=True)
            for name, value in common.image_terms(out, view, bg, stage.config).items():
                expected[name] += float(value) / views
    # The views render beside each other: the drawn cameras, in whatever order they ran.
    assert sorted(map(id, cameras)) == sorted(map(id, drawn))
    assert terms.keys() == expected.keys()
    for name in terms:
        assert terms[name] == pytest.approx(expected[name], rel=1e-5, abs=1e-7), name
