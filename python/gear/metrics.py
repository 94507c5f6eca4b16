"""Evaluation metrics with the definitions used by the articulated-object literature
(docs/evaluation.md).

Joints are compared as start->end motions:
- Axis Ang: angle between axis directions in degrees, folded to [0, 90] (an axis and its
  opposite are the same line).
- Axis Pos: distance between the predicted and ground-truth axis lines, x10 (the field's scale);
  0 for prismatic joints, whose axis has no position.
- Geo Dist: revolute: the rotation angle of R_pred·R_gtᵀ in degrees; prismatic: ‖t_pred − t_gt‖.

Meshes are compared by Chamfer distance over surface samples (squared nearest-neighbour distances,
mean in each direction, summed, x1000). Segmentation by per-part IoU, images by PSNR.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import trimesh
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

AXIS_POS_SCALE = 10.0
CHAMFER_SCALE = 1000.0
PSNR_MAX_DB = 100.0  # reported for identical images instead of +inf
_PARALLEL_SIN = 1e-8  # |d1 x d2| below this: the lines are treated as parallel
JOINT_TYPES = ("revolute", "prismatic")


def _unit(vector: Any, name: str) -> np.ndarray:
    v = np.asarray(vector, dtype=np.float64).reshape(-1)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ValueError(f"{name}: expected 3 finite numbers, got {vector!r}")
    norm = np.linalg.norm(v)
    if norm < 1e-12:
        raise ValueError(f"{name}: zero-length direction")
    return v / norm


def _point(vector: Any, name: str) -> np.ndarray:
    v = np.asarray(vector, dtype=np.float64).reshape(-1)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ValueError(f"{name}: expected 3 finite numbers, got {vector!r}")
    return v


@dataclass(frozen=True)
class Joint:
    """One start->end joint, predicted or ground truth, in a single comparable form."""

    type: str
    axis: np.ndarray  # unit direction
    origin: np.ndarray  # a point on the axis
    amount: float  # degrees (revolute) or distance along `axis` (prismatic)

    @classmethod
    def from_any(cls, joint: Any, name: str = "joint") -> Joint:
        """From a joints.json entry (dict) or a ground-truth joint object (gear.data.GtJoint)."""
        get = joint.get if isinstance(joint, Mapping) else lambda key: getattr(joint, key, None)
        kind = get("type")
        if kind not in JOINT_TYPES:
            raise ValueError(f"{name}: type must be one of {JOINT_TYPES}, got {kind!r}")
        axis = _unit(get("axis"), f"{name}.axis")
        origin_value = get("origin")
        origin = np.zeros(3) if origin_value is None else _point(origin_value, f"{name}.origin")
        if get("amount") is not None:
            amount = get("amount")
        else:
            amount = get("angle_deg") if kind == "revolute" else get("distance")
        if amount is None or not np.isfinite(float(amount)):
            key = "angle_deg" if kind == "revolute" else "distance"
            raise ValueError(f"{name}: missing or non-finite {key}")
        return cls(kind, axis, origin, float(amount))

    @property
    def rotation(self) -> np.ndarray:
        """The start->end rotation (identity for prismatic joints)."""
        if self.type != "revolute":
            return np.eye(3)
        return rotation_matrix(self.axis, self.amount)

    @property
    def translation_vector(self) -> np.ndarray:
        """The start->end translation of a prismatic joint (zero for revolute joints)."""
        return self.axis * self.amount if self.type == "prismatic" else np.zeros(3)


def rotation_matrix(axis: np.ndarray, angle_deg: float) -> np.ndarray:
    """Right-handed rotation by `angle_deg` about the unit `axis` (Rodrigues)."""
    a = _unit(axis, "axis")
    theta = np.deg2rad(angle_deg)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(theta) * k + (1.0 - np.cos(theta)) * (k @ k)


def rotation_angle_deg(rotation: np.ndarray) -> float:
    """The angle in [0, 180] of a rotation matrix, from its trace (clipped against rounding)."""
    cos = np.clip((np.trace(rotation) - 1.0) * 0.5, -1.0, 1.0)
    return float(np.rad2deg(np.arccos(cos)))


def axis_angle_error(axis_a: Any, axis_b: Any) -> float:
    """Angle between two axis directions in degrees, folded to [0, 90]."""
    a, b = _unit(axis_a, "axis_a"), _unit(axis_b, "axis_b")
    angle = float(np.rad2deg(np.arccos(np.clip(np.dot(a, b), -1.0, 1.0))))
    return min(angle, 180.0 - angle)


def line_distance(origin_a: Any, axis_a: Any, origin_b: Any, axis_b: Any) -> float:
    """Shortest distance between two infinite lines (parallel, skew or intersecting)."""
    oa, ob = _point(origin_a, "origin_a"), _point(origin_b, "origin_b")
    da, db = _unit(axis_a, "axis_a"), _unit(axis_b, "axis_b")
    offset = ob - oa
    normal = np.cross(da, db)
    sin = np.linalg.norm(normal)
    if sin < _PARALLEL_SIN:
        # Parallel lines: the offset's component perpendicular to the shared direction.
        return float(np.linalg.norm(np.cross(offset, da)))
    return float(abs(np.dot(offset, normal)) / sin)


def joint_errors(pred: Any, gt: Any) -> dict[str, float]:
    """Axis Ang, Axis Pos (x10) and Geo Dist of a predicted joint against a ground-truth one.

    `pred` is a joints.json entry, `gt` a GtJoint (or either in the other form). When the types
    differ the errors are taken in the ground truth's terms, with the prediction contributing no
    motion of that kind (a prismatic prediction has R = I; a revolute one has t = 0): the error is
    then the whole ground-truth motion, never hidden. `type_match` says which case applies.
    """
    p, g = Joint.from_any(pred, "pred"), Joint.from_any(gt, "gt")
    axis_ang = axis_angle_error(p.axis, g.axis)
    if g.type == "revolute":
        axis_pos = AXIS_POS_SCALE * line_distance(p.origin, p.axis, g.origin, g.axis)
        geo = rotation_angle_deg(p.rotation @ g.rotation.T)
    else:
        axis_pos = 0.0
        geo = float(np.linalg.norm(p.translation_vector - g.translation_vector))
    return {
        "axis_ang": axis_ang,
        "axis_pos": axis_pos,
        "geo_dist": geo,
        "type_match": p.type == g.type,
    }


@dataclass
class Matching:
    """Which predicted joint was matched to each ground-truth joint, and what did not fit."""

    pairs: list[tuple[int, int]]  # (gt index, pred index)
    errors: list[dict[str, float]]  # joint_errors of each pair, same order
    type_mismatches: list[tuple[int, int]] = field(default_factory=list)  # pairs whose types differ
    unmatched_gt: list[int] = field(default_factory=list)  # GT joints with no prediction
    unmatched_pred: list[int] = field(default_factory=list)  # extra predicted joints

    @property
    def count_mismatch(self) -> bool:
        return bool(self.unmatched_gt or self.unmatched_pred)

    def pred_for_gt(self) -> dict[int, int]:
        return {g: p for g, p in self.pairs}


def matching_cost(errors: Mapping[str, float]) -> float:
    """The error summed when choosing a matching: Axis Ang + Axis Pos + Geo Dist."""
    return float(errors["axis_ang"] + errors["axis_pos"] + errors["geo_dist"])


def match_parts(pred_joints: Sequence[Any], gt_joints: Sequence[Any]) -> Matching:
    """Match predicted joints to ground-truth joints.

    Among all one-to-one assignments, those with the fewest type disagreements win; among them,
    the one with the smallest summed error (matching_cost). The optimum is exact (Hungarian
    algorithm on a cost whose type term outweighs any possible error sum), which equals the
    exhaustive search over permutations. Counts may differ: extra joints on either side are
    listed as unmatched.
    """
    # Validate every joint up front so a bad one is named by its index.
    pred_joints = [Joint.from_any(p, f"joints[{i}]") for i, p in enumerate(pred_joints)]
    gt_joints = [Joint.from_any(g, f"gt joint {i}") for i, g in enumerate(gt_joints)]
    n_gt, n_pred = len(gt_joints), len(pred_joints)
    if n_gt == 0 or n_pred == 0:
        return Matching([], [], [], list(range(n_gt)), list(range(n_pred)))
    table = [[joint_errors(p, g) for p in pred_joints] for g in gt_joints]
    cost = np.array([[matching_cost(e) for e in row] for row in table])
    mismatch = np.array([[0.0 if e["type_match"] else 1.0 for e in row] for row in table])
    # Any assignment's error sum is below cost.sum() + 1, so one type disagreement costs more.
    penalty = cost.sum() + 1.0
    rows, cols = linear_sum_assignment(cost + penalty * mismatch)
    pairs = sorted(zip(rows.tolist(), cols.tolist(), strict=True))
    return _matching(pairs, [table[g][p] for g, p in pairs],
                     unmatched_gt=sorted(set(range(n_gt)) - set(rows.tolist())),
                     unmatched_pred=sorted(set(range(n_pred)) - set(cols.tolist())))


def _matching(pairs: list[tuple[int, int]], errors: list[dict[str, float]],
              unmatched_gt: list[int], unmatched_pred: list[int]) -> Matching:
    """A Matching of `pairs` with their `errors`, its type mismatches read off the errors."""
    return Matching(
        pairs=pairs, errors=errors,
        type_mismatches=[(g, p) for (g, p), e in zip(pairs, errors, strict=True)
                         if not e["type_match"]],
        unmatched_gt=unmatched_gt, unmatched_pred=unmatched_pred,
    )


# Ground-truth joints whose errors against each other all lie below these are one motion (two
# drawers of a column pulled by the same travel along the same axis: a slide has no position):
# no joint error tells which of their predictions is which.
SAME_MOTION_TOLERANCE = {"axis_ang": 1e-3, "axis_pos": 1e-4, "geo_dist": 1e-4}


def same_motion_groups(gt_joints: Sequence[Any]) -> list[list[int]]:
    """Groups (of two or more) of ground-truth joints that are one motion, each in index
    order (SAME_MOTION_TOLERANCE; types equal)."""
    joints = [Joint.from_any(g, f"gt joint {i}") for i, g in enumerate(gt_joints)]
    groups: list[list[int]] = []
    for i, joint in enumerate(joints):
        for group in groups:
            errors = joint_errors(joint, joints[group[0]])
            if errors["type_match"] and all(errors[k] <= tol
                                            for k, tol in SAME_MOTION_TOLERANCE.items()):
                group.append(i)
                break
        else:
            groups.append([i])
    return [g for g in groups if len(g) > 1]


def untie_same_motions(matching: Matching, pred_joints: Sequence[Any], gt_joints: Sequence[Any],
                       pred_centres: Mapping[int, np.ndarray],
                       gt_centres: Mapping[int, np.ndarray]) -> Matching:
    """`matching` with the predictions matched to each group of ground-truth joints that are
    one motion (same_motion_groups) reassigned among that group by where the parts are: the
    assignment with the smallest summed distance between predicted and true part centres
    (`pred_centres` by prediction index, `gt_centres` by GT joint index). A group with a part
    whose centre is missing, or with fewer than two matched joints, is left as it is."""
    pred_for = matching.pred_for_gt()
    for group in same_motion_groups(gt_joints):
        members = [g for g in group if g in pred_for]
        if len(members) < 2 or any(g not in gt_centres or pred_for[g] not in pred_centres
                                   for g in members):
            continue
        preds = [pred_for[g] for g in members]
        distance = np.array([[np.linalg.norm(np.asarray(pred_centres[p]) - gt_centres[g])
                              for p in preds] for g in members])
        rows, cols = linear_sum_assignment(distance)
        pred_for.update({members[r]: preds[c] for r, c in zip(rows, cols, strict=True)})
    if pred_for == matching.pred_for_gt():
        return matching
    pairs = sorted(pred_for.items())
    pred = [Joint.from_any(p, f"joints[{i}]") for i, p in enumerate(pred_joints)]
    gt = [Joint.from_any(g, f"gt joint {i}") for i, g in enumerate(gt_joints)]
    return _matching(pairs, [joint_errors(pred[p], gt[g]) for g, p in pairs],
                     matching.unmatched_gt, matching.unmatched_pred)


def sample_surface(mesh: trimesh.Trimesh, n: int, seed: int) -> np.ndarray:
    """`n` points uniformly distributed over the mesh surface (area-weighted), reproducibly."""
    if mesh is None or len(mesh.faces) == 0 or mesh.area <= 0:
        raise ValueError("cannot sample an empty mesh (no faces or zero area)")
    points, _ = trimesh.sample.sample_surface(mesh, n, seed=seed)
    return np.asarray(points, dtype=np.float64)


def chamfer_points(a: np.ndarray, b: np.ndarray) -> float:
    """Mean squared nearest-neighbour distance a->b plus b->a, x1000."""
    d_ab, _ = cKDTree(b).query(a, k=1)
    d_ba, _ = cKDTree(a).query(b, k=1)
    return float(CHAMFER_SCALE * (np.mean(d_ab**2) + np.mean(d_ba**2)))


def chamfer(mesh_a: trimesh.Trimesh, mesh_b: trimesh.Trimesh, n: int = 10000,
            seed: int = 0) -> float:
    """Chamfer distance x1000 between two meshes over `n` surface samples each.

    Sampling sets a floor even for identical meshes: on a surface with n samples per area A, the
    mean squared distance to the nearest sample is about A/(πn) per direction.
    """
    if n < 1:
        raise ValueError(f"n must be positive, got {n}")
    a = sample_surface(mesh_a, n, seed)
    b = sample_surface(mesh_b, n, seed + 1)  # independent samples, as two separate meshes get
    return chamfer_points(a, b)


@dataclass
class IouAccumulator:
    """Per-label intersection and union counts summed over many label images."""

    ignore: int = 255  # background label: not a class, but predicted parts there count in unions
    intersection: dict[int, int] = field(default_factory=dict)
    union: dict[int, int] = field(default_factory=dict)

    def add(self, pred: np.ndarray, gt: np.ndarray) -> None:
        pred, gt = np.asarray(pred), np.asarray(gt)
        if pred.shape != gt.shape:
            raise ValueError(f"label images differ in shape: pred {pred.shape} vs gt {gt.shape}")
        labels = set(np.unique(gt).tolist()) | set(np.unique(pred).tolist())
        for label in sorted(labels - {self.ignore}):
            p, g = pred == label, gt == label
            self.intersection[label] = self.intersection.get(label, 0) + int(np.sum(p & g))
            self.union[label] = self.union.get(label, 0) + int(np.sum(p | g))

    def per_label(self, labels: Iterable[int] | None = None) -> dict[int, float]:
        """IoU of each label (default: every label seen), 0 for a label seen in one side only."""
        keys = sorted(self.union) if labels is None else list(labels)
        return {k: (self.intersection.get(k, 0) / self.union[k]) if self.union.get(k) else 0.0
                for k in keys}


def part_iou(pred: np.ndarray | Sequence[np.ndarray], gt: np.ndarray | Sequence[np.ndarray],
             ignore: int = 255) -> dict[str, Any]:
    """Part-segmentation IoU of label images (one image or lists of them, counts pooled).

    Returns {"per_part": {label: IoU}, "mean": mean over the labels present in the ground truth}.
    `ignore` is the background label; a part predicted on background still enlarges that part's
    union (it is a false positive).
    """
    preds = [pred] if isinstance(pred, np.ndarray) else list(pred)
    gts = [gt] if isinstance(gt, np.ndarray) else list(gt)
    if len(preds) != len(gts):
        raise ValueError(f"got {len(preds)} predicted and {len(gts)} ground-truth label images")
    acc = IouAccumulator(ignore=ignore)
    gt_labels: set[int] = set()
    for p, g in zip(preds, gts, strict=True):
        acc.add(p, g)
        gt_labels |= set(np.unique(g).tolist()) - {ignore}
    per_part = acc.per_label(sorted(gt_labels))
    mean = float(np.mean(list(per_part.values()))) if per_part else 0.0
    return {"per_part": per_part, "mean": mean}


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None,
         max_value: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB of images in [0, max_value] ([H,W] or [H,W,C]).

    With `mask` ([H,W], bool or weights > 0.5), only those pixels count. Identical images give
    PSNR_MAX_DB instead of infinity.
    """
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if a.shape != b.shape:
        raise ValueError(f"images differ in shape: {a.shape} vs {b.shape}")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        raise ValueError("images contain non-finite values")
    sq = (a - b) ** 2
    if mask is not None:
        m = np.asarray(mask)
        if m.shape != a.shape[:2]:
            raise ValueError(f"mask shape {m.shape} does not match image {a.shape[:2]}")
        m = m > 0.5 if m.dtype != bool else m
        if not m.any():
            raise ValueError("mask selects no pixels")
        sq = sq[m]
    mse = float(np.mean(sq))
    if mse <= max_value**2 * 10 ** (-PSNR_MAX_DB / 10):
        return PSNR_MAX_DB
    return float(10.0 * np.log10(max_value**2 / mse))
