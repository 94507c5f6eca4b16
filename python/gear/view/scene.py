"""What the viewer shows, as plain arrays: per-part Gaussians and meshes in the start state, each
joint's axis, and the rigid pose of a part at any joint value.

Everything is expressed in the start state (s = 0), so moving a part to a joint value is one
rigid transform of its scene node: the same `TwinJoint.motion` that `Twin.pose` and
`gear render` use, so the viewer, the renders and the URDF agree on every intermediate state.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh

from gear.commands.render import part_colors
from gear.kinematics import quat_from_matrix, quat_to_matrix
from gear.twin import Twin, TwinJoint

AXIS_LENGTH = 0.8  # a revolute axis is drawn this fraction of the object's radius either side
MIN_TRAVEL = 0.3  # a prismatic axis is drawn at least this fraction of the radius long


@dataclass(frozen=True)
class PartSplats:
    """The Gaussians of one part at the start state (float32 arrays)."""

    part: int
    centers: np.ndarray  # [n,3]
    covariances: np.ndarray  # [n,3,3]
    rgb: np.ndarray  # [n,3] trained colours
    part_rgb: np.ndarray  # [n,3] the part's flat colour (as `gear render --color parts`)
    opacities: np.ndarray  # [n,1] in [0, 1]


def covariances(quats: torch.Tensor, log_scales: torch.Tensor) -> torch.Tensor:
    """[N,3,3] world covariances R diag(scale^2) R^T of Gaussians (quats w,x,y,z, any norm)."""
    rot = quat_to_matrix(quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12))
    return rot @ torch.diag_embed(torch.exp(2.0 * log_scales)) @ rot.transpose(-1, -2)


def part_splats(twin: Twin) -> list[PartSplats]:
    """One entry per part that holds Gaussians, ordered by part id."""
    means, quats = twin.pose(0.0)
    cov = covariances(quats.double(), twin.log_scales.double()).float().numpy()
    means, parts = means.numpy(), twin.parts.numpy()
    rgb, opacity = twin.rgb.numpy(), torch.sigmoid(twin.opacity).numpy()[:, None]
    flat = part_colors(parts)
    out = []
    for k in range(twin.num_parts):
        sel = parts == k
        if sel.any():
            out.append(PartSplats(k, means[sel], cov[sel], rgb[sel], flat[sel], opacity[sel]))
    return out


def joint_fraction(joint: TwinJoint, value: float) -> float:
    """The fraction of the start -> end motion at joint value `value` (degrees for a revolute
    joint, distance for a prismatic one, counted from the start state)."""
    return value / joint.amount if joint.amount else 0.0


def part_pose(joint: TwinJoint, fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """(wxyz [4], position [3]) float64: the scene-node transform moving the part's start-state
    geometry by `fraction` of its joint's motion."""
    rot, t = joint.motion(fraction)
    return quat_from_matrix(torch.as_tensor(rot)).numpy(), t


def axis_segment(joint: TwinJoint, part_center: np.ndarray, center: np.ndarray,
                 radius: float) -> np.ndarray:
    """[2,3] end points drawing a joint: a revolute axis as its line through the point nearest
    the object's centre; a prismatic axis from the part's start centre along its travel."""
    if joint.type == "revolute":
        foot = joint.origin + np.dot(center - joint.origin, joint.axis) * joint.axis
        half = AXIS_LENGTH * radius * joint.axis
        return np.stack([foot - half, foot + half])
    travel = joint.amount if abs(joint.amount) >= MIN_TRAVEL * radius else (
        np.copysign(MIN_TRAVEL * radius, joint.amount))
    return np.stack([part_center, part_center + travel * joint.axis])


def part_meshes(out_dir: Path, num_parts: int) -> dict[int, trimesh.Trimesh]:
    """Start-state TSDF meshes by part id (meshes/start/static.ply, part_<k-1>.ply); parts
    without a mesh file, or with an empty one, are left out."""
    folder = Path(out_dir) / "meshes" / "start"
    out = {}
    for k in range(num_parts):
        path = folder / ("static.ply" if k == 0 else f"part_{k - 1}.ply")
        if not path.is_file():
            continue
        mesh = trimesh.load(path, force="mesh")
        if len(mesh.faces):
            out[k] = mesh
    return out
