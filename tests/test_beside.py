"""Work beside the caller (pipeline.common.map_beside) and what uses it: results in order and
the caller's grad mode on the worker; the M-step's views differentiated beside each other give
the motion the gradients of one graph of all the views, bit for bit (native rasterizer)."""

import threading

import numpy as np
import pytest
import torch

from gear.articulation import PartMotion
from gear.config import make_config
from gear.pipeline.common import in_turn, map_beside
from gear.pipeline.stage3 import Refine
from stage3_scenes import grid_gaussians, plank, rot_z, views_of, wall


def test_results_come_back_in_order_from_both_threads():
    threads = []

    def work(i: int) -> int:
        threads.append(threading.current_thread().name)
        return i * i

    assert map_beside(work, list(range(7))) == [i * i for i in range(7)]
    assert len(set(threads)) == 2  # the caller's thread and the worker's
    assert map_beside(work, []) == [] and map_beside(work, [3]) == [9]


def test_the_worker_runs_in_the_callers_grad_mode():
    x = torch.ones(2, requires_grad=True)
    with torch.no_grad():
        assert map_beside(lambda _: (x * 2).requires_grad, [0, 1]) == [False, False]
    assert map_beside(lambda _: (x * 2).requires_grad, [0, 1]) == [True, True]


def test_an_error_on_either_thread_reaches_the_caller_after_both_finish():
    finished = []

    def work(i: int) -> int:
        if i == 1:
            raise ValueError("worker item")
        finished.append(i)
        return i

    with pytest.raises(ValueError, match="worker item"):
        map_beside(work, [0, 1, 2])
    assert sorted(finished) == [0, 2]


def test_inside_in_turn_everything_runs_on_the_calling_thread():
    with in_turn():
        names = map_beside(lambda _: threading.current_thread().name, [0, 1, 2])
    assert set(names) == {threading.current_thread().name}
    assert len(set(map_beside(lambda _: threading.current_thread().name, [0, 1]))) == 2


def test_work_inside_work_runs_in_turn():
    inner = map_beside(lambda i: map_beside(lambda j: (i, j), [0, 1]), [0, 1])
    assert inner == [[(0, 0), (0, 1)], [(1, 0), (1, 1)]]


def wall_and_planks(views: int) -> tuple[Refine, list, list[torch.Tensor]]:
    """Stage 3 on a wall with a turning and a sliding plank, its `views` target views and a
    background for each."""
    blocks = [(wall(), 0), (plank(-0.3, 0.0), 1), (plank(0.1, 0.3, z=-0.25), 2)]
    g = grid_gaussians(blocks)
    turn = (rot_z(30.0), np.array([0.05, -0.02, 0.0]))
    slide = (np.eye(3), np.array([0.0, -0.2, 0.0]))
    target = views_of(g, PartMotion.from_rt([turn, slide]), n=views)
    s = Refine(g, PartMotion.from_rt([(rot_z(26.0), np.zeros(3)), slide]), g.clone(),
               views_of(g, PartMotion(g.num_parts), n=views), target,
               make_config("quick", dict(em_interval=2)), seed=0)
    backgrounds = [torch.rand(3, generator=torch.Generator().manual_seed(i))
                   for i in range(views)]
    return s, target, backgrounds


def test_held_image_step_gives_the_gradients_of_one_graph():
    s, target, backgrounds = wall_and_planks(4)
    qr, qd = s.motion.qr, s.motion.qd
    terms = s.held_image_terms(s.motion, target, backgrounds)
    sum(terms.values()).backward()
    one_graph = (qr.grad.clone(), qd.grad.clone())
    qr.grad = qd.grad = None
    stepped = s.held_image_step(s.motion, target, backgrounds)
    assert {k: float(v.detach()) for k, v in stepped.items()} == {
        k: float(v.detach()) for k, v in terms.items()}
    assert torch.equal(qr.grad, one_graph[0]) and torch.equal(qd.grad, one_graph[1])
    assert float(qr.grad.abs().max()) > 0


def test_the_static_parts_layers_change_no_motion_gradient():
    """The M-step draws the moving parts over the static part's layer per camera: the terms
    and the motion's gradients of the full renders, bit for bit, with one layer kept per view
    rendered."""
    s, target, backgrounds = wall_and_planks(3)
    qr, qd = s.motion.qr, s.motion.qd

    def step() -> tuple[dict, torch.Tensor, torch.Tensor]:
        qr.grad = qd.grad = None
        terms = s.held_image_step(s.motion, target, backgrounds)
        return {k: float(v.detach()) for k, v in terms.items()}, qr.grad.clone(), qd.grad.clone()

    held = s.held()
    assert held.counts[0] > 0
    layered = step()
    assert len(held.layers) == 3 and held.layers.nbytes() > 0
    held.layers = None  # every render full
    full = step()
    assert layered[0] == full[0]
    assert torch.equal(layered[1], full[1]) and torch.equal(layered[2], full[2])
    assert float(full[1].abs().max()) > 0


def test_static_layers_stop_at_their_budget():
    """Past their byte budget no more layers are made: those cameras render in full, with the
    same terms and motion gradients."""
    s, target, backgrounds = wall_and_planks(3)
    qr = s.motion.qr
    held = s.held()
    held.layers.budget = 1  # the first layer already holds more

    def step() -> tuple[dict, torch.Tensor]:
        qr.grad = None
        terms = s.held_image_step(s.motion, target, backgrounds)
        return {k: float(v.detach()) for k, v in terms.items()}, qr.grad.clone()

    budgeted = step()
    assert len(held.layers) == 1 and held.layers.nbytes() > 1
    held.layers = None
    full = step()
    assert budgeted[0] == full[0] and torch.equal(budgeted[1], full[1])
