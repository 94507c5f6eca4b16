"""Axes square to the body (gear.pipeline.stage3.square_axes): the body's frame from its
surface normals, the squared axis and motion, and the end-of-stage-3 step that keeps a
squared hinge only where the images do not see it worse."""

import math

import numpy as np
import pytest
import torch

from gear.articulation import PartMotion
from gear.config import make_config
from gear.kinematics import dq_from_rt, quat_from_axis_angle, quat_from_matrix, quat_to_matrix
from gear.pipeline.stage2.frame import body_frame, upright_frame
from gear.pipeline.stage3 import Refine
from gear.pipeline.stage3.square_axes import (
    MIN_SQUARE_DEG,
    SQUARE_TOLERANCE_DEG,
    squared_axis,
    squared_motion,
)
from stage3_scenes import OFFSET, grid_gaussians, rot_z, views_of

DTYPE = torch.float64


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """The angle between two lines (sign-free), in degrees."""
    cos = abs(float(np.dot(a, b))) / (np.linalg.norm(a) * np.linalg.norm(b))
    return math.degrees(math.acos(min(1.0, cos)))


def tilted(direction: np.ndarray, degrees: float, towards: np.ndarray) -> np.ndarray:
    """`direction` turned by `degrees` towards `towards` (square to it)."""
    a = math.radians(degrees)
    return math.cos(a) * direction + math.sin(a) * towards


def rotation(seed: int) -> np.ndarray:
    """A random rotation matrix (QR of a Gaussian matrix)."""
    q, r = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q * np.sign(np.diag(r))


def box_points(frame: np.ndarray, count: int, noise: float, seed: int,
               wedge_deg: float = 0.0) -> np.ndarray:
    """`count` centres on the faces of a box 1.0 x 0.6 x 0.8 (open at the front: a cabinet's
    body) turned by `frame` (rows: its axes in the world), each off its face by a normal
    error of `noise`. With `wedge_deg`, the x and z faces of each pair tilt that much against
    each other's (a body reconstructed slightly wedge-shaped): neither normal is the body's
    axis, their mean is."""
    rng = np.random.default_rng(seed)
    half = np.array([0.5, 0.3, 0.4])
    slope = math.tan(math.radians(wedge_deg))
    faces = [(a, s) for a in range(3) for s in (-1.0, 1.0) if (a, s) != (1, -1.0)]
    local = rng.uniform(-1, 1, size=(count, 3)) * half
    for i, (axis, side) in enumerate(faces[j] for j in rng.integers(0, len(faces), count)):
        tilt = 0.0 if axis == 1 else side * slope * local[i, 2 - axis]  # x along z, z along x
        local[i, axis] = side * half[axis] + tilt + noise * rng.normal()
    return local @ frame


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_box_gives_its_three_face_directions(seed):
    frame = rotation(seed)
    clutter = np.random.default_rng(seed).uniform(-0.3, 0.3, size=(1000, 3)) @ frame
    points = np.concatenate([box_points(frame, 8000, noise=0.004, seed=seed), clutter])
    found = body_frame(points)
    assert found.shape == (3, 3)
    assert np.allclose(found @ found.T, np.eye(3), atol=1e-9)
    for direction in frame:
        assert min(angle_deg(direction, f) for f in found) < 0.3


def test_opposite_faces_tilted_against_each_other_give_the_axis_between_them():
    frame = rotation(3)
    points = box_points(frame, 12000, noise=0.002, seed=3, wedge_deg=1.5)
    found = body_frame(points)
    for direction in frame:
        assert min(angle_deg(direction, f) for f in found) < 0.3  # each face alone: 1.5


def test_a_round_body_one_face_or_too_few_centres_give_no_frame():
    rng = np.random.default_rng(5)
    ball = rng.normal(size=(5000, 3))
    ball /= np.linalg.norm(ball, axis=1, keepdims=True)
    assert body_frame(ball) is None
    plate = rng.uniform(-1, 1, size=(5000, 3)) * np.array([1.0, 1.0, 0.001])
    assert body_frame(plate) is None  # a face, and nothing square to it
    assert body_frame(box_points(rotation(6), 8, noise=0.0, seed=6)) is None
    assert body_frame(np.full((50, 3), np.nan)) is None


def test_an_axis_is_squared_only_within_the_tolerance():
    frame = rotation(7)
    near = tilted(frame[1], SQUARE_TOLERANCE_DEG - 1, frame[2])
    far = tilted(frame[1], SQUARE_TOLERANCE_DEG + 1, frame[2])
    assert np.allclose(squared_axis(near, frame), frame[1])
    assert np.allclose(squared_axis(-near, frame), -frame[1])  # the sign of the axis is kept
    assert squared_axis(far, frame) is None


def test_a_squared_hinge_keeps_its_angle_and_lands_the_centres_on_average():
    frame = rotation(8)
    spread = np.random.default_rng(9).normal(size=(200, 3))
    points = torch.as_tensor(spread * 0.2 + 0.5, dtype=DTYPE)
    axis = torch.as_tensor(tilted(frame[2], 3.0, frame[0]), dtype=DTYPE)
    quat = quat_from_axis_angle(axis, torch.tensor(math.radians(60.0), dtype=DTYPE))
    trans = torch.tensor([0.1, -0.2, 0.05], dtype=DTYPE)
    new_quat, new_trans, moved = squared_motion(points, quat, trans, False, frame)
    assert abs(moved - 3.0) < 1e-6
    assert angle_deg(new_quat[1:].numpy(), frame[2]) < 1e-6
    assert abs(2 * math.degrees(math.atan2(float(new_quat[1:].norm()), float(new_quat[0])))
               - 60.0) < 1e-6
    landed = points @ quat_to_matrix(quat).T + trans
    landed_new = points @ quat_to_matrix(new_quat).T + new_trans
    assert torch.allclose(landed.mean(0), landed_new.mean(0), atol=1e-12)
    # A slide keeps its travel along the direction; a hinge already square is left alone.
    travel = 0.3 * torch.as_tensor(tilted(frame[0], 2.0, frame[1]), dtype=DTYPE)
    identity = torch.tensor([1.0, 0, 0, 0], dtype=DTYPE)
    _, slide, _ = squared_motion(points, identity, travel, True, frame)
    assert angle_deg(slide.numpy(), frame[0]) < 1e-6
    assert abs(float(slide.norm()) - 0.3 * math.cos(math.radians(2.0))) < 1e-9
    # An axis on a direction, or closer to it than the frame is known, is left alone.
    for off in (0.0, MIN_SQUARE_DEG - 0.1):
        near = torch.as_tensor(tilted(frame[2], off, frame[0]), dtype=DTYPE)
        square = quat_from_axis_angle(near, torch.tensor(1.0, dtype=DTYPE))
        assert squared_motion(points, square, trans, False, frame) is None


# Gaussians along each side of a face: enough centres for each face to count (MIN_FACE_CENTRES).
TILES = 24
# How far the door turns, or slides as a drawer's front.
OPEN_DEG = 80.0
SLIDE = 0.3


def box_faces(frame: np.ndarray) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Centres, quaternions and log-scales of flat Gaussians tiling five faces of a box
    (0.8 x 0.5 x 0.6, open at the front, -y in its frame) turned by `frame` (rows: its x, y, z
    axes in the world)."""
    centres, quats = [], []
    sizes = np.array([0.4, 0.25, 0.3])
    for axis in range(3):
        for side in (-1.0, 1.0):
            if axis == 1 and side < 0:
                continue  # the open front, where the door is
            u, v = [a for a in range(3) if a != axis]
            for a in np.linspace(-0.9, 0.9, TILES):
                for b in np.linspace(-0.9, 0.9, TILES):
                    local = np.zeros(3)
                    local[axis], local[u], local[v] = side * sizes[axis], a * sizes[u], b * sizes[v]
                    centres.append(frame.T @ local)
                    # The Gaussian's short (third) axis along the face's normal.
                    axes = np.eye(3)[[u, v, axis]]
                    quats.append(quat_from_matrix(torch.as_tensor(frame.T @ axes.T)).numpy())
    count = len(centres)
    log_scales = torch.log(torch.tensor([0.02, 0.02, 0.001])).repeat(count, 1)
    return (torch.as_tensor(np.array(centres), dtype=torch.float32),
            torch.as_tensor(np.array(quats), dtype=torch.float32), log_scales)


def hinge(axis: np.ndarray, pivot: np.ndarray, degrees: float) -> tuple[torch.Tensor, ...]:
    """(qr, qd) of a turn by `degrees` about the line through `pivot` along `axis`."""
    quat = quat_from_axis_angle(torch.as_tensor(axis / np.linalg.norm(axis), dtype=DTYPE),
                                torch.tensor(math.radians(degrees), dtype=DTYPE))
    pivot = torch.as_tensor(pivot, dtype=DTYPE)
    return dq_from_rt(quat, pivot - quat_to_matrix(quat) @ pivot)


def door_stage(true_axis: np.ndarray, trained_axis: np.ndarray,
               slide: bool = False, back_only: bool = False) -> tuple[Refine, np.ndarray]:
    """A Refine of an open box (static, turned 20 degrees about z) and a door (part 1) in
    front of it, the target images rendered with the door turned OPEN_DEG about `true_axis`
    (in the box's frame) and the motion trained about `trained_axis`; with `slide`, the door
    slides SLIDE along each axis instead (a drawer's front); with `back_only`, the static body
    is the box's back face alone (one face: no frame of its own); and the box's frame. The
    cameras are held upright about z."""
    frame = rot_z(20.0).T  # rows: the box's axes in the world
    centres, quats, log_scales = box_faces(frame)
    if back_only:
        back = (centres.double() @ torch.as_tensor(frame, dtype=DTYPE).T)[:, 1] > 0.24
        centres, quats, log_scales = centres[back], quats[back], log_scales[back]
    gen = torch.Generator().manual_seed(11)
    door_local = torch.rand(60, 3, generator=gen, dtype=DTYPE) * torch.tensor(
        [0.8, 0.02, 0.6], dtype=DTYPE) + torch.tensor([-0.4, -0.27, -0.3], dtype=DTYPE)
    door = (door_local @ torch.as_tensor(frame, dtype=DTYPE)).float()
    g = grid_gaussians([(centres, 0), (door, 1)])
    with torch.no_grad():
        g["quats"][: len(centres)] = quats
        g["log_scales"][: len(centres)] = log_scales
    pivot = frame.T @ np.array([-0.4, -0.27, 0.0]) + OFFSET  # the door's left edge
    world = lambda local: frame.T @ local  # noqa: E731
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=DTYPE)

    def moved_about(axis: np.ndarray) -> PartMotion:
        motion = PartMotion(2)
        if slide:
            travel = torch.as_tensor(SLIDE * world(axis), dtype=DTYPE)
            motion.set_part(1, *dq_from_rt(identity, travel), prismatic=True)
        else:
            motion.set_part(1, *hinge(world(axis), pivot, OPEN_DEG), prismatic=False)
        return motion

    views = views_of(g, moved_about(true_axis), n=4)
    trained = moved_about(trained_axis)
    return Refine(g, trained, None, views, views, make_config("quick"), seed=0), frame


def door_axis_error(stage: Refine, frame: np.ndarray) -> float:
    """Degrees between the door's hinge axis and the box's vertical axis."""
    return angle_deg(np.asarray(stage.motion.joints(torch.zeros(3))[0]["axis"]), frame[2])


def test_a_door_trained_about_a_tilted_axis_is_squared_to_the_box():
    up, right = np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])
    stage, frame = door_stage(true_axis=up, trained_axis=tilted(up, 3.0, right))
    assert door_axis_error(stage, frame) > 2.9
    stage.square_axes()
    (event,) = stage.events
    (record,) = event["parts"]
    assert event["event"] == "axis_square" and record["kept"], record
    assert record["squared_loss"] < record["loss"]
    assert door_axis_error(stage, frame) < 0.05
    assert torch.isfinite(stage.motion.qr).all() and torch.isfinite(stage.motion.qd).all()


def test_a_drawer_pulled_along_a_tilted_line_is_squared_to_the_box():
    out, right = np.array([0.0, -1.0, 0.0]), np.array([1.0, 0.0, 0.0])
    stage, frame = door_stage(true_axis=out, trained_axis=tilted(out, 3.0, right), slide=True)
    stage.square_axes()
    (record,) = stage.events[0]["parts"]
    assert record["kept"], record
    (joint,) = stage.motion.joints(torch.zeros(3))
    assert joint["type"] == "prismatic"
    assert angle_deg(np.asarray(joint["axis"]), frame[1]) < 0.05
    assert abs(joint["distance"] - SLIDE) < 0.01


def test_a_held_slide_is_not_squared_again():
    """A slide held to a line (stage 2 pushed it along the body's frame) keeps that line: the
    same drawer, free, is squared (above)."""
    out, right = np.array([0.0, -1.0, 0.0]), np.array([1.0, 0.0, 0.0])
    stage, _ = door_stage(true_axis=out, trained_axis=tilted(out, 3.0, right), slide=True)
    (before,) = stage.motion.joints(torch.zeros(3))
    stage.held_slides = {1: np.asarray(before["axis"])}
    stage.square_axes()
    assert stage.events[0]["parts"] == []
    (after,) = stage.motion.joints(torch.zeros(3))
    np.testing.assert_allclose(after["axis"], before["axis"])


def test_a_door_that_truly_turns_off_square_keeps_its_axis():
    up, right = np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])
    skew = tilted(up, SQUARE_TOLERANCE_DEG - 0.5, right)
    stage, frame = door_stage(true_axis=skew, trained_axis=skew)
    stage.square_axes()
    (record,) = stage.events[0]["parts"]
    assert not record["kept"] and record["squared_loss"] > record["loss"], record
    assert abs(door_axis_error(stage, frame) - (SQUARE_TOLERANCE_DEG - 0.5)) < 1e-3


def test_squaring_off_leaves_the_motion():
    up, right = np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])
    stage, _ = door_stage(true_axis=up, trained_axis=tilted(up, 3.0, right))
    stage.config.square_axes = False
    qr, qd = stage.motion.qr.detach().clone(), stage.motion.qd.detach().clone()
    stage.square_axes()
    assert stage.events == []
    assert torch.equal(stage.motion.qr.detach(), qr) and torch.equal(stage.motion.qd.detach(), qd)


def test_a_door_before_one_face_is_squared_to_the_upright_of_the_cameras():
    """A body with one face has no frame of its own (a pair of glasses' front); the cameras,
    held upright about z, give the direction the door's hinge is squared to."""
    up, right = np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])
    stage, frame = door_stage(true_axis=up, trained_axis=tilted(up, 3.0, right), back_only=True)
    ids = stage.gaussians.part_ids()
    assert body_frame(stage.gaussians["means"].detach()[ids == 0].numpy()) is None
    stage.square_axes()
    (record,) = stage.events[0]["parts"]
    assert record["kept"] and record["squared_loss"] < record["loss"], record
    assert door_axis_error(stage, frame) < 0.05


def test_an_upright_frame_holds_the_up_and_a_face_square_to_it():
    rng = np.random.default_rng(3)
    plate = rng.uniform(-1, 1, size=(5000, 3)) * np.array([1.0, 0.002, 0.4])  # normal y
    up = tilted(np.array([0.0, 0.0, 1.0]), 2.0, np.array([0.0, 1.0, 0.0]))
    frame = upright_frame(plate, up)
    assert frame is not None and frame.shape == (3, 3)
    assert np.allclose(frame @ frame.T, np.eye(3), atol=1e-9)
    assert np.allclose(frame[0], up)
    assert angle_deg(frame[1], np.array([0.0, 1.0, 0.0])) < 2.1  # the face, made square to up
    assert upright_frame(plate, None) is None
    ball = rng.normal(size=(5000, 3))
    ball /= np.linalg.norm(ball, axis=1, keepdims=True)
    only_up = upright_frame(ball, up)  # no face: the up alone
    assert only_up is not None and only_up.shape == (1, 3) and np.allclose(only_up[0], up)
