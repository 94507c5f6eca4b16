"""What an export reads from a trained run: joints, part meshes and Gaussians, all in the START
state (joint value 0), which is the state every exported file is written in."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import trimesh

from gear.twin import Twin, TwinError, TwinJoint

EXPORT_STATE = "start"  # every export file holds the object in this state (joint value 0)


@dataclass
class PartSource:
    """One part of the twin in the start state."""

    name: str  # "static" | "part_<i>" (the run's mesh file names)
    mesh: trimesh.Trimesh | None  # None when the run's mesh is empty
    means: np.ndarray  # [M,3] float64 Gaussian centres of this part
    rgb: np.ndarray  # [M,3] in [0,1]
    opacity: np.ndarray  # [M] in (0,1)
    index: np.ndarray  # [M] rows of the part's Gaussians in the twin


@dataclass
class RunSource:
    """A trained run read for export: the twin (canonical Gaussians), its joints with
    non-negative amounts, and every part in the start state."""

    twin: Twin
    joints: list[TwinJoint]  # joints[i] moves parts[i + 1]
    parts: list[PartSource]
    notes: list[str] = field(default_factory=list)


def positive_amount(joint: TwinJoint) -> TwinJoint:
    """The same motion with a non-negative amount (a negative one flips the axis)."""
    if joint.amount >= 0:
        return joint
    return TwinJoint(joint.part, joint.type, -joint.axis, joint.origin, -joint.amount)


def _load_mesh(path: Path) -> trimesh.Trimesh | None:
    """The triangles in `path` (None when the file holds none); a broken file is an error."""
    try:
        loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as err:  # trimesh raises many exception kinds for broken files
        raise TwinError(f"{path}: unreadable mesh ({err})") from None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        return None
    if not np.all(np.isfinite(loaded.vertices)):
        raise TwinError(f"{path}: mesh has non-finite vertices")
    return loaded


def _start_mesh(out_dir: Path, name: str, joint: TwinJoint | None,
                notes: list[str]) -> trimesh.Trimesh | None:
    """meshes/start/<name>.ply, else the end-state file moved back along its joint."""
    start, end = (out_dir / "meshes" / s / f"{name}.ply" for s in ("start", "end"))
    if start.is_file():
        return _load_mesh(start)
    if not end.is_file():
        raise TwinError(f"{start}: missing (and no {end} either): the part meshes of a "
                        "trained run")
    mesh = _load_mesh(end)
    if mesh is not None and joint is not None:
        rot, t = joint.motion(-1.0)
        matrix = np.eye(4)
        matrix[:3, :3], matrix[:3, 3] = rot, t
        mesh.apply_transform(matrix)
    notes.append(f"{name}: no start-state mesh, used {end} moved back to the start state")
    return mesh


def load_run(out_dir: str | Path) -> RunSource:
    """Reads OUT_DIR (joints.json, the canonical Gaussians, part ids, part meshes); a missing
    or malformed file raises TwinError naming it."""
    out_dir = Path(out_dir)
    twin = Twin.load(out_dir)
    joints = [positive_amount(j) for j in twin.joints]
    means, _ = twin.pose(0.0)
    means_np = means.double().numpy()
    rgb = twin.rgb.double().numpy()
    opacity = torch.sigmoid(twin.opacity).double().numpy()
    ids = twin.parts.numpy()
    notes: list[str] = []
    parts = []
    for k in range(twin.num_parts):
        name = "static" if k == 0 else f"part_{k - 1}"
        mesh = _start_mesh(out_dir, name, joints[k - 1] if k else None, notes)
        if mesh is None:
            notes.append(f"{name}: its mesh is empty, the link has no visual, collision or mass")
        rows = np.flatnonzero(ids == k)
        parts.append(PartSource(name, mesh, means_np[rows], rgb[rows], opacity[rows], rows))
    return RunSource(twin, joints, parts, notes)
