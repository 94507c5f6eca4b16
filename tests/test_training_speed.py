"""What makes training cheaper, against its definition: the motion-only steps' held model
(pose per part by matrix products) against the per-Gaussian dual-quaternion pose of
gear.kinematics, the densification statistics, and the per-pixel Gaussian budget."""

import math

import numpy as np
import pytest
import torch

from gear.camera import Camera
from gear.config import make_config
from gear.kinematics import dq_normalize, pose_parts
from gear.pipeline.stage3.shared import HeldModel, held_key
from gear.splats import Densifier, Gaussians, gaussian_budget


def random_gaussians(n: int, parts: int, dtype: torch.dtype = torch.float32) -> Gaussians:
    gen = torch.Generator().manual_seed(3)
    g = Gaussians({name: torch.randn(shape, generator=gen) for name, shape in (
        ("means", (n, 3)), ("quats", (n, 4)), ("log_scales", (n, 3)), ("opacity", (n,)),
        ("colors", (n, 3)), ("logits", (n, parts)))})
    if dtype != torch.float32:  # Gaussians store float32; the parity check runs in float64
        g.params = {k: v.detach().to(dtype).requires_grad_(True) for k, v in g.params.items()}
    return g


def random_motion(parts: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Raw dual quaternions (the learnt parameters; PartMotion.motion normalises them)."""
    gen = torch.Generator().manual_seed(5)
    return (torch.randn(parts, 4, generator=gen, dtype=torch.float64).requires_grad_(True),
            torch.randn(parts, 4, generator=gen, dtype=torch.float64).requires_grad_(True))


def test_held_pose_matches_the_dual_quaternion_pose_and_its_gradients():
    g = random_gaussians(300, 4, torch.float64)
    held = HeldModel(g)
    raw = random_motion(4)
    qr, qd = dq_normalize(*raw)
    # Part 0, the static part, is the identity (as PartMotion.motion gives it).
    qr = torch.cat([torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64), qr[1:]])
    qd = torch.cat([torch.zeros(1, 4, dtype=torch.float64), qd[1:]])
    means, quats = held.pose(qr, qd)
    ids = g.part_ids()
    order = torch.argsort(ids, stable=True)
    # ... and its Gaussians come back as they are, bit for bit (what its static layers hold).
    static = held.counts[0]
    assert static > 0 and torch.equal(means[:static], g["means"].detach()[order][:static])
    assert torch.equal(quats[:static], g["quats"].detach()[order][:static])
    ref_means, ref_quats = pose_parts(g["means"].detach(), g["quats"].detach(), ids, qr, qd)
    ref_means, ref_quats = ref_means[order], ref_quats[order]
    # q and -q are one rotation: the blend may flip a part's sign, the per-part product never.
    sign = torch.sign((quats * ref_quats).sum(-1, keepdim=True)).detach()
    assert torch.allclose(means, ref_means, atol=1e-12)
    assert torch.allclose(quats, sign * ref_quats, atol=1e-12)
    # the gradient a loss on the posed model sends to the motion's parameters
    weights = torch.randn(means.shape, dtype=torch.float64), torch.randn(4, dtype=torch.float64)
    mine = torch.autograd.grad((means * weights[0]).sum() + ((quats * sign) @ weights[1]).sum(),
                               raw, retain_graph=True)
    ref = torch.autograd.grad(
        (ref_means * weights[0]).sum() + ((ref_quats * sign) @ weights[1]).sum(), raw)
    for a, b in zip(mine, ref, strict=True):
        assert torch.allclose(a, b, atol=1e-9)
    # the other arrays are the stored ones, detached, in the same order
    log_scales, opacity, rgb = held.splat_arrays()[2:]
    assert torch.equal(log_scales, g["log_scales"].detach()[order])
    assert torch.equal(opacity, g["opacity"].detach()[order])
    assert torch.equal(rgb, g.rgb().detach()[order]) and not rgb.requires_grad


def test_held_key_changes_with_every_edit_and_step():
    g = random_gaussians(50, 2)
    g.setup_optimizer({name: 0.1 for name in g.params})
    key = held_key(g)
    assert held_key(g) == key
    g["logits"].grad = torch.ones_like(g["logits"])
    g.optimizer.step()  # an E-step's update in place (the fused kernel bumps no version)
    assert held_key(g) != key
    key = held_key(g)
    g.optimizer.step()
    assert held_key(g) != key
    key = held_key(g)
    g.lower_opacity(torch.arange(len(g)) < 10, 0.01)  # an edit of the values in place
    assert held_key(g) != key
    key = held_key(g)
    g.keep(torch.ones(len(g), dtype=torch.bool))  # an edit that keeps every Gaussian
    assert held_key(g) != key


def test_densify_statistics_are_the_ndc_gradient_norm_of_visible_gaussians():
    gen = torch.Generator().manual_seed(1)
    n = 40
    g = random_gaussians(n, 2)
    angle = 0.3
    rot = np.array([[math.cos(angle), 0, math.sin(angle)], [0, 1, 0],
                    [-math.sin(angle), 0, math.cos(angle)]])
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = rot, [0.1, -0.2, 4.0]
    camera = Camera(world_to_cam=w2c, fx=50.0, fy=60.0, cx=16.0, cy=12.0, width=32, height=24)
    means = torch.randn(n, 3, generator=gen).requires_grad_(True)
    means.grad = torch.randn(n, 3, generator=gen)
    means.grad[::3] = 0  # not seen by the render
    with torch.no_grad():
        means[3] = math.inf  # culled by the render (zero gradient); its norm would be NaN
    densifier = Densifier(g)
    densifier.accumulate(means, camera, 1, 10)
    densifier.accumulate(means, camera, 9, 10)
    densifier.accumulate(means, camera, 10, 10)  # no densification left: nothing gathered
    # the definition, per Gaussian in float64
    for i in range(n):
        grad = means.grad[i].double().numpy()
        if not grad.any():
            assert densifier.grad_count[i] == 0 and densifier.grad_accum[i] == 0
            continue
        g_cam = rot @ grad
        z = (rot @ means[i].detach().double().numpy() + w2c[:3, 3])[2]
        du = g_cam[0] * z / camera.fx * camera.width / 2
        dv = g_cam[1] * z / camera.fy * camera.height / 2
        assert densifier.grad_count[i] == 2
        assert math.isclose(float(densifier.grad_accum[i]), 2 * math.hypot(du, dv),
                            rel_tol=1e-5)


def test_gaussian_budget_per_pixel_of_the_largest_view():
    small = Camera(world_to_cam=np.eye(4), fx=10.0, fy=10.0, cx=4.0, cy=3.0, width=8, height=6)
    large = Camera(world_to_cam=np.eye(4), fx=10.0, fy=10.0, cx=8.0, cy=6.0, width=16, height=12)
    assert gaussian_budget(make_config("full"), [small, large]) == 1_000_000  # no per-pixel cap
    assert gaussian_budget(make_config("fast"), [small, large]) == 8 * 16 * 12  # fast: 8 / px
    uncapped = make_config("fast", {"max_gaussians_per_pixel": None})
    assert gaussian_budget(uncapped, [small, large]) == 1_000_000
    capped = make_config("fast", {"max_gaussians_per_pixel": 2.5})
    assert gaussian_budget(capped, [small, large]) == int(2.5 * 16 * 12)
    both = make_config("quick", {"max_gaussians_per_pixel": 1000.0})
    assert gaussian_budget(both, [small]) == both.max_gaussians  # the lower cap wins
    with pytest.raises(ValueError, match="max_gaussians_per_pixel: must be > 0"):
        make_config("fast", {"max_gaussians_per_pixel": 0.0})


def test_densification_stops_at_the_budget():
    g = random_gaussians(20, 2)
    g.params["log_scales"] = torch.full((20, 3), -8.0).requires_grad_(True)  # all clone
    g.params["opacity"] = torch.full((20,), 3.0).requires_grad_(True)  # none pruned
    g.setup_optimizer({name: 0.1 for name in g.params})
    config = make_config("quick")
    densifier = Densifier(g, budget=26)
    densifier.grad_accum += 1.0  # every Gaussian far above the threshold
    densifier.grad_count += 1
    events = densifier.maintain(g, config.densify_from, config, 1.0, config.densify_until, True,
                                torch.Generator().manual_seed(0))
    assert events[0]["event"] == "densify" and events[0]["cloned"] == 6
    assert len(g) == 26
