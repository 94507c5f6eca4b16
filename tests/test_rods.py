"""A rod's twist about its own length is dropped at the end of stage 3; anything else keeps
its motion (gear.pipeline.stage3.rods)."""

import math

import pytest
import torch

from gear.articulation import PartMotion
from gear.config import make_config
from gear.kinematics import dq_from_rt, quat_from_axis_angle, quat_mul, quat_to_matrix
from gear.pipeline.stage3 import Refine
from gear.pipeline.stage3.rods import rod_swing
from stage3_scenes import OFFSET, grid_gaussians, views_of

DTYPE = torch.float64
HINGE_AXIS = torch.tensor([0.0, 1.0, 0.0], dtype=DTYPE)  # the lever turns about +y
PIVOT = torch.tensor([0.3, 0.0, -0.2], dtype=DTYPE)


def lever(length_over_thickness: float = 50.0, count: int = 400) -> torch.Tensor:
    """Centres of a round bar along +z from the pivot, `length_over_thickness` times longer
    than thick (a faucet's lever)."""
    gen = torch.Generator().manual_seed(3)
    along = torch.rand(count, generator=gen, dtype=DTYPE)
    radius = 1.0 / length_over_thickness
    around = radius * torch.randn(count, 2, generator=gen, dtype=DTYPE)
    return PIVOT + torch.stack([around[:, 0], around[:, 1], along], 1)


def turn(axis: torch.Tensor, degrees: float, about: torch.Tensor = PIVOT):
    """(quaternion, translation) of a turn by `degrees` about the line through `about`."""
    quat = quat_from_axis_angle(axis / axis.norm(), torch.tensor(math.radians(degrees),
                                                                 dtype=DTYPE))
    return quat, about - quat_to_matrix(quat) @ about


def with_twist(degrees: float, twist: float, pivot: torch.Tensor = PIVOT):
    """The hinge's turn after a twist of the bar about its own length (its centre line, from
    `pivot` along +z): the bar lands in the same place as without it."""
    quat, trans = turn(HINGE_AXIS, degrees, pivot)
    twist_quat, twist_trans = turn(torch.tensor([0.0, 0.0, 1.0], dtype=DTYPE), twist, pivot)
    rot = quat_to_matrix(quat)
    return quat_mul(quat, twist_quat), rot @ twist_trans + trans


@pytest.mark.parametrize("twist", [-12.0, 3.0, 9.0])
def test_a_twisted_lever_gets_back_the_hinge_it_turned_about(twist):
    points = lever()
    quat, trans = with_twist(47.0, twist)
    swing = rod_swing(points, quat, trans)
    assert swing is not None
    swing_quat, swing_trans, record = swing
    axis = swing_quat[1:] / swing_quat[1:].norm()
    # The bar's measured direction deviates from +z by its sampling noise only.
    assert math.degrees(math.acos(min(1.0, abs(float(axis @ HINGE_AXIS))))) < 0.5
    assert math.degrees(2 * math.acos(min(1.0, float(swing_quat[0])))) == pytest.approx(47.0,
                                                                                         abs=0.5)
    assert record["twist_deg"] == pytest.approx(abs(twist), abs=0.5)
    # The pivot lies on the true hinge line, and the bar lands where the trained motion put it.
    rot = quat_to_matrix(swing_quat)
    pivot_offset = (torch.eye(3, dtype=DTYPE) - rot) @ PIVOT - swing_trans
    assert float(pivot_offset.norm()) < 0.01
    landed = points @ quat_to_matrix(quat).T + trans
    moved = points @ rot.T + swing_trans
    # Centres lie within ~3 radii (0.06) of the bar's centre line, where a twist of 12° or
    # less moves them by at most 0.013: the swing lands them within that.
    assert float((moved - landed).norm(dim=1).max()) < 0.015


def test_a_door_keeps_its_motion():
    gen = torch.Generator().manual_seed(4)
    plate = PIVOT + torch.rand(400, 3, generator=gen, dtype=DTYPE) * torch.tensor(
        [0.6, 0.8, 0.02], dtype=DTYPE)
    assert rod_swing(plate, *with_twist(47.0, 9.0)) is None


def test_a_flat_bar_shows_its_twist_and_keeps_its_motion():
    # Three times wider than thick, still 5 times longer than wide, from the pivot.
    flat = lever() * torch.tensor([3.0, 1.0, 1.0], dtype=DTYPE) - PIVOT * torch.tensor(
        [2.0, 0.0, 0.0], dtype=DTYPE)
    assert rod_swing(flat, *with_twist(47.0, 9.0)) is None
    assert rod_swing(lever(), *with_twist(47.0, 9.0)) is not None  # the same bar, round


def test_centres_at_one_point_are_no_rod():
    point = PIVOT.repeat(20, 1)
    assert rod_swing(point, *with_twist(47.0, 9.0)) is None


def test_a_knob_spinning_about_its_length_keeps_its_motion():
    quat, trans = turn(torch.tensor([0.05, 0.0, 1.0], dtype=DTYPE), 60.0)
    assert rod_swing(lever(), quat, trans) is None


def rod_stage(untwist: bool, prismatic: bool = False) -> Refine:
    """A Refine holding a static plate and a lever (part 1) whose motion carries a twist."""
    gen = torch.Generator().manual_seed(6)
    plate = torch.rand(40, 3, generator=gen) * torch.tensor([0.6, 0.6, 0.02]) - 0.5
    g = grid_gaussians([(plate, 0), (lever(count=100).float(), 1)])
    quat, trans = with_twist(47.0, 9.0, PIVOT + torch.as_tensor(OFFSET, dtype=DTYPE))
    motion = PartMotion(2)
    motion.set_part(1, *dq_from_rt(quat.float(), trans.float()), prismatic=prismatic)
    views = views_of(g, motion)
    cfg = make_config("quick", dict(untwist_rods=untwist))
    return Refine(g, motion, None, views, views, cfg, seed=0)


def test_stage3_untwists_a_lever_and_says_so():
    stage = rod_stage(untwist=True)
    before = stage.motion.joints(torch.zeros(3))[0]
    stage.untwist_rods()
    (event,) = stage.events
    assert event["event"] == "rod_untwist" and [p["part"] for p in event["parts"]] == [1]
    after = stage.motion.joints(torch.zeros(3))[0]
    axis_error = lambda joint: math.degrees(math.acos(min(1.0, abs(joint["axis"][1]))))  # noqa: E731
    assert axis_error(before) > 5.0 and axis_error(after) < 1.0
    assert torch.isfinite(stage.motion.qr).all() and torch.isfinite(stage.motion.qd).all()


@pytest.mark.parametrize("untwist, prismatic", [(False, False), (True, True)])
def test_untwisting_off_or_a_slide_leaves_the_motion(untwist, prismatic):
    stage = rod_stage(untwist=untwist, prismatic=prismatic)
    qr, qd = stage.motion.qr.detach().clone(), stage.motion.qd.detach().clone()
    stage.untwist_rods()
    assert torch.equal(stage.motion.qr.detach(), qr) and torch.equal(stage.motion.qd.detach(), qd)
