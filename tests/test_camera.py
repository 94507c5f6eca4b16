"""Camera conventions: OpenGL <-> OpenCV, projection and back-projection."""

import numpy as np
import pytest

from gear.camera import Camera


def test_blender_round_trip_and_axes():
    cam = Camera.look_at([0, -3, 1], [0, 0, 0], [0, 0, 1], np.deg2rad(50), 64, 48)
    again = Camera.from_blender(cam.to_blender(), cam.camera_angle_x, 64, 48)
    np.testing.assert_allclose(again.world_to_cam, cam.world_to_cam, atol=1e-12)
    # The target projects to the image centre, in front of the camera.
    uv, z = cam.project(np.zeros((1, 3)))
    np.testing.assert_allclose(uv[0], [32, 24], atol=1e-9)
    assert z[0] == pytest.approx(np.sqrt(10))
    # World up (+z) appears towards the top of the image (smaller v).
    uv_up, _ = cam.project(np.array([[0, 0, 0.1]]))
    assert uv_up[0, 1] < 24


def test_unproject_inverts_project():
    cam = Camera.look_at([2, 1, 3], [0, 0, 0], [0, 1, 0], 0.8, 40, 30)
    depth = np.full((30, 40), 2.5)
    pts = cam.unproject(depth)
    uv, z = cam.project(pts)
    v, u = np.mgrid[0:30, 0:40]
    np.testing.assert_allclose(uv, np.stack([u.ravel() + 0.5, v.ravel() + 0.5], 1), atol=1e-9)
    np.testing.assert_allclose(z, 2.5, atol=1e-12)


@pytest.mark.parametrize(
    "matrix, message",
    [
        (np.full((4, 4), np.nan), "non-finite"),
        (np.diag([2.0, 1, 1, 1]), "not a rotation"),
        (np.eye(3), "4x4"),
    ],
)
def test_bad_matrices_are_rejected(matrix, message):
    with pytest.raises(ValueError, match=message):
        Camera(matrix, 10, 10, 5, 5, 10, 10)
