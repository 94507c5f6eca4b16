"""View-dependent colour in the pipeline (gear.splats.sh): degree 0 changes nothing, the
coefficients follow every edit of the Gaussians, posed Gaussians are coloured in their
canonical frame (with the pose's gradient), and a whole run trains at degree 3 without NaN."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from gear import checkpoint
from gear.camera import Camera
from gear.config import make_config
from gear.kinematics import pose_parts, quat_from_axis_angle, quat_mul, quat_rotate
from gear.pipeline.stage3.shared import HeldModel
from gear.sh import coefficient_count
from gear.splats import Densifier, Gaussians, render
from gear.splats.sh import SH_PARAM, add_sh, view_rgb
from gear.twin import read_ply_vertices


def gaussians(n: int = 50, seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    return Gaussians(dict(
        means=0.3 * torch.randn(n, 3, generator=g),
        quats=torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=1),
        log_scales=torch.full((n, 3), -2.5),
        opacity=torch.randn(n, generator=g),
        colors=torch.randn(n, 3, generator=g),
    ))


def camera(eye) -> Camera:
    return Camera.look_at(np.asarray(eye, dtype=float), np.zeros(3), np.array([0, 0, 1.0]),
                          0.9, 16, 16)


def with_random_sh(g: Gaussians, degree: int, seed: int = 1) -> Gaussians:
    add_sh(g, degree, 1e-3)
    shape = g[SH_PARAM].shape
    with torch.no_grad():
        g[SH_PARAM].copy_(0.3 * torch.randn(shape, generator=torch.Generator().manual_seed(seed)))
    return g


def test_sh_degree_is_validated_like_the_other_fields():
    assert make_config("quick").sh_degree == 0
    for bad, message in ((4, "sh_degree: must be <= 3"), (-1, "sh_degree: must be >= 0"),
                         (1.0, "sh_degree: expected an int"), ("3", "sh_degree: expected an int")):
        with pytest.raises(ValueError, match=message):
            make_config("quick", {"sh_degree": bad})
    with pytest.raises(ValueError, match="lr_sh: must be > 0"):
        make_config("quick", {"lr_sh": 0.0})


def test_degree_zero_is_the_plain_colour_and_zero_coefficients_change_nothing():
    g = gaussians()
    add_sh(g, 0, 1e-3)
    assert SH_PARAM not in g.params
    rgb = g.rgb()
    assert view_rgb(g, rgb, camera([2, 0, 0.5]), g["means"], g["quats"], g["quats"]) is rgb
    add_sh(g, 3, 1e-3)
    assert g[SH_PARAM].shape == (len(g), coefficient_count(3) - 1, 3)
    assert not g[SH_PARAM].any()
    got = view_rgb(g, rgb, camera([2, 0, 0.5]), g["means"], g["quats"], g["quats"])
    torch.testing.assert_close(got, rgb, rtol=0, atol=1e-6)


@pytest.mark.parametrize("degree", [1, 3])
def test_a_posed_gaussian_keeps_its_colour_when_the_whole_scene_turns(degree):
    # Turning the Gaussians (as a part motion) and the camera by the same rotation leaves every
    # Gaussian seen from the same canonical direction.
    g = with_random_sh(gaussians(), degree)
    q = quat_from_axis_angle(torch.tensor([0.3, -0.5, 0.8]) / np.sqrt(0.98), torch.tensor(1.1))
    eye = np.array([2.0, 0.5, 0.7])
    moved_eye = quat_rotate(q.double(), torch.as_tensor(eye)).numpy()
    means, quats = g["means"].detach(), g["quats"].detach()
    posed = (quat_rotate(q, means), quat_mul(q.expand(len(g), 4), quats))
    rgb = g.rgb().detach()
    still = view_rgb(g, rgb, camera(eye), means, quats, quats)
    turned = view_rgb(g, rgb, camera(moved_eye), *posed, quats)
    torch.testing.assert_close(turned, still, rtol=0, atol=1e-5)
    plain = view_rgb(g, rgb, camera(moved_eye), *posed, posed[1])  # the pose ignored
    assert (plain - still).abs().max() > 1e-2


def test_colour_gradients_reach_the_pose_and_the_coefficients():
    g = with_random_sh(gaussians(), 3)
    q = quat_from_axis_angle(torch.tensor([0.0, 0.0, 1.0]), torch.tensor(0.4))
    q = q.clone().requires_grad_(True)
    means = g["means"].detach().clone().requires_grad_(True)
    posed_quats = quat_mul(q.expand(len(g), 4), g["quats"].detach())
    rgb = view_rgb(g, g.rgb(), camera([2, 0, 0.5]), means, posed_quats, g["quats"])
    rgb.square().sum().backward()
    for grad in (q.grad, means.grad, g[SH_PARAM].grad, g["colors"].grad):
        assert grad is not None and torch.isfinite(grad).all() and grad.abs().sum() > 0


def test_coefficients_follow_densification_and_checkpoints():
    g = with_random_sh(gaussians(n=30), 2)
    g.setup_optimizer(dict(means=1e-3, quats=1e-3, log_scales=1e-3, opacity=1e-2, colors=1e-2,
                           sh=1e-3))
    densifier = Densifier(g)
    densifier.grad_accum[:10] = 1.0  # ten hot Gaussians: cloned or split
    densifier.grad_count[:10] = 1.0
    before = g[SH_PARAM].detach().clone()
    densifier.densify_and_prune(g, 0.5, 1.0, 0.01, 0.0, None, 1000, torch.Generator())
    assert g[SH_PARAM].shape == (len(g), coefficient_count(2) - 1, 3) and len(g) > 30
    # Survivors keep their coefficients, in order; copies carry their parent's.
    kept = g[SH_PARAM].detach()
    assert all(any(torch.equal(row, old) for old in before) for row in kept)
    restored = checkpoint.gaussians_from_state(checkpoint.gaussians_state(g))
    assert torch.equal(restored[SH_PARAM], g[SH_PARAM])
    assert any(group["name"] == SH_PARAM for group in restored.optimizer.param_groups)


@pytest.mark.skipif(not hasattr(__import__("gear")._core, "rasterize_forward"),
                    reason="needs the rasterizer in gear._core")
def test_a_run_at_degree_three_trains_without_nan(tmp_path):
    from gear.synth import generate
    from gear.train import train

    scene = generate("fridge", tmp_path / "scene", res=32, views=6, test_views=1, seed=0,
                     effects="specular")
    config = make_config("quick", dict(
        sh_degree=3, lr_sh=1e-2, stage1_iterations=60, stage3_iterations=40, densify_from=10,
        densify_interval=10, densify_until=50, stage3_densify_until=30, em_interval=10,
        joint_classify_iteration=20, em_refine_joint_iterations=10, mesh_voxel=0.04,
        mesh_trunc=0.16))
    out = tmp_path / "out"
    train(scene, out, config, quiet=True)
    log = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    losses = [v for r in log for k, v in r.items() if k in ("rgb", "loss")
              and isinstance(v, float)]
    assert losses and all(np.isfinite(losses))
    vertices = read_ply_vertices(out / "gaussians_canonical.ply")
    rest = np.stack([vertices[f"f_rest_{i}"] for i in range(3 * 15)], axis=1)
    assert np.isfinite(rest).all() and np.abs(rest).max() > 0  # the coefficients learned


def test_the_motion_only_steps_held_model_keeps_the_view_dependent_colour():
    # The M-step and joint scoring draw a detached copy sorted by part (HeldModel): it must
    # render what the full model renders at the same hard-assignment pose, SH included.
    g = with_random_sh(gaussians(200), 3)
    g.add_param("logits", torch.randn(len(g), 2, generator=torch.Generator().manual_seed(4)), 1e-3)
    qr = torch.nn.functional.normalize(torch.tensor([[1.0, 0, 0, 0], [0.9, 0.1, -0.3, 0.2]]), dim=1)
    qd = torch.zeros(2, 4)
    held = HeldModel(g)
    cam = camera([2.0, 0.4, 0.6])
    mine = render(held, cam, pose=held.pose(qr, qd))
    posed = pose_parts(g["means"].detach(), g["quats"].detach(), g.part_ids(), qr, qd)
    ref = render(g, cam, pose=posed, detach=True)
    torch.testing.assert_close(mine.features, ref.features, rtol=0, atol=2e-5)
    plain = render(g, cam, pose=posed, features=g.rgb().detach())  # SH ignored: differs
    assert (plain.features - ref.features).abs().max() > 1e-2
