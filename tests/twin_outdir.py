"""Hand-made trained OUT_DIRs shared by the twin and export tests: a toy of boxes, and the
ground truth of a built-in object (`make_gt_out_dir`).

The toy (`make_out_dir`): three parts around the origin, a static box (part 0, blue), a
door (part 1, red) hinged on a vertical axis at one edge of the box, turning 70 degrees, and a
drawer (part 2, green) sliding 0.2 along +x. The canonical Gaussians go through the trainer's
own PLY writer, so the twin reads exactly what training writes.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
import trimesh
from scipy.spatial.transform import Rotation

from gear.camera import Camera
from gear.outputs import write_ply
from gear.run_folder import COMPLETE, write_atomic
from gear.splats import Gaussians
from gear.splats.sh import SH_PARAM

HINGE = {"part": 1, "type": "revolute", "axis": [0.0, 0.0, 1.0], "origin": [0.25, -0.25, 0.1],
         "angle_deg": 70.0, "distance": 0.0}
SLIDE = {"part": 2, "type": "prismatic", "axis": [0.6, 0.8, 0.0], "origin": [0.0, 0.0, 0.0],
         "angle_deg": 0.0, "distance": 0.2}
COLORS = np.array([[0.1, 0.2, 0.9], [0.95, 0.1, 0.1], [0.1, 0.9, 0.2]])


def joint_matrix(joint: dict, fraction: float) -> np.ndarray:
    """4x4 start -> `fraction` motion by Rodrigues (scipy), independent of gear's kinematics."""
    out = np.eye(4)
    axis = np.asarray(joint["axis"], dtype=np.float64)
    axis /= np.linalg.norm(axis)
    if joint["type"] == "prismatic":
        out[:3, 3] = axis * joint["distance"] * fraction
        return out
    rot = Rotation.from_rotvec(axis * np.deg2rad(joint["angle_deg"] * fraction)).as_matrix()
    origin = np.asarray(joint["origin"], dtype=np.float64)
    out[:3, :3], out[:3, 3] = rot, origin - rot @ origin
    return out


def _grid(lo: list[float], hi: list[float], n: list[int]) -> np.ndarray:
    axes = [np.linspace(a, b, k) for a, b, k in zip(lo, hi, n, strict=True)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


# Start-state boxes (min corner, max corner) of each part.
BOXES = [
    ([-0.25, -0.25, -0.2], [0.25, 0.25, 0.1]),  # static body
    ([-0.25, -0.27, 0.1], [0.25, -0.25, 0.4]),  # door: a thin panel above, hinged at x=0.25
    ([-0.2, -0.2, -0.35], [0.2, 0.2, -0.2]),  # drawer below
]


def start_points() -> tuple[np.ndarray, np.ndarray]:
    """(points [N,3], part ids [N]) of the start state."""
    pts = [_grid(lo, hi, [7, 7, 5]) for lo, hi in BOXES]
    ids = np.concatenate([np.full(len(p), k) for k, p in enumerate(pts)])
    return np.concatenate(pts), ids


def moved(points: np.ndarray, parts: np.ndarray, fraction: float) -> np.ndarray:
    """Start-state points moved by `fraction` of every part's joint (reference motion)."""
    out = points.copy()
    for k, joint in ((1, HINGE), (2, SLIDE)):
        m = joint_matrix(joint, fraction)
        out[parts == k] = points[parts == k] @ m[:3, :3].T + m[:3, 3]
    return out


def toy_gaussians(canonical: str = "start", seed: int = 0, sh_degree: int = 0) -> Gaussians:
    """The toy's trained Gaussians in the `canonical` state (part logits included); with
    `sh_degree` > 0 they carry SH bands 1..sh_degree (random per part, jittered)."""
    rng = np.random.default_rng(seed)
    points, parts = start_points()
    canon = points if canonical == "start" else moved(points, parts, 1.0)
    n = len(points)
    quats = rng.normal(size=(n, 4))
    rgb = np.clip(COLORS[parts] + rng.uniform(-0.05, 0.05, (n, 3)), 0.02, 0.98)
    logits = np.full((n, 3), -5.0)
    logits[np.arange(n), parts] = 5.0
    g = Gaussians({
        "means": torch.tensor(canon, dtype=torch.float32),
        "quats": torch.tensor(quats / np.linalg.norm(quats, axis=1, keepdims=True),
                              dtype=torch.float32),
        "log_scales": torch.full((n, 3), float(np.log(0.04))),
        "opacity": torch.full((n,), 4.0),
        "colors": torch.tensor(np.log(rgb / (1 - rgb)), dtype=torch.float32),
        "logits": torch.tensor(logits, dtype=torch.float32),
    })
    if sh_degree:
        # One view-dependent sheen per part (as one material would give), a little jitter.
        bands = (sh_degree + 1) ** 2 - 1
        rest = rng.normal(0.0, 0.2, (3, bands, 3))[parts] + rng.normal(0.0, 0.02, (n, bands, 3))
        g.add_param(SH_PARAM, torch.tensor(rest, dtype=torch.float32), 0.0)
    return g


def make_out_dir(root: Path, canonical: str = "start", seed: int = 0,
                 sh_degree: int = 0) -> Path:
    """Writes joints.json, gaussians_canonical.ply (the toy_gaussians), parts.npy and
    meshes/{start,end}/*.ply."""
    _, parts = start_points()
    g = toy_gaussians(canonical, seed, sh_degree)
    root.mkdir(parents=True, exist_ok=True)
    write_ply(root / "gaussians_canonical.ply", g)
    np.save(root / "parts.npy", parts.astype(np.int64))
    (root / "joints.json").write_text(json.dumps({"canonical": canonical,
                                                  "joints": [HINGE, SLIDE]}, indent=2))
    for state, fraction in (("start", 0.0), ("end", 1.0)):
        folder = root / "meshes" / state
        folder.mkdir(parents=True, exist_ok=True)
        for k, name in enumerate(["static", "part_0", "part_1"]):
            lo, hi = np.asarray(BOXES[k][0]), np.asarray(BOXES[k][1])
            box = trimesh.creation.box(extents=hi - lo)
            box.apply_translation((lo + hi) / 2)
            if k:
                box.apply_transform(joint_matrix((HINGE, SLIDE)[k - 1], fraction))
            box.export(folder / f"{name}.ply")
    write_atomic(root / COMPLETE, "{}\n")  # a finished run, as train's last write
    return root


def front_camera(res: int = 48) -> Camera:
    """A camera above the door side (-y), seeing the whole object and the door swing."""
    return Camera.look_at(np.array([0.0, -1.2, 1.8]), np.zeros(3), np.array([0.0, 0.0, 1.0]),
                          np.deg2rad(45.0), res, res)


def make_gt_out_dir(root: Path, object_name: str, seed: int = 0,
                    gaussians_per_part: int = 3000) -> Path:
    """A run folder built from the ground truth of the built-in object `object_name`: its exact
    joints, its GT part meshes as meshes/{start,end}/*.ply, and Gaussians sampled on the
    start-state surfaces with the surfaces' colours (canonical state: start)."""
    from gear.synth.objects import build

    obj = build(object_name, seed)
    rng = np.random.default_rng(seed)
    means, colors, parts = [], [], []
    for k, surfaces in enumerate(obj.posed("start")):
        mesh = trimesh.util.concatenate([trimesh.Trimesh(s.vertices, s.faces, process=False)
                                         for s in surfaces])
        face_colors = np.concatenate([s.colors for s in surfaces])
        points, faces = trimesh.sample.sample_surface(mesh, gaussians_per_part, seed=seed + k)
        means.append(points)
        colors.append(face_colors[faces])
        parts.append(np.full(len(points), k))
    means_np, parts_np = np.concatenate(means), np.concatenate(parts)
    rgb = np.clip(np.concatenate(colors), 0.02, 0.98)
    n = len(means_np)
    logits = np.full((n, len(obj.parts) + 1), -5.0)
    logits[np.arange(n), parts_np] = 5.0
    quats = rng.normal(size=(n, 4))
    g = Gaussians({
        "means": torch.tensor(means_np, dtype=torch.float32),
        "quats": torch.tensor(quats / np.linalg.norm(quats, axis=1, keepdims=True),
                              dtype=torch.float32),
        "log_scales": torch.full((n, 3), float(np.log(0.006))),
        "opacity": torch.full((n,), 4.0),
        "colors": torch.tensor(np.log(rgb / (1 - rgb)), dtype=torch.float32),
        "logits": torch.tensor(logits, dtype=torch.float32),
    })
    root.mkdir(parents=True, exist_ok=True)
    write_ply(root / "gaussians_canonical.ply", g)
    np.save(root / "parts.npy", parts_np.astype(np.int64))
    joints = []
    for k, part in enumerate(obj.parts, start=1):
        gt = part.joint.gt()
        joints.append({"part": k, "type": gt.type, "axis": gt.axis.tolist(),
                       "origin": gt.origin.tolist(),
                       "angle_deg": gt.amount if gt.type == "revolute" else 0.0,
                       "distance": gt.amount if gt.type == "prismatic" else 0.0})
    (root / "joints.json").write_text(json.dumps({"canonical": "start", "joints": joints},
                                                 indent=2))
    for state in ("start", "end"):
        folder = root / "meshes" / state
        folder.mkdir(parents=True, exist_ok=True)
        for name, mesh in obj.gt_meshes(state).items():
            mesh.export(folder / f"{name}.ply")
    write_atomic(root / COMPLETE, "{}\n")  # a finished run, as train's last write
    return root
