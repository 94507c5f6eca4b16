"""Hinges corrected at the end of stage 3. Landed on the target's reconstruction
(gear.pipeline.stage3.landing): a door whose trained turn stopped short about a shifted pivot
is moved to the turn that lays it on the target state's model, and nothing moves where that
model agrees with the motion already. Stage 2's lines tried again
(gear.pipeline.stage3.hinge_lines): a turn carried off its line goes back to stage 2's where
the images see it better, and stays where they do not."""

import math

import numpy as np
import torch

from gear.articulation import PartMotion
from gear.config import make_config
from gear.kinematics import dq_from_rt, quat_from_axis_angle, quat_to_matrix
from gear.pipeline.stage3 import Refine
from gear.pipeline.stage3.hinge_lines import MIN_TURN_RAD
from gear.pipeline.stage3.landing import IMAGE_COST_PER_GAIN, LANDING_SEARCH, MIN_LANDING_GAIN
from gear.pipeline.stage3.square_axes import SQUARE_MARGIN
from stage3_scenes import OFFSET, grid_gaussians, views_of

DTYPE = torch.float64
UP = np.array([0.0, 0.0, 1.0])
PIVOT = np.array([-0.4, -0.27, 0.0]) + OFFSET  # the door's left edge, in the world
OPEN_DEG = 60.0


def body() -> torch.Tensor:
    """Centres on five faces of a box 0.8 x 0.5 x 0.6 open at the front (-y)."""
    half = np.array([0.4, 0.25, 0.3])
    grid = np.linspace(-0.9, 0.9, 7)
    centres = []
    for axis in range(3):
        for side in (-1.0, 1.0):
            if axis == 1 and side < 0:
                continue
            u, v = [a for a in range(3) if a != axis]
            for a in grid:
                for b in grid:
                    local = np.zeros(3)
                    local[axis], local[u], local[v] = side * half[axis], a * half[u], b * half[v]
                    centres.append(local)
    return torch.as_tensor(np.array(centres), dtype=torch.float32)


def door() -> torch.Tensor:
    """A plate of 1500 centres 0.8 x 0.02 x 0.6 closing the box's front."""
    rng = np.random.default_rng(5)
    local = rng.uniform(0, 1, size=(1500, 3)) * [0.8, 0.02, 0.6] + [-0.4, -0.28, -0.3]
    return torch.as_tensor(local, dtype=torch.float32)


def turn(degrees: float, pivot: np.ndarray, axis: np.ndarray = UP) -> tuple[torch.Tensor, ...]:
    """(quaternion, translation) of a turn by `degrees` about the line through `pivot`."""
    quat = quat_from_axis_angle(torch.as_tensor(axis / np.linalg.norm(axis), dtype=DTYPE),
                                torch.tensor(math.radians(degrees), dtype=DTYPE))
    pivot = torch.as_tensor(pivot, dtype=DTYPE)
    return quat, pivot - quat_to_matrix(quat) @ pivot


def motion_of(rt: tuple[torch.Tensor, ...], prismatic: bool = False) -> PartMotion:
    motion = PartMotion(2)
    motion.set_part(1, *dq_from_rt(*rt), prismatic=prismatic)
    return motion


def rigid(rt: tuple[torch.Tensor, ...]) -> tuple[np.ndarray, np.ndarray]:
    """A (quaternion, translation) turn as stage 2's (R, t) guess."""
    quat, trans = rt
    return quat_to_matrix(quat).numpy(), trans.numpy()


def door_stage(trained: tuple[torch.Tensor, ...], landed_on: tuple[torch.Tensor, ...],
               prismatic: bool = False, stage2: tuple[torch.Tensor, ...] | None = None):
    """(a Refine of the box and its door trained to `trained` (stage 2's guess `stage2`, when
    given), its target images and the target state's model made with the door moved by the
    truth's turn; that model with the door moved by `landed_on`)."""
    g = grid_gaussians([(body(), 0), (door(), 1)])
    views = views_of(g, motion_of(turn(OPEN_DEG, PIVOT)), n=4)
    guesses = [] if stage2 is None else [[rigid(stage2)]]
    stage = Refine(g, motion_of(trained, prismatic), None, views, views, make_config("quick"),
                   seed=0, init_motions=guesses)
    quat, trans = landed_on
    world = door().double() + torch.as_tensor(OFFSET)
    moved = (world @ quat_to_matrix(quat).T + trans - torch.as_tensor(OFFSET)).float()
    return stage, grid_gaussians([(body(), 0), (moved, 1)])


def hinge_of(stage: Refine) -> dict:
    (joint,) = stage.motion.joints(torch.as_tensor(OFFSET))
    return joint


def line_distance(joint: dict) -> float:
    """How far the joint's axis line passes from the true hinge line (both nearly along z)."""
    origin = np.asarray(joint["origin"])
    axis = np.asarray(joint["axis"]) / np.linalg.norm(joint["axis"])
    at_pivot_height = origin + axis * (PIVOT[2] - origin[2]) / axis[2]
    return float(np.linalg.norm((at_pivot_height - PIVOT)[:2]))


def test_a_door_stopped_short_about_a_shifted_pivot_lands_on_the_target():
    short = turn(OPEN_DEG - 5.0, PIVOT + np.array([0.03, -0.02, 0.0]))
    stage, target = door_stage(short, landed_on=turn(OPEN_DEG, PIVOT))
    before = hinge_of(stage)
    assert abs(abs(before["angle_deg"]) - OPEN_DEG) > 4.9 and line_distance(before) > 0.03
    stage.land_hinges(target)
    (event,) = stage.events
    (record,) = event["parts"]
    assert event["event"] == "hinge_landing" and record["kept"], record
    assert record["landed_fit"] > 2 * record["fit"]
    after = hinge_of(stage)
    assert abs(abs(after["angle_deg"]) - OPEN_DEG) < 0.3, after
    assert line_distance(after) < 0.01, after
    axis = np.asarray(after["axis"]) / np.linalg.norm(after["axis"])
    assert math.degrees(math.acos(min(1.0, abs(axis @ UP)))) < 0.5
    assert torch.isfinite(stage.motion.qr).all() and torch.isfinite(stage.motion.qd).all()


def test_a_hinge_the_target_agrees_with_is_left_bit_for_bit():
    trained = turn(OPEN_DEG - 2.0, PIVOT + np.array([0.01, 0.0, 0.0]))
    stage, target = door_stage(trained, landed_on=trained)
    qr, qd = stage.motion.qr.detach().clone(), stage.motion.qd.detach().clone()
    stage.land_hinges(target)
    (record,) = stage.events[0]["parts"]
    assert not record["kept"], record
    assert torch.equal(stage.motion.qr.detach(), qr) and torch.equal(stage.motion.qd.detach(), qd)


def test_a_modest_gain_the_images_see_much_worse_is_refused():
    """The target's model holds the door 2.5 degrees further open about a pivot 0.01 aside
    while the images agree with the trained turn: the fit gains ~26 % for images ~4 % worse,
    under SQUARE_MARGIN but more than IMAGE_COST_PER_GAIN of the gain allows."""
    trained = turn(OPEN_DEG, PIVOT)
    stage, target = door_stage(trained, landed_on=turn(OPEN_DEG + 2.5,
                                                       PIVOT + np.array([0.01, 0.0, 0.0])))
    qr, qd = stage.motion.qr.detach().clone(), stage.motion.qd.detach().clone()
    stage.land_hinges(target)
    (record,) = stage.events[0]["parts"]
    gain = record["landed_fit"] / record["fit"] - 1
    cost = record["landed_loss"] / record["loss"] - 1
    assert MIN_LANDING_GAIN <= gain < SQUARE_MARGIN / IMAGE_COST_PER_GAIN, record
    assert IMAGE_COST_PER_GAIN * gain < cost <= SQUARE_MARGIN, record
    assert not record["kept"], record
    assert torch.equal(stage.motion.qr.detach(), qr) and torch.equal(stage.motion.qd.detach(), qd)


def test_the_search_stays_within_its_bounds():
    """A target turned far beyond the angle bound pulls the door to the bound, no further."""
    stage, target = door_stage(turn(OPEN_DEG - 30.0, PIVOT), landed_on=turn(OPEN_DEG, PIVOT))
    stage.land_hinges(target)
    (record,) = stage.events[0]["parts"]
    assert record["angle_moved_deg"] <= LANDING_SEARCH.angle_deg + 1e-6
    assert record["axis_moved_deg"] <= LANDING_SEARCH.tilt_deg + 1e-6


def test_slides_and_a_config_that_turns_it_off_leave_the_motion():
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=DTYPE)
    slide = (identity, torch.tensor([0.0, -0.2, 0.0], dtype=DTYPE))
    stage, target = door_stage(slide, landed_on=turn(OPEN_DEG, PIVOT), prismatic=True)
    stage.land_hinges(target)
    assert stage.events[0]["parts"] == []
    stage, target = door_stage(turn(OPEN_DEG - 5.0, PIVOT), landed_on=turn(OPEN_DEG, PIVOT))
    stage.config.land_hinges = False
    qr, qd = stage.motion.qr.detach().clone(), stage.motion.qd.detach().clone()
    stage.land_hinges(target)
    assert stage.events == []
    assert torch.equal(stage.motion.qr.detach(), qr) and torch.equal(stage.motion.qd.detach(), qd)


def test_a_turn_carried_off_stage_2s_line_goes_back_where_the_images_see_it_better():
    """Trained to the true angle about a line 0.05 off; stage 2 had the true line (and an
    angle 4 degrees short): the trained turn about stage 2's line is the truth."""
    truth = turn(OPEN_DEG, PIVOT)
    carried = turn(OPEN_DEG, PIVOT + np.array([0.04, -0.03, 0.0]))
    stage, _ = door_stage(carried, landed_on=truth, stage2=turn(OPEN_DEG - 4.0, PIVOT))
    assert line_distance(hinge_of(stage)) > 0.045
    stage.recall_hinge_lines()
    (event,) = stage.events
    (record,) = event["parts"]
    assert event["event"] == "hinge_lines" and record["kept"], record
    assert record["recalled_loss"] < record["loss"]
    assert abs(record["pivot_moved"] - 0.05) < 1e-3, record
    after = hinge_of(stage)
    assert line_distance(after) < 1e-3, after
    assert abs(abs(after["angle_deg"]) - OPEN_DEG) < 1e-3, after
    assert torch.isfinite(stage.motion.qr).all() and torch.isfinite(stage.motion.qd).all()


def test_stage_2s_line_the_images_see_worse_is_refused_bit_for_bit():
    """Trained to the truth; stage 2's line lay 0.05 off: the images refuse it."""
    truth = turn(OPEN_DEG, PIVOT)
    stage, _ = door_stage(truth, landed_on=truth,
                          stage2=turn(OPEN_DEG, PIVOT + np.array([0.03, 0.04, 0.0])))
    qr, qd = stage.motion.qr.detach().clone(), stage.motion.qd.detach().clone()
    stage.recall_hinge_lines()
    (record,) = stage.events[0]["parts"]
    assert not record["kept"] and record["recalled_loss"] > record["loss"], record
    assert torch.equal(stage.motion.qr.detach(), qr) and torch.equal(stage.motion.qd.detach(), qd)


def test_no_line_to_recall_from_a_slide_or_no_guess_or_with_the_config_off():
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=DTYPE)
    slide = (identity, torch.tensor([0.0, -0.2, 0.0], dtype=DTYPE))
    carried = turn(OPEN_DEG, PIVOT + np.array([0.04, -0.03, 0.0]))
    # Stage 2 guessed only a slide (a turn below MIN_TURN_RAD): no line to offer.
    nearly = turn(math.degrees(MIN_TURN_RAD) / 2, PIVOT)
    for guess in (slide, nearly, None):
        stage, _ = door_stage(carried, landed_on=carried, stage2=guess)
        stage.recall_hinge_lines()
        assert stage.events[0]["parts"] == []
    # A part trained as a slide is left alone, whatever stage 2 guessed.
    stage, _ = door_stage(slide, landed_on=slide, prismatic=True, stage2=turn(OPEN_DEG, PIVOT))
    stage.recall_hinge_lines()
    assert stage.events[0]["parts"] == []
    stage, _ = door_stage(carried, landed_on=carried, stage2=turn(OPEN_DEG, PIVOT))
    stage.config.recall_hinge_lines = False
    qr, qd = stage.motion.qr.detach().clone(), stage.motion.qd.detach().clone()
    stage.recall_hinge_lines()
    assert stage.events == []
    assert torch.equal(stage.motion.qr.detach(), qr) and torch.equal(stage.motion.qd.detach(), qd)
