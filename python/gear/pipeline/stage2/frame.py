"""The body's frame: the directions of a boxy body's faces, read off its centres. Boxes hinge
and slide along their edges, so stage 2 pushes drawers along these directions
(frame_slides) and stage 3 tries trained axes along them (stage3/square_axes)."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from gear.geometry import box_diagonal
from gear.pipeline.stage2.hypotheses import ransac_plane

# The body's faces: RANSAC planes of its opaque centres (an even subsample of at most
# FRAME_POINTS, FRAME_TRIALS seeded triples each), points within FRAME_TOLERANCE of the
# object's size from the plane counting for it.
FRAME_POINTS = 20_000
FRAME_TRIALS = 300
FRAME_TOLERANCE = 0.005
# A face holds at least this share of the body's centres (a box's faces: 10-30 %) and this
# many: the hazy static parts of quick models (300-600 opaque centres) gave frames 0.7-3.3
# degrees off their boxes, about as far as the axes they would square; a fast model's faces
# hold thousands (the oven counter's frame: 0.16 degrees off).
MIN_FACE_SHARE = 0.05
MIN_FACE_CENTRES = 500
# ... and the second face's normal lies within this of square to the first's.
SQUARE_FACES_DEG = 10.0
# A face's opposite: parallel to it within this, and at least this share of the object's size
# away from it (a box's sides, not a ledge beside a face).
OPPOSITE_FACES_DEG = 5.0
OPPOSITE_FACE_GAP = 0.1
# Fewer finite centres than this give no frame.
MIN_CENTRES = 10


def body_frame(points: np.ndarray, seed: int = 0) -> np.ndarray | None:
    """The body's frame [3, 3] (orthonormal rows) from its centres `points` [N, 3]: the
    direction of its largest face, that of its largest face square to the first (within
    SQUARE_FACES_DEG), made square to it, and their cross product (each direction from a face
    and its opposite, _face_direction); None unless both faces hold MIN_FACE_SHARE of the
    centres and MIN_FACE_CENTRES. Faces are fitted to many centres, so their normals are known
    far better than any one Gaussian's (the shortest axes of a real oven counter's Gaussians
    spread 5.5 degrees about its faces, and their modes lay 2-3 degrees off)."""
    pts = _frame_sample(points)
    if len(pts) < MIN_CENTRES:
        return None
    size = box_diagonal(pts)
    rng = np.random.default_rng(seed)
    first = _face_direction(pts, size, rng, None)
    if first is None:
        return None
    second = _face_direction(pts, size, rng, first)
    if second is None:
        return None
    second = second - (second @ first) * first
    second = second / np.linalg.norm(second)
    return np.stack([first, second, np.cross(first, second)])


def upright_frame(points: np.ndarray, up: np.ndarray | None, seed: int = 0) -> np.ndarray | None:
    """The frame [M, 3] (orthonormal rows) of a body with no two square faces, from the
    direction `up` the cameras were held upright about (gear.camera.capture_up): `up`, and
    with the direction of the body's largest face square to it (within SQUARE_FACES_DEG, made
    square; _face_direction) that one and their cross product. None without `up`. A pair of
    glasses is one thin front: no second face, but its temples turn about the upright of the
    capture (their trained axes 1.6 and 0.9 degrees off it at fast)."""
    if up is None:
        return None
    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    pts = _frame_sample(points)
    if len(pts) < MIN_CENTRES:
        return up[None]
    size = box_diagonal(pts)
    face = _face_direction(pts, size, np.random.default_rng(seed), up)
    if face is None:
        return up[None]
    face = face - (face @ up) * up
    face = face / np.linalg.norm(face)
    return np.stack([up, face, np.cross(up, face)])


def _frame_sample(points: np.ndarray) -> np.ndarray:
    """The finite rows of `points` [N, 3] as float64, evenly subsampled to at most
    FRAME_POINTS."""
    pts = np.asarray(points, dtype=np.float64)
    pts = pts[np.isfinite(pts).all(axis=1)]
    return pts[:: max(1, -(-len(pts) // FRAME_POINTS))]


def _face_direction(pts: np.ndarray, size: float, rng: np.random.Generator,
                   square_to: np.ndarray | None) -> np.ndarray | None:
    """The unit normal of the largest face of `pts` (an object `size` across), among faces
    within SQUARE_FACES_DEG of square to `square_to` when given, averaged with that of the
    largest face opposite it (parallel within OPPOSITE_FACES_DEG, OPPOSITE_FACE_GAP of the
    size or more away, as large as a face must be) when there is one. A fast model's opposite
    faces tilt against each other (0.2-2.6 degrees apart on real bodies): over seven fast
    models and six RANSAC seeds the mean of the two normals lay 0.25 degrees off the true
    axes on average, the largest face alone 0.43 (1.02 on a cabinet whose sides lie 1.78
    degrees apart)."""
    tolerance = FRAME_TOLERANCE * size
    least = max(MIN_FACE_CENTRES, MIN_FACE_SHARE * len(pts))
    face = _largest_face(pts, tolerance, least, rng,
                         lambda normal: _square_enough(normal, square_to))
    if face is None:
        return None
    origin, normal = face
    beyond = pts[np.abs((pts - origin) @ normal) >= OPPOSITE_FACE_GAP * size]
    if len(beyond) < least:
        return normal
    opposite = _largest_face(beyond, tolerance, least, rng,
                             lambda other: _parallel_enough(other, normal))
    if opposite is None:
        return normal
    mean = normal + math.copysign(1.0, float(opposite[1] @ normal)) * opposite[1]
    return mean / np.linalg.norm(mean)


def _largest_face(pts: np.ndarray, tolerance: float, least: float, rng: np.random.Generator,
                  accept: Callable[[np.ndarray], bool]) -> tuple[np.ndarray, np.ndarray] | None:
    """(a point, unit normal) of the plane holding the most of `pts` within `tolerance`
    (RANSAC over FRAME_TRIALS triples, refitted to its points by least squares twice), among
    the normals `accept` allows; None when it holds fewer than `least` of them or its refit
    left what `accept` allows."""
    best = ransac_plane(pts, tolerance, FRAME_TRIALS, rng, accept=accept)
    if best is None:
        return None
    origin, normal = best
    for _ in range(2):
        near = pts[np.abs((pts - origin) @ normal) <= tolerance]
        if len(near) < 3:
            return None
        origin = near.mean(axis=0)
        normal = np.linalg.svd(near - origin, full_matrices=False)[2][-1]
    if len(near) < least or not accept(normal):
        return None  # too small, or refitted onto another face (a strip of it)
    return origin, normal / np.linalg.norm(normal)


def _square_enough(normal: np.ndarray, square_to: np.ndarray | None) -> bool:
    """Whether the unit `normal` lies within SQUARE_FACES_DEG of square to `square_to` (True
    without one)."""
    limit = math.sin(math.radians(SQUARE_FACES_DEG))
    return square_to is None or abs(float(normal @ square_to)) <= limit


def _parallel_enough(normal: np.ndarray, other: np.ndarray) -> bool:
    """Whether the unit normals lie within OPPOSITE_FACES_DEG of parallel (either sign)."""
    return abs(float(normal @ other)) >= math.cos(math.radians(OPPOSITE_FACES_DEG))
