import numpy as np
import pytest
import torch

from gear.camera import Camera
from gear.data import View
from gear.kinematics import quat_normalize, quat_to_matrix
from gear.outputs import write_ply
from gear.splats import Densifier, Gaussians
from gear.splats.init import points_from_masks, scene_extent
from gear.splats.strategy import small_part_mask

LRS = dict(means=0.01, quats=0.01, log_scales=0.01, opacity=0.01, colors=0.01, logits=0.01)


def make_gaussians(n: int = 6, parts: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(0)
    params = dict(
        means=torch.randn(n, 3, generator=g),
        quats=torch.tensor([1.0, 0, 0, 0]).repeat(n, 1),
        log_scales=torch.full((n, 3), -3.0),
        opacity=torch.zeros(n),
        colors=torch.zeros(n, 3),
    )
    if parts:
        params["logits"] = torch.zeros(n, parts)
    return Gaussians(params)


def step_with_row_gradients(gs: Gaussians) -> None:
    """One Adam step where row i of every parameter gets gradient i+1: moments identify rows."""
    gs.optimizer.zero_grad()
    for t in gs.params.values():
        rows = torch.arange(1, len(t) + 1, dtype=torch.float32)
        t.grad = rows.reshape(-1, *([1] * (t.dim() - 1))).expand_as(t).clone()
    gs.optimizer.step()


def moments(gs: Gaussians, name: str) -> torch.Tensor:
    return gs.optimizer.state[gs.params[name]]["exp_avg"]


def test_prune_keeps_adam_moments_aligned():
    gs = make_gaussians(6, parts=2)
    gs.setup_optimizer(LRS)
    step_with_row_gradients(gs)
    before = {n: moments(gs, n).clone() for n in gs.params}
    means_before = gs["means"].detach().clone()
    keep = torch.tensor([True, False, True, True, False, True])
    generation = gs.generation
    gs.keep(keep)
    assert len(gs) == 4
    assert gs.generation == generation + 1  # the set changed: KNN caches must rebuild
    assert torch.equal(gs["means"].detach(), means_before[keep])
    for name in gs.params:
        assert torch.equal(moments(gs, name), before[name][keep]), name
        assert gs.optimizer.param_groups[[g["name"] for g in gs.optimizer.param_groups].index(
            name)]["params"][0] is gs.params[name]
    step_with_row_gradients(gs)  # shapes still agree with the optimizer


def test_append_gives_new_gaussians_zero_moments():
    gs = make_gaussians(3)
    gs.setup_optimizer(LRS)
    step_with_row_gradients(gs)
    old = moments(gs, "opacity").clone()
    extra = {n: t.detach()[:2].clone() for n, t in gs.params.items()}
    generation = gs.generation
    gs.append(extra)
    assert len(gs) == 5
    assert gs.generation == generation + 1
    assert torch.equal(moments(gs, "opacity")[:3], old)
    assert torch.equal(moments(gs, "opacity")[3:], torch.zeros(2))
    with pytest.raises(ValueError, match="append"):
        gs.append({"means": torch.zeros(1, 3)})


def test_densify_clones_small_splits_large_and_prunes_transparent():
    gs = make_gaussians(4)
    gs.setup_optimizer(LRS)
    with torch.no_grad():
        gs["log_scales"][1] = np.log(0.5)  # large: split
        gs["opacity"][3] = -10.0  # transparent: pruned
    strategy = Densifier(gs)
    strategy.grad_accum = torch.tensor([1e-3, 1e-3, 0.0, 0.0])
    strategy.grad_count = torch.ones(4)
    info = strategy.densify_and_prune(gs, 2e-4, extent=10.0, percent_dense=0.01, min_opacity=0.005,
                                max_scale=None, max_gaussians=100,
                                generator=torch.Generator().manual_seed(0))
    assert (info["cloned"], info["split"]) == (1, 1)
    # 4 + 1 clone + 2 children - split parent - transparent one
    assert len(gs) == 5
    scales = torch.exp(gs["log_scales"].detach()).max(dim=1).values
    assert int((scales < 0.5 / 1.5).sum() - (scales < 0.1).sum()) == 2  # children shrank by 1.6
    assert len(strategy.grad_accum) == len(gs)
    step_with_row_gradients(gs)


def test_densify_respects_the_gaussian_budget():
    gs = make_gaussians(4)
    gs.setup_optimizer(LRS)
    strategy = Densifier(gs)
    strategy.grad_accum = torch.tensor([1e-3, 3e-3, 2e-3, 1e-3])
    strategy.grad_count = torch.ones(4)
    info = strategy.densify_and_prune(gs, 2e-4, 1.0, 0.01, 0.005, None, max_gaussians=6,
                                generator=torch.Generator().manual_seed(0))
    # all four want to split (2 new each); the budget of 2 takes the strongest one only
    assert (info["split"], info["cloned"]) == (1, 0)
    assert len(gs) == 5


def test_opacity_reset_protects_small_movable_parts():
    gs = make_gaussians(6, parts=3)
    with torch.no_grad():
        gs["opacity"][:] = 3.0
        gs["logits"][:] = torch.tensor([5.0, 0.0, 0.0])
        gs["logits"][4] = torch.tensor([0.0, 5.0, 0.0])  # part 1 has one Gaussian: small
    gs.setup_optimizer(LRS)
    step_with_row_gradients(gs)
    before = gs["opacity"].detach().clone()
    protect = small_part_mask(gs, threshold=2)
    assert protect.tolist() == [False, False, False, False, True, False]
    n = Densifier(gs).reset_opacity(gs, protect)
    assert n == 5
    o = torch.sigmoid(gs["opacity"].detach())
    assert torch.equal(gs["opacity"].detach()[protect], before[protect])
    assert torch.all(o[~protect] <= 0.01 + 1e-6)
    state = gs.optimizer.state[gs["opacity"]]
    assert torch.all(state["exp_avg"][~protect] == 0) and torch.all(state["exp_avg"][protect] != 0)


def test_quat_to_matrix_is_a_rotation():
    q = torch.randn(5, 4, generator=torch.Generator().manual_seed(3))
    r = quat_to_matrix(quat_normalize(q))
    assert torch.allclose(r @ r.transpose(1, 2), torch.eye(3).expand(5, 3, 3), atol=1e-5)
    assert torch.allclose(torch.linalg.det(r), torch.ones(5), atol=1e-5)


def _sphere_views(radius: float = 0.3, res: int = 24) -> list[View]:
    views = []
    for i in range(6):
        a = 2 * np.pi * i / 6
        eye = np.array([2 * np.cos(a), 0.5 * np.sin(3 * a), 2 * np.sin(a)])  # y is up here
        cam = Camera.look_at(eye, np.zeros(3), np.array([0, 1.0, 0]), 0.8, res, res)
        rays_centre = cam.project(np.zeros((1, 3)))[0][0]
        v, u = np.mgrid[0:res, 0:res] + 0.5
        dist = np.hypot(u - rays_centre[0], v - rays_centre[1])
        r_pix = cam.fx * radius / np.linalg.norm(eye)
        alpha = (dist < r_pix).astype(np.float32)
        views.append(View(f"start/train/{i:04d}", cam, np.full((res, res, 3), 0.5, np.float32),
                          alpha))
    return views


def test_visual_hull_init_lies_inside_the_object():
    views = _sphere_views()
    pts, cols = points_from_masks(views, 20_000, np.random.default_rng(0))
    assert len(pts) > 50
    assert np.linalg.norm(pts, axis=1).max() < 0.3 * 1.3  # hull of 6 views is a bit larger
    assert np.allclose(cols, 0.5)
    assert scene_extent([v.camera for v in views]) > 0


def test_ply_has_the_3dgs_layout_and_part_ids(tmp_path):
    gs = make_gaussians(5, parts=3)
    with torch.no_grad():
        gs["logits"][2, 2] = 4.0
    write_ply(tmp_path / "g.ply", gs)
    raw = (tmp_path / "g.ply").read_bytes()
    header, body = raw.split(b"end_header\n", 1)
    lines = header.decode().splitlines()
    assert "element vertex 5" in lines
    names = [line.split()[-1] for line in lines if line.startswith("property")]
    for name in ("x", "f_dc_0", "opacity", "scale_2", "rot_3", "part"):
        assert name in names
    dtype = [(n, "<i4" if n == "part" else "<f4") for n in names]
    data = np.frombuffer(body, dtype=dtype)
    assert data["part"].tolist() == [0, 0, 2, 0, 0]
    assert np.allclose(data["x"], gs["means"].detach()[:, 0].numpy())
