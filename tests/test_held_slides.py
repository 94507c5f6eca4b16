"""Stage 3's held slides: a part that stage 2 pushed along the body's frame slides along that
line from the start, no deeper than stage 2's reach, and trains its travel alone; the
joint-type decision leaves it a slide (gear.pipeline.stage3.shared.RefineState.hold_slides)."""

import numpy as np
import pytest
import torch

from gear.articulation import PartMotion
from gear.config import make_config
from gear.kinematics import dq_from_rt, dq_to_rt, quat_from_axis_angle
from gear.pipeline.stage3 import Refine
from gear.pipeline.stage3.joint_types import classify
from stage3_scenes import grid_gaussians, views_of

DEEPEST = np.array([0.3, 0.0, 0.0])  # the deepest shift the slide is held to
TRUE_SHIFT = torch.tensor([0.12, 0.0, 0.0])


def tray_stage(held: bool, start: torch.Tensor, deepest: np.ndarray = DEEPEST) -> Refine:
    """A Refine holding a static plate and a small box (part 1) that truly slides by
    TRUE_SHIFT, its motion started at `start` (a translation), held to `deepest` when
    `held`."""
    gen = torch.Generator().manual_seed(4)
    plate = torch.rand(60, 3, generator=gen) * torch.tensor([0.8, 0.8, 0.02]) - 0.4
    box = torch.rand(60, 3, generator=gen) * 0.15 + torch.tensor([-0.1, -0.1, 0.05])
    g = grid_gaussians([(plate, 0), (box, 1)])
    truth = PartMotion(2)
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0])
    truth.set_part(1, *dq_from_rt(identity, TRUE_SHIFT), prismatic=True)
    views = views_of(g, truth)
    motion = PartMotion(2)
    turned = quat_from_axis_angle(torch.tensor([0.0, 0.0, 1.0]), torch.tensor(0.05))
    motion.set_part(1, *dq_from_rt(turned, start), prismatic=False)
    cfg = make_config("quick")
    return Refine(g, motion, None, views, views, cfg, seed=0,
                  held_slides=[deepest if held else None])


def part_motion(stage: Refine) -> tuple[torch.Tensor, torch.Tensor]:
    qr, qd = stage.motion.motion()
    quat, trans = dq_to_rt(qr, qd)
    return quat[1].detach(), trans[1].detach()


def test_a_held_slide_starts_on_its_line_without_a_turn():
    stage = tray_stage(True, torch.tensor([0.1, 0.03, -0.02]))
    quat, trans = part_motion(stage)
    torch.testing.assert_close(quat, torch.tensor([1.0, 0.0, 0.0, 0.0]))
    torch.testing.assert_close(trans, torch.tensor([0.1, 0.0, 0.0]))
    assert bool(stage.motion.prismatic[1])


@pytest.mark.parametrize(("start", "kept"), [(0.3, 0.2), (-0.05, 0.0)])
def test_a_held_slide_starts_between_no_shift_and_its_deepest(start, kept):
    stage = tray_stage(True, torch.tensor([start, 0.0, 0.0]), deepest=np.array([0.2, 0, 0]))
    _, trans = part_motion(stage)
    torch.testing.assert_close(trans, torch.tensor([kept, 0.0, 0.0]))


def train_motion(stage: Refine, steps: int) -> None:
    """`steps` motion-only steps on the target views in turn."""
    for it in range(steps):
        stage.motion_optimizer.zero_grad(set_to_none=True)
        view = stage.target_views[it % len(stage.target_views)]
        loss = stage.held_image_step(stage.motion, [view], [torch.zeros(3)])
        del loss
        stage.step_motion()


@pytest.mark.parametrize("held", [True, False])
def test_motion_steps_keep_a_held_slide_on_its_line(held):
    stage = tray_stage(held, torch.tensor([0.08, 0.0, 0.0]))
    train_motion(stage, 40)
    quat, trans = part_motion(stage)
    off_line = float(torch.linalg.norm(trans[1:]))
    if held:
        assert off_line == 0.0
        torch.testing.assert_close(quat, torch.tensor([1.0, 0.0, 0.0, 0.0]))
    else:
        assert off_line > 1e-4  # free, Adam's steps move it across the line too


def test_the_joint_type_decision_leaves_a_held_slide_a_slide():
    stage = tray_stage(True, torch.tensor([0.1, 0.0, 0.0]))
    classify(stage)
    assert bool(stage.motion.prismatic[1])
    assert stage.events[-1]["types"] == ["prismatic"]


def test_motion_steps_stop_a_held_slide_at_its_deepest():
    """The images pull the box towards its true shift (0.12), past a reach of 0.1: it goes
    as far as the reach and no further; with a reach past the truth it passes 0.1."""
    reach = 0.1
    stage = tray_stage(True, torch.tensor([0.06, 0.0, 0.0]), deepest=np.array([reach, 0, 0]))
    free = tray_stage(True, torch.tensor([0.06, 0.0, 0.0]))
    train_motion(stage, 60)
    train_motion(free, 60)
    assert float(part_motion(stage)[1][0]) == pytest.approx(reach, abs=1e-7)
    assert float(part_motion(free)[1][0]) > reach + 0.005


def test_a_resumed_stage_keeps_the_held_slides_it_had():
    """A held slide merged away (its part moves as another) stays released after a resume."""
    stage = tray_stage(True, torch.tensor([0.1, 0.0, 0.0]))
    stage.held_slides.pop(1)
    resumed = tray_stage(True, torch.tensor([0.1, 0.0, 0.0]))
    resumed.load_state_dict(stage.state_dict())
    assert resumed.held_slides == {}
