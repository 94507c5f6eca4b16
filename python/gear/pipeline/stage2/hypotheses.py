"""Stage 2's motion hypotheses on the voxel grid: least-squares planes of components, the
hinges about the intersection of two planes (or the half turn folding one onto the other) and
whole-voxel slides by cross-correlation (docs/method.md, "Stage 2")."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.fft import set_workers
from scipy.optimize import minimize
from scipy.signal import fftconvolve

from gear import _core
from gear.articulation import RigidMotion
from gear.geometry import NearestTree

# max/min principal extent above which a component is a plane (may turn on a hinge). Not 3: a
# door reconstructed from few, small views blurs into what lies behind it (docs/method.md,
# "Stage 2"); the scores still decide between hinge and slide.
PLANE_ASPECT = 2.0
PARALLEL_COS = 0.95  # |n_s . n_t| above this: the planes are too parallel to intersect
# RANSAC of a target piece's dominant plane (dominant_plane): triples tried, centres used.
DOMINANT_PLANE_TRIALS = 200
DOMINANT_PLANE_POINTS = 5000
# ... and the share of them it must hold: any slice of a cloud is flat (a voxel-thick slice of
# a cloud 0.8 deep holds 5 %); the sink cabinet's closed front held 39 % of its piece.
DOMINANT_PLANE_SHARE = 0.25
MIN_OVERLAP = 0.1  # overlap / min(|S|, |T|) below this: no motion hypothesis is trusted
# Counting a piece as a new part (K unknown) needs more: pieces seen in one state only (a
# cabinet's interior through an open door) reach 10-20 % by chance.
DETECT_OVERLAP = 0.3
# Turns of a blob (swept_hinges): angle step, centre samples of the sweep (4x for the best few),
# translation settling steps of the best few, and how many of the best turns are kept.
SWEEP_STEP_DEG = 10
SWEEP_SAMPLES = 100
SWEEP_SETTLE = 10
SWEEP_KEEP = 3
SWEEP_TARGETS = 3  # the largest target pieces a blob's turns start on
# A local search of a turn (refine_turn): the centres sampled and the evaluations allowed
# per width.
REFINE_SAMPLES = 1000
REFINE_EVALUATIONS = 600


@dataclass(frozen=True)
class TurnSearch:
    """The bounds of refine_turn: how far the axis may tilt (degrees, a cone), the pivot move
    across the axis (a fraction of the extent given) and the angle change (degrees), and the
    widths of the surface fit, coarse to fine (fractions of the extent; None: the fit's own)."""

    tilt_deg: float
    pivot: float
    angle_deg: float
    widths: tuple[float | None, ...]


# A thick piece's hinge in stage 2, from a plane intersection that can miss it by tens of
# degrees (extent: the piece's largest). At the fit's own width alone, a lid shifted by a few
# centimetres along its length still lands half on itself, a maximum the search stops at.
THICK_PIECE_SEARCH = TurnSearch(tilt_deg=30.0, pivot=0.5, angle_deg=20.0,
                                widths=(1 / 8, 1 / 32, None))


@dataclass
class Plane:
    """Least-squares plane of a point set: centroid, principal axes (rows, largest extent
    first; the last is the unit normal), the extent along each axis and the ratio of the largest
    to the smallest extent."""

    centroid: np.ndarray
    axes: np.ndarray
    aspect: float
    extents: np.ndarray

    def width_along(self, direction: np.ndarray) -> float:
        """The point set's extent along `direction` (unit), from its principal extents."""
        return float(np.abs(self.axes @ direction) @ self.extents)

    @property
    def normal(self) -> np.ndarray:
        return self.axes[-1]

    @property
    def is_plane(self) -> bool:
        return self.aspect > PLANE_ASPECT

    @property
    def is_flat(self) -> bool:
        """Much thinner than its two other sides: a slab or a blade, with a normal of its own
        (a rod passes is_plane, but its normal is any direction across it)."""
        return self.extents[1] > PLANE_ASPECT * max(self.extents[2], 1e-12)

    @property
    def is_rod(self) -> bool:
        """Much longer than wide: a lever or a handle, whose longest direction turns."""
        return self.extents[0] > PLANE_ASPECT * max(self.extents[1], 1e-12)


@dataclass
class Hypothesis:
    """A candidate canonical -> target motion for one component, scored on the voxel grid.

    landed: fraction of the component's cells that land on occupied target cells, within one
    voxel (the part must end up where the target has matter). explained: target dynamic cells
    it covers over min(|S|, |dynamic target|), the paper's overlap (it must explain change).
    """

    kind: str  # "hinge", "slide" or "identity"
    rot: np.ndarray
    trans: np.ndarray
    landed: float = 0.0
    explained: float = 0.0
    fold: bool = False  # a half turn between parallel planes (see init_motion)

    @property
    def trusted(self) -> bool:
        return self.kind != "identity" and self.explained >= MIN_OVERLAP


IDENTITY = Hypothesis("identity", np.eye(3), np.zeros(3))


def fit_plane(points: np.ndarray) -> Plane:
    """PCA plane of points [N, 3]; extents are 2-98 percentile ranges (robust to strays)."""
    pts = np.asarray(points, dtype=np.float64)
    centroid = pts.mean(axis=0)
    _, _, axes = np.linalg.svd(pts - centroid, full_matrices=False)
    proj = (pts - centroid) @ axes.T
    lo, hi = np.percentile(proj, [2, 98], axis=0)
    extent = hi - lo
    aspect = float(extent.max() / max(extent.min(), 1e-9 * max(extent.max(), 1e-300)))
    return Plane(centroid, axes / np.linalg.norm(axes, axis=1, keepdims=True), aspect, extent)


def ransac_plane(pts: np.ndarray, tolerance: float, trials: int, rng: np.random.Generator,
                 accept: Callable[[np.ndarray], bool] | None = None,
                 ) -> tuple[np.ndarray, np.ndarray] | None:
    """(a point, unit normal) of the plane through one of `trials` random triples of `pts`
    [N, 3] (drawn from `rng`) holding the most of them within `tolerance`, among the normals
    `accept` allows; None when no triple spans an allowed plane."""
    best, best_count = None, 0
    for a, b, c in pts[rng.integers(0, len(pts), (trials, 3))]:
        normal = np.cross(b - a, c - a)
        length = np.linalg.norm(normal)
        if length <= 1e-12:
            continue
        normal = normal / length
        if accept is not None and not accept(normal):
            continue
        count = int((np.abs((pts - a) @ normal) <= tolerance).sum())
        if count > best_count:
            best, best_count = (a, normal), count
    return best


def dominant_plane(points: np.ndarray, tolerance: float, seed: int = 0) -> Plane | None:
    """The plane (fit_plane of its inliers) holding the most of `points` [N, 3] within
    `tolerance`, by RANSAC over DOMINANT_PLANE_TRIALS triples of an even subsample of at most
    DOMINANT_PLANE_POINTS (seeded: the same points give the same plane); None when those
    inliers are under DOMINANT_PLANE_SHARE of the points or no plane. A closed door is flat,
    but the target's change around it often is not: a real sink cabinet's closed front (two
    doors and a drawer's face, one piece) came with matter behind it, a piece 1.6 x 1.6 x 0.8
    across, and no turn of the open doors onto it was tried."""
    pts = np.asarray(points, dtype=np.float64)
    pts = pts[:: -(-len(pts) // DOMINANT_PLANE_POINTS)]
    if len(pts) < 3:
        return None
    found = ransac_plane(pts, tolerance, DOMINANT_PLANE_TRIALS, np.random.default_rng(seed))
    if found is None:
        return None
    best = np.abs((pts - found[0]) @ found[1]) <= tolerance
    if best.sum() < max(3, DOMINANT_PLANE_SHARE * len(pts)):
        return None
    plane = fit_plane(pts[best])
    return plane if plane.is_plane else None


def rotation_about_line(
    axis: np.ndarray, pivot: np.ndarray, angle: float
) -> RigidMotion:
    """(R, t) of a right-handed rotation by `angle` radians about the line (pivot, axis)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    rot = np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)
    p = np.asarray(pivot, dtype=np.float64)
    return rot, p - rot @ p


def hinge_candidates(
    src: Plane, dst: Plane, fold_offsets: Sequence[float] = (0.0,)
) -> list[RigidMotion]:
    """Rotations about the intersection line of two planes taking `src` onto `dst`.

    Axis n_s x n_t, pivot the least-squares point on both planes (midway between the centroids
    along the axis), angle arccos(n_s . n_t), and that angle + pi (the normals' signs are
    arbitrary). Nearly parallel planes have no usable intersection; if `dst` lies beside `src`
    (their centroids apart mostly within the plane) they give the half turns that fold one onto
    the other: a door opened by 180 degrees, which the plane intersection cannot see. The fold
    axes lie in the (mean) plane (fold_axes), each through the centroids' midpoint moved by
    each of `fold_offsets` across the axis in the plane and along the normal (the two pieces
    are rarely cut symmetrically about the hinge, nor is the hinge in their plane).
    """
    cos = float(np.dot(src.normal, dst.normal))
    if abs(cos) > PARALLEL_COS:
        offset = dst.centroid - src.centroid
        beside = offset - np.dot(offset, src.normal) * src.normal
        length = float(np.linalg.norm(beside))
        if length <= 0.5 * np.linalg.norm(offset):
            return []
        # Folded about an axis at or near its edge, a piece lands beside its old place, its
        # centroid moved by about its width. Two slivers of a door turned by a few degrees lie
        # much closer: that is no fold.
        if length < 0.5 * max(src.width_along(beside / length), dst.width_along(beside / length)):
            return []
        normal = src.normal + np.sign(cos) * dst.normal
        normal /= np.linalg.norm(normal)
        mid = (src.centroid + dst.centroid) / 2
        return [
            rotation_about_line(axis, mid + a * np.cross(normal, axis) + b * src.normal, np.pi)
            for axis in fold_axes(src, normal, beside / length)
            for a in fold_offsets
            for b in fold_offsets
        ]
    axis = np.cross(src.normal, dst.normal)
    axis /= np.linalg.norm(axis)
    system = np.stack([src.normal, dst.normal, axis])
    rhs = np.array(
        [
            src.normal @ src.centroid,
            dst.normal @ dst.centroid,
            axis @ (src.centroid + dst.centroid) / 2,
        ]
    )
    pivot = np.linalg.lstsq(system, rhs, rcond=None)[0]
    angle = float(np.arccos(np.clip(cos, -1.0, 1.0)))
    return [rotation_about_line(axis, pivot, a) for a in (angle, angle + np.pi)]


def fold_axes(src: Plane, normal: np.ndarray, across: np.ndarray) -> list[np.ndarray]:
    """Axes (unit, in the plane of unit `normal`) a half turn folding the slab `src` onto a
    piece offset by the in-plane unit direction `across` may turn about. A half turn reflects
    a piece's centroid through its axis, so the axis lies across the centroids' offset; but the
    target's piece is often only part of the slab (the rest merges with static matter), which
    tilts that offset. A door's hinge runs along one of its edges, so the slab's two in-plane
    principal directions are axes too (a square slab has none worth the name: then the offset
    decides, through the scores)."""
    axes = [np.cross(normal, across)]
    for direction in src.axes[:2]:
        in_plane = direction - np.dot(direction, normal) * normal
        if np.linalg.norm(in_plane) > 0.5:
            axes.append(in_plane / np.linalg.norm(in_plane))
    return axes


def _skew_vector(rot: np.ndarray) -> np.ndarray:
    """2 sin(angle) times the unit axis of rotation matrix `rot` (from its skew part)."""
    return np.array([rot[2, 1] - rot[1, 2], rot[0, 2] - rot[2, 0], rot[1, 0] - rot[0, 1]])


def axis_of(rot: np.ndarray) -> np.ndarray:
    """The unit axis of rotation matrix `rot` (sign arbitrary for a half turn)."""
    axis = _skew_vector(rot)
    if np.linalg.norm(axis) < 1e-9:  # no turn, or a half turn: the eigenvector of R + R^T
        axis = np.linalg.eigh(rot + rot.T)[1][:, -1]
    return axis / np.linalg.norm(axis)


def axis_angle_of(rot: np.ndarray) -> tuple[np.ndarray, float]:
    """(unit axis, angle in radians, signed about that axis) of rotation matrix `rot`."""
    axis = axis_of(rot)
    sine = 0.5 * float(axis @ _skew_vector(rot))
    return axis, float(np.arctan2(sine, (np.trace(rot) - 1) / 2))


def edge_hinges(src: Plane, rot: np.ndarray) -> list[RigidMotion]:
    """The rotation `rot` about lines through the two ends of the piece `src` across its axis
    (along its longest principal direction not along the axis): the two sides a hinge can be
    on. Two planes' intersection line misses a door's hinge by about its thickness over
    tan(angle / 2) (it turns about its edge, not its mid-plane), most of its width at small
    angles; a lever turns about one of its ends, not its middle."""
    axis = axis_of(rot)
    for direction in src.axes[:2]:
        across = direction - np.dot(direction, axis) * axis
        if np.linalg.norm(across) > 0.5:
            break
    else:
        return []
    across /= np.linalg.norm(across)
    half = src.width_along(across) / 2
    ends = [src.centroid + side * half * across for side in (-1.0, 1.0)]
    return [(rot, end - rot @ end) for end in ends]


def rod_hinges(src: Plane, dst: Plane) -> list[RigidMotion]:
    """Rotations turning the long piece `src` onto the long piece `dst` (a lever, a handle: no
    plane to intersect): axis d_s x d_t of their longest directions, angle between them (and
    that minus pi: the directions' signs are arbitrary), about the point midway between the
    two lines where they pass closest. Nearly parallel rods give none."""
    ds, dt = src.axes[0], dst.axes[0]
    cross = np.cross(ds, dt)
    if np.linalg.norm(cross) < np.sqrt(1 - PARALLEL_COS**2):
        return []
    axis = cross / np.linalg.norm(cross)
    # Closest points c_s + u d_s and c_t + v d_t of the two lines.
    system = np.stack([ds, -dt], axis=1)
    u, v = np.linalg.lstsq(system, dst.centroid - src.centroid, rcond=None)[0]
    pivot = (src.centroid + u * ds + dst.centroid + v * dt) / 2
    angle = float(np.arccos(np.clip(np.dot(ds, dt), -1.0, 1.0)))
    return [rotation_about_line(axis, pivot, a) for a in (angle, angle - np.pi)]


def correlate(grid: np.ndarray, src: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For every whole-voxel shift d: how many cells of mask `src` land on `grid` when moved by
    d (FFT cross-correlation). Returns the counts and the shift [3] of counts[0, 0, 0]."""
    cells = np.argwhere(src)
    lo, hi = cells.min(0), cells.max(0) + 1
    crop = src[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]].astype(np.float32)
    # The transforms on the executor's threads (GEAR_THREADS); the counts are whole numbers
    # rounded from sums that agree far closer than a half for any thread count.
    with set_workers(_core.cpu_threads()):
        counts = np.rint(
            fftconvolve(grid.astype(np.float32), crop[::-1, ::-1, ::-1], mode="full")
        )
    return counts, -(np.array(crop.shape) - 1) - lo


def settle(
    sample: np.ndarray, rot: np.ndarray, trans: np.ndarray, tree: NearestTree, steps: int
) -> np.ndarray:
    """The translation after `steps` moves of `sample` (turned by `rot`) by the mean offset
    to the nearest centre of `tree` of its nearest 80 % (the part of a piece the target state
    hides, a lid's underside on its base, must not drag the rest)."""
    for _ in range(steps):
        moved = sample @ rot.T + trans
        dist, index = tree.query(moved, k=1)
        near = dist <= np.percentile(dist, 80)
        trans = trans + (tree.data[index[near]] - moved[near]).mean(axis=0)
    return trans


def swept_hinges(
    points: np.ndarray,
    axes: Sequence[np.ndarray],
    starts: Sequence[np.ndarray],
    tree: NearestTree,
    fit: Callable[[np.ndarray, np.ndarray, np.ndarray], float],
    keep: int = SWEEP_KEEP,
    step_deg: float = SWEEP_STEP_DEG,
) -> list[RigidMotion]:
    """Turns of a piece with neither a plane nor a long direction (a stapler's lid that a short
    stage 1 leaves a blob): no two planes or lines to intersect, so each axis direction of
    `axes` (near-duplicates skipped) is swept through every `step_deg`. Each turn first
    puts the piece's centroid on each of `starts` (where target pieces are), then settles its
    translation on the target centres (`tree`, settle): briefly for every turn, longer for the
    best few. The `keep` turns that `fit(points, R, t)` (higher is better, on a sample of the
    centres) scores best are returned as (R, t): a hinge about a line of that direction, plus
    whatever slide along it the scores allow."""
    pts = np.asarray(points, dtype=np.float64)
    centroid = pts.mean(axis=0)
    coarse = pts[:: max(1, len(pts) // SWEEP_SAMPLES)]
    unique: list[np.ndarray] = []
    for axis in axes:
        a = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
        if all(abs(float(a @ b)) < PARALLEL_COS for b in unique):
            unique.append(a)
    scored = []
    for a in unique:
        for angle in np.deg2rad(np.arange(step_deg, 360, step_deg)):
            rot, _ = rotation_about_line(a, np.zeros(3), float(angle))
            for start in starts:
                trans = settle(coarse, rot, np.asarray(start) - rot @ centroid, tree, 2)
                scored.append((fit(coarse, rot, trans), rot, trans))
    scored.sort(key=lambda s: -s[0])
    fine = pts[:: max(1, len(pts) // (4 * SWEEP_SAMPLES))]
    refined = []
    for _, rot, trans in scored[: 3 * keep]:
        trans = settle(fine, rot, trans, tree, SWEEP_SETTLE)
        refined.append((fit(fine, rot, trans), rot, trans))
    refined.sort(key=lambda s: -s[0])
    return [(rot, trans) for _, rot, trans in refined[:keep]]


def refine_turn(
    points: np.ndarray, rot: np.ndarray, trans: np.ndarray, extent: float,
    fit: Callable[..., float], search: TurnSearch = THICK_PIECE_SEARCH,
) -> RigidMotion:
    """The turn (R, t) of `points` refined to a maximum of `fit(points, R, t, width=w)`
    (higher is better; surface_fit): its axis tilted, its pivot moved across the axis and its
    angle changed within the bounds of `search` (Powell's method, on a sample of the centres;
    no slide along the axis is added), coarse to fine over the search's widths. For a piece
    whose plane leaves its normal loose (a thick lid), the intersection of two such planes can
    miss the hinge by tens of degrees, while the surface fit, smooth in the motion, climbs from
    there to the turn that lays the piece on the target's centres."""
    pts = np.asarray(points, dtype=np.float64)
    sample = pts[:: max(1, len(pts) // REFINE_SAMPLES)]
    axis, angle = axis_angle_of(rot)
    pivot = pivot_near(rot, trans, pts.mean(axis=0))
    across = np.linalg.svd(axis[None, :])[2][1:]  # two unit directions square to the axis
    scale = max(extent, 1e-12)
    tilt = np.tan(np.deg2rad(search.tilt_deg))

    def motion(x: np.ndarray) -> RigidMotion:
        # The tilt's two components are bounded together (a cone, not a square's corners).
        lean = x[:2] * min(1.0, tilt / max(float(np.linalg.norm(x[:2])), 1e-300))
        tilted = axis + lean[0] * across[0] + lean[1] * across[1]
        return rotation_about_line(tilted, pivot + scale * (x[2] * across[0] + x[3] * across[1]),
                                   angle + x[4])

    turn = np.deg2rad(search.angle_deg)
    bounds = [(-tilt, tilt)] * 2 + [(-search.pivot, search.pivot)] * 2 + [(-turn, turn)]
    x = np.zeros(5)
    for width in [None if f is None else scale * f for f in search.widths]:
        x = minimize(lambda x, w=width: -fit(sample, *motion(x), width=w), x, method="Powell",
                     bounds=bounds, options={"maxfev": REFINE_EVALUATIONS, "xtol": 1e-3,
                                             "ftol": 1e-4}).x
    return motion(x)


def pivot_near(rot: np.ndarray, trans: np.ndarray, point: np.ndarray) -> np.ndarray:
    """The point of the axis line of the turn x -> R x + t nearest `point`: (I - R) p = t
    holds for every point of the line (t has no part along the axis for a pure turn; the
    least-squares solution drops one that has)."""
    axis = axis_of(rot)
    pivot = np.linalg.lstsq(np.eye(3) - rot, trans, rcond=None)[0]
    return pivot + axis * float(axis @ (point - pivot))


def surface_fit(tree: NearestTree, points: np.ndarray, rot: np.ndarray, trans: np.ndarray,
                width: float) -> float:
    """How closely `points` moved by p -> R p + t lie on the points of `tree`: the mean of
    exp(-(d / width)^2) over their distances d to the nearest. Unlike a count of landed cells
    it varies smoothly with the motion."""
    moved = points @ np.asarray(rot).T + np.asarray(trans)
    dist, _ = tree.query(moved, k=1)
    return float(np.exp(-((dist / width) ** 2)).mean())
