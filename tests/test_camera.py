"""Camera conventions: OpenGL <-> OpenCV, projection and back-projection."""

import numpy as np
import pytest

from gear.camera import UPRIGHT_TOLERANCE_DEG, Camera, capture_up
from gear.commands.render import orbit_cameras


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


def ring(up: np.ndarray, count: int = 8, sweep_deg: float = 300.0,
         roll_deg: float = 0.0) -> list[Camera]:
    """Cameras on an orbit about `up` (the viewer's, 30 degrees above the object), held upright
    about `up`; the first one rolled by `roll_deg` about its view direction."""
    cams = orbit_cameras(np.zeros(3), 1.0, np.linspace(0.0, sweep_deg, count), 30.0, up, 64)
    if roll_deg:
        r = np.radians(roll_deg)
        roll = np.array([[np.cos(r), -np.sin(r), 0, 0], [np.sin(r), np.cos(r), 0, 0],
                         [0, 0, 1, 0], [0, 0, 0, 1.0]])
        c = cams[0]
        cams[0] = Camera(roll @ c.world_to_cam, c.fx, c.fy, c.cx, c.cy, c.width, c.height)
    return cams


@pytest.mark.parametrize("up", [[0, 0, 1.0], [0, 1.0, 0], [0.3, -0.2, 0.93]])
def test_capture_up_is_the_upright_the_cameras_were_held_about(up):
    up = np.asarray(up) / np.linalg.norm(up)
    found = capture_up(ring(up))
    assert found is not None and np.allclose(found, up, atol=1e-9)
    # Rolled within the tolerance: the direction moves little; beyond it: none.
    slight = capture_up(ring(up, roll_deg=0.5 * UPRIGHT_TOLERANCE_DEG))
    assert slight is not None and float(slight @ up) > np.cos(np.radians(0.5))
    assert capture_up(ring(up, roll_deg=3.0)) is None


def test_capture_up_needs_cameras_around_the_object():
    up = np.array([0.0, 0.0, 1.0])
    assert capture_up(ring(up)[:2]) is None
    assert capture_up(ring(up, sweep_deg=5.0)) is None  # all from one side: any up fits
    assert capture_up(ring(up, sweep_deg=60.0)) is not None
