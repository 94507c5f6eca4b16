"""The real-asset suite's measure of how far each true part moves in the training images
(gear.bench.accuracy.visibility), against the pinhole arithmetic on a flat part."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from gear.bench.accuracy.records import Run
from gear.bench.accuracy.visibility import part_motion_pixels
from gear.camera import Camera
from gear.data.scene import GroundTruth, GtJoint, Scene, View

FOCAL = 100.0
DEPTH = 2.0


def frontal_camera(offset: float = 0.0) -> Camera:
    """Looks down world +z from the origin (OpenCV axes), shifted by `offset` along x."""
    world_to_cam = np.eye(4)
    world_to_cam[0, 3] = -offset
    return Camera(world_to_cam, FOCAL, FOCAL, 32.0, 32.0, 64, 64)


def scene_with(tmp_path, joints: list[GtJoint], cameras: list[Camera]) -> Scene:
    """One flat square part at depth DEPTH facing the cameras, moved by each joint."""
    square = trimesh.Trimesh(
        vertices=[[-0.2, -0.2, DEPTH], [0.2, -0.2, DEPTH], [0.2, 0.2, DEPTH], [-0.2, 0.2, DEPTH]],
        faces=[[0, 1, 2], [0, 2, 3]], process=False)
    meshes = {}
    for i in range(len(joints)):
        path = tmp_path / f"part_{i}.ply"
        square.export(path)
        meshes[f"part_{i}"] = path
    blank = np.zeros((64, 64, 3), np.float32)
    views = [View(f"start/train/{i:04d}", c, blank, blank[..., 0]) for i, c in enumerate(cameras)]
    return Scene(tmp_path, {"start": {"train": views}}, GroundTruth(joints, {"start": meshes}))


def test_a_slide_across_the_view_moves_focal_times_travel_over_depth(tmp_path):
    # A slide along x at constant depth moves every point by FOCAL * travel / DEPTH pixels; a
    # slide of a millimetre is a twentieth of a pixel: below what the images show.
    slides = [GtJoint("prismatic", np.zeros(3), [1.0, 0.0, 0.0], travel)
              for travel in (0.1, 0.001)]
    px = part_motion_pixels(scene_with(tmp_path, slides, [frontal_camera(), frontal_camera(0.5)]))
    assert px == pytest.approx([FOCAL * 0.1 / DEPTH, FOCAL * 0.001 / DEPTH], rel=1e-9)
    run = Run("flat", "quick", parts_true=3, part_motion_px=px)
    assert run.parts_visible == 2


def test_a_hinge_counts_its_free_edge_and_views_behind_are_left_out(tmp_path):
    # A quarter turn about the square's left edge (the line x = -0.2, z = DEPTH, along y)
    # towards the camera: the free edge (x = 0.2) swings to x = -0.2, z = DEPTH - 0.4, so its
    # middle moves from u = 32 + 100 * 0.2 / 2 = 42 to 32 - 100 * 0.2 / 1.6 = 19.5 (22.5 px)
    # and its corners also 2.5 px in v; the 95 % quantile of the sampled surface lies just
    # inside that edge. A camera looking away sees nothing and is not counted in the median.
    hinge = GtJoint("revolute", [-0.2, 0.0, DEPTH], [0.0, 1.0, 0.0], 90.0)
    away = frontal_camera().world_to_cam.copy()
    away[:3, :3] = np.diag([-1.0, 1.0, -1.0])
    cameras = [frontal_camera(), Camera(away, FOCAL, FOCAL, 32.0, 32.0, 64, 64)]
    (px,) = part_motion_pixels(scene_with(tmp_path, [hinge], cameras))
    assert 0.9 * 22.5 < px <= np.hypot(22.5, 2.5) * (1 + 1e-9)


def test_scenes_without_ground_truth_report_nothing(tmp_path):
    scene = scene_with(tmp_path, [GtJoint("prismatic", np.zeros(3), [1, 0, 0], 0.1)],
                       [frontal_camera()])
    scene.gt = None
    assert part_motion_pixels(scene) is None
    assert Run("x", "quick").parts_visible is None
