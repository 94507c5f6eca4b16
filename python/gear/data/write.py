"""Write a scene in the ArtGS/GEAR layout (the generator's output, and round-trip tests)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import trimesh
from PIL import Image

from gear.data.artgs import transforms_name
from gear.data.files import DEPTH_SCALE
from gear.data.gt import gt_mesh_files
from gear.data.scene import GtJoint, View

MAX_DEPTH_M = np.iinfo(np.uint16).max / DEPTH_SCALE
PNG_LEVEL = 1  # fast zlib level: ~3x faster writes than the default for ~30% larger files


def _to_u8(x: np.ndarray) -> np.ndarray:
    return (np.clip(x, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def write_view(root: Path, view: View) -> str:
    """Write one view's images; returns its rgba path relative to `root`."""
    state, split, index = view.name.split("/")
    base = Path(state) / split
    rgba = np.concatenate([_to_u8(view.rgb), _to_u8(view.alpha)[..., None]], axis=-1)
    rel = base / "rgba" / f"{index}.png"
    (root / rel).parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(rgba, "RGBA").save(root / rel, compress_level=PNG_LEVEL)
    if view.depth is not None:
        depth = np.nan_to_num(view.depth, nan=0.0, posinf=0.0, neginf=0.0)
        if depth.max(initial=0.0) > MAX_DEPTH_M:
            raise ValueError(
                f"{view.name}: depth beyond {MAX_DEPTH_M:.1f} m does not fit uint16 mm"
            )
        mm = np.round(np.clip(depth, 0.0, None) * DEPTH_SCALE).astype(np.uint16)
        (root / base / "depth").mkdir(parents=True, exist_ok=True)
        Image.fromarray(mm).save(root / base / "depth" / f"{index}.png", compress_level=PNG_LEVEL)
    if view.regions is not None:
        if view.regions.max(initial=0) > np.iinfo(np.uint16).max or view.regions.min(initial=0) < 0:
            raise ValueError(f"{view.name}: region ids must fit uint16")
        (root / base / "mask").mkdir(parents=True, exist_ok=True)
        np.save(root / base / "mask" / f"{index}.npy", view.regions.astype(np.uint16))
    if view.parts is not None:
        (root / base / "parts").mkdir(parents=True, exist_ok=True)
        Image.fromarray(view.parts.astype(np.uint8), "L").save(
            root / base / "parts" / f"{index}.png"
        )
    return rel.as_posix()


def write_transforms(root: Path, state: str, split: str, views: list[View]) -> None:
    """transforms_{split}_{state}.json; all views of one file share the intrinsics."""
    first = views[0].camera
    for v in views[1:]:
        c = v.camera
        if (c.width, c.height, c.fx, c.fy) != (first.width, first.height, first.fx, first.fy):
            raise ValueError(f"{v.name}: intrinsics differ from {views[0].name}")
    meta: dict = {"camera_angle_x": first.camera_angle_x}
    if abs(first.fx - first.fy) > 1e-9 * first.fx:
        meta["camera_angle_y"] = first.camera_angle_y
    time = 0.0 if state == "start" else 1.0
    meta["frames"] = [
        {
            "file_path": write_view(root, v),
            "time": time,
            "transform_matrix": v.camera.to_blender().tolist(),
        }
        for v in views
    ]
    (root / transforms_name(split, state)).write_text(json.dumps(meta, indent=1))


def trans_info(joints: list[GtJoint]) -> dict:
    """gt/trans.json content: l = start value, r = end value, d unit."""
    entries = []
    for j in joints:
        kind = "rotate" if j.type == "revolute" else "translate"
        entries.append(
            {
                "axis": {"o": j.origin.tolist(), "d": j.axis.tolist()},
                "type": kind,
                kind: {"l": j.start, "r": j.start + j.amount},
            }
        )
    return {"trans_info": entries}


def write_scene(
    root: str | Path,
    views: dict[str, dict[str, list[View]]],
    joints: list[GtJoint] | None = None,
    meshes: dict[str, dict[str, trimesh.Trimesh]] | None = None,
    meta: dict | None = None,
) -> Path:
    """Write views (state -> split -> views), optional GT joints and GT meshes
    (state -> {"whole", "static", "part_i"} -> mesh) and optional generator metadata
    (`synth.json`, not part of the format; it records how the scene was made)."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    for state, splits in views.items():
        for split, vs in splits.items():
            if vs:
                write_transforms(root, state, split, vs)
    if joints is not None:
        (root / "gt").mkdir(exist_ok=True)
        (root / "gt" / "trans.json").write_text(json.dumps(trans_info(joints), indent=1))
    for state, named in (meshes or {}).items():
        files = gt_mesh_files(state, len(joints or []))
        (root / "gt" / state).mkdir(parents=True, exist_ok=True)
        for key, mesh in named.items():
            if key not in files:
                raise ValueError(f"GT mesh key {key!r} is not one of {sorted(files)}")
            mesh.export(root / "gt" / state / files[key])
    if meta is not None:
        (root / "synth.json").write_text(json.dumps(meta, indent=1))
    return root
