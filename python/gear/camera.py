"""Pinhole cameras: OpenCV axes (+x right, +y down, +z forward), world-to-camera 4x4.

Datasets (ArtGS/GEAR/Blender) store camera-to-world matrices in OpenGL axes (+y up, camera looks
down -z); `Camera.from_blender` and `Camera.to_blender` convert. Every other module works in
OpenCV axes only.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

# Flips y and z: OpenGL camera axes <-> OpenCV camera axes (its own inverse).
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])
_RIGID_TOL = 1e-3


def _check_rigid(matrix: np.ndarray, name: str) -> np.ndarray:
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (4, 4):
        raise ValueError(f"{name}: expected a 4x4 matrix, got shape {m.shape}")
    if not np.all(np.isfinite(m)):
        raise ValueError(f"{name}: matrix has non-finite entries")
    rot = m[:3, :3]
    if np.abs(rot @ rot.T - np.eye(3)).max() > _RIGID_TOL or np.linalg.det(rot) <= 0:
        raise ValueError(f"{name}: the 3x3 block is not a rotation (scaled, sheared or mirrored)")
    if np.abs(m[3] - [0, 0, 0, 1]).max() > _RIGID_TOL:
        raise ValueError(f"{name}: last row must be [0, 0, 0, 1]")
    return m


@dataclass(frozen=True)
class Camera:
    """A pinhole camera; `world_to_cam` maps world points to OpenCV camera coordinates."""

    world_to_cam: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        object.__setattr__(self, "world_to_cam", _check_rigid(self.world_to_cam, "world_to_cam"))
        for name in ("fx", "fy", "cx", "cy"):
            value = float(getattr(self, name))
            if not np.isfinite(value):
                raise ValueError(f"camera {name} is not finite: {value}")
            object.__setattr__(self, name, value)
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if int(self.width) < 1 or int(self.height) < 1:
            raise ValueError(f"image size must be at least 1x1, got {self.width}x{self.height}")
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @classmethod
    def from_blender(
        cls,
        cam_to_world: np.ndarray,
        camera_angle_x: float,
        width: int,
        height: int,
        camera_angle_y: float | None = None,
    ) -> Camera:
        """From a dataset's OpenGL camera-to-world matrix and horizontal field of view (rad)."""
        c2w_gl = _check_rigid(cam_to_world, "transform_matrix")
        if not 0 < camera_angle_x < np.pi:
            raise ValueError(f"camera_angle_x must be in (0, pi), got {camera_angle_x}")
        fx = 0.5 * width / np.tan(0.5 * camera_angle_x)
        fy = fx if camera_angle_y is None else 0.5 * height / np.tan(0.5 * camera_angle_y)
        return cls.from_gl(c2w_gl, fx, fy, width / 2.0, height / 2.0, width, height)

    @classmethod
    def from_gl(
        cls,
        cam_to_world: np.ndarray,
        fx: float,
        fy: float,
        cx: float,
        cy: float,
        width: int,
        height: int,
    ) -> Camera:
        """From an OpenGL camera-to-world matrix and pixel intrinsics (nerfstudio's fl_x, fl_y,
        cx, cy: the image centre is (width / 2, height / 2), as in OpenCV and COLMAP)."""
        c2w_gl = _check_rigid(cam_to_world, "transform_matrix")
        return cls(np.linalg.inv(c2w_gl @ _GL_TO_CV), fx, fy, cx, cy, width, height)

    @classmethod
    def look_at(
        cls,
        eye: np.ndarray,
        target: np.ndarray,
        up: np.ndarray,
        fov_x: float,
        width: int,
        height: int,
    ) -> Camera:
        """A camera at `eye` looking at `target`, image-up along `up` (fov_x in radians)."""
        eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
        forward = target - eye
        forward /= np.linalg.norm(forward)
        right = np.cross(forward, up)
        if np.linalg.norm(right) < 1e-9:  # looking along `up`: pick any perpendicular
            right = np.cross(forward, [1.0, 0.0, 0.0] if abs(forward[0]) < 0.9 else [0, 1.0, 0])
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        c2w = np.eye(4)
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, forward, eye
        fx = 0.5 * width / np.tan(0.5 * fov_x)
        return cls(np.linalg.inv(c2w), fx, fx, width / 2.0, height / 2.0, width, height)

    @property
    def cam_to_world(self) -> np.ndarray:
        return np.linalg.inv(self.world_to_cam)

    @property
    def center(self) -> np.ndarray:
        """Camera position in world coordinates."""
        return self.cam_to_world[:3, 3]

    @property
    def intrinsics(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    @property
    def camera_angle_x(self) -> float:
        return float(2.0 * np.arctan(0.5 * self.width / self.fx))

    @property
    def camera_angle_y(self) -> float:
        return float(2.0 * np.arctan(0.5 * self.height / self.fy))

    def to_blender(self) -> np.ndarray:
        """The dataset's OpenGL camera-to-world matrix."""
        return self.cam_to_world @ _GL_TO_CV

    def resized(self, width: int, height: int) -> Camera:
        """The same camera for an image resampled to `width` x `height`."""
        sx, sy = width / self.width, height / self.height
        return Camera(
            self.world_to_cam, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy,
            width, height,
        )

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points [N,3] -> (pixel coordinates [N,2], camera-space depth z [N]).

        Pixel (u, v) = (0, 0) is the top-left corner of the top-left pixel, whose centre is
        (0.5, 0.5): the same convention as the rasterizer.
        """
        pts = np.asarray(points, dtype=np.float64)
        cam = pts @ self.world_to_cam[:3, :3].T + self.world_to_cam[:3, 3]
        z = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.stack(
                [self.fx * cam[:, 0] / z + self.cx, self.fy * cam[:, 1] / z + self.cy], axis=1
            )
        return uv, z

    def unproject(self, depth: np.ndarray) -> np.ndarray:
        """A z-depth image [H,W] (camera-space z; <= 0 invalid) -> world points of valid pixels."""
        v, u = np.nonzero(depth > 0)
        z = depth[v, u].astype(np.float64)
        x = (u + 0.5 - self.cx) / self.fx * z
        y = (v + 0.5 - self.cy) / self.fy * z
        cam = np.stack([x, y, z], axis=1)
        c2w = self.cam_to_world
        return cam @ c2w[:3, :3].T + c2w[:3, 3]


# Cameras count as held upright when every one's right axis lies within this of square to one
# direction (a camera rolled further, or cameras spread over too little of a turn about the
# object to fix that direction, give none).
UPRIGHT_TOLERANCE_DEG = 1.0
# The right axes must spread over a turn about the object: the second singular value of their
# stack at least this share of the first (all cameras on one side: near zero).
UPRIGHT_MIN_SPREAD = 0.2


def capture_up(cameras: Sequence[Camera]) -> np.ndarray | None:
    """The world direction [3] (unit) the `cameras` were held upright about: the one square to
    every camera's right axis (least squares), signed against their image-down axes. None when
    fewer than three cameras, when their right axes do not spread over a turn about the object,
    or when one lies more than UPRIGHT_TOLERANCE_DEG off square to it (a rolled camera)."""
    if len(cameras) < 3:
        return None
    poses = np.array([np.asarray(c.world_to_cam, dtype=np.float64)[:3, :3] for c in cameras])
    rights, downs = poses[:, 0], poses[:, 1]
    _, spread, directions = np.linalg.svd(rights, full_matrices=False)
    if spread[1] < UPRIGHT_MIN_SPREAD * spread[0]:
        return None
    up = directions[-1]
    if np.abs(rights @ up).max() > np.sin(np.radians(UPRIGHT_TOLERANCE_DEG)):
        return None
    return up if float(downs.sum(axis=0) @ up) < 0 else -up
