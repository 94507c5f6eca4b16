"""Training makes no assumption about the world frame, image size or view counts.

A built-in fridge is re-expressed in a world whose up axis is no longer +z (a rotation about
(1, 1, 1) sends z to x) and whose origin is elsewhere; the end state is cropped to a
non-square image and keeps fewer training views than the start state. The quick profile must
recover the door hinge of the transformed ground truth as well as it does in the original frame
(tests/test_train.py uses the same 5-degree bound).
"""

import dataclasses

import numpy as np
import pytest

from gear import _core
from gear.camera import Camera
from gear.config import make_config
from gear.data import View, load_scene
from gear.data.scene import GtJoint
from gear.data.write import write_scene

GPU_RASTERIZER = hasattr(_core, "rasterize_forward")


def rotation_about(axis: np.ndarray, degrees: float) -> np.ndarray:
    k = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    a = np.deg2rad(degrees)
    return np.eye(3) + np.sin(a) * cross + (1 - np.cos(a)) * cross @ cross


# z -> x, x -> y, y -> z, then a shift: no axis of the new world is "up".
WORLD_ROT = rotation_about(np.ones(3), 120.0)
WORLD_SHIFT = np.array([0.7, -1.3, 2.1])


def world_transform() -> np.ndarray:
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = WORLD_ROT, WORLD_SHIFT
    return m


def moved_view(view: View, crop_rows: int) -> View:
    """The view in the new world (camera-space depth is unchanged), `crop_rows` cut off the top
    and the bottom of every image."""
    cam = view.camera
    w2c = cam.world_to_cam @ np.linalg.inv(world_transform())
    rows = slice(crop_rows, cam.height - crop_rows)
    camera = Camera(w2c, cam.fx, cam.fy, cam.cx, cam.cy - crop_rows, cam.width,
                    cam.height - 2 * crop_rows)

    def crop(image: np.ndarray | None) -> np.ndarray | None:
        return None if image is None else np.ascontiguousarray(image[rows])

    return dataclasses.replace(view, camera=camera, rgb=crop(view.rgb), alpha=crop(view.alpha),
                               depth=crop(view.depth), regions=crop(view.regions),
                               parts=crop(view.parts))


def moved_joint(joint: GtJoint) -> GtJoint:
    return GtJoint(joint.type, WORLD_ROT @ joint.origin + WORLD_SHIFT, WORLD_ROT @ joint.axis,
                   joint.amount, joint.start)


def test_moved_world_check_is_consistent():
    """The helper itself: a world point projects to the same pixel before and after the move."""
    cam = Camera.look_at(np.array([2.0, 0.3, 0.5]), np.zeros(3), np.array([0, 0, 1.0]), 0.8,
                         32, 32)
    view = View("start/train/0000", cam, np.zeros((32, 32, 3), np.float32),
                np.zeros((32, 32), np.float32))
    moved = moved_view(view, crop_rows=3)
    point = np.array([[0.1, -0.2, 0.05]])
    uv, z = cam.project(point)
    uv2, z2 = moved.camera.project(point @ WORLD_ROT.T + WORLD_SHIFT)
    np.testing.assert_allclose(uv2, uv - [0, 3], atol=1e-9)
    np.testing.assert_allclose(z2, z, atol=1e-12)


@pytest.mark.skipif(not GPU_RASTERIZER, reason="needs the GPU rasterizer in gear._core")
def test_quick_run_in_a_tilted_world_with_uneven_states(tmp_path):
    from gear.metrics import match_parts
    from gear.synth import generate
    from gear.train import train

    original = load_scene(generate("fridge", tmp_path / "orig", res=64, views=16, test_views=2,
                                   seed=0))
    views = {
        "start": {split: [moved_view(v, 0) for v in original.views["start"][split]]
                  for split in ("train", "test")},
        # the end state: 64x52 images and only 12 of the 16 training views
        "end": {"train": [moved_view(v, 6) for v in original.train("end")[:12]],
                "test": [moved_view(v, 6) for v in original.test("end")]},
    }
    joints = [moved_joint(j) for j in original.gt.joints]
    scene_dir = write_scene(tmp_path / "moved", views, joints)

    result = train(scene_dir, tmp_path / "out", make_config("quick"), quiet=True)
    matching = match_parts(result.joints, joints)
    assert len(matching.pairs) == 1 and not matching.type_mismatches, result.joints
    assert matching.errors[0]["axis_ang"] < 5.0, matching.errors
    for joint in result.joints:
        assert np.isfinite(joint["axis"]).all() and np.isfinite(joint["origin"]).all()
