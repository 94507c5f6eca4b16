"""Ground truth of a scene (any layout): `gt/trans.json` joints and the GT meshes beside it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from gear.data.files import Reader, finite_vector
from gear.data.scene import STATES, GroundTruth, GtJoint


def gt_mesh_files(state: str, n_parts: int) -> dict[str, str]:
    """GT mesh names: key ("whole", "static", "part_i") -> file under gt/{state}/."""
    names = {"whole": f"{state}_rotate.ply", "static": f"{state}_static_rotate.ply"}
    if n_parts == 1:
        names["part_0"] = f"{state}_dynamic_rotate.ply"
    else:
        names.update({f"part_{i}": f"{state}_dynamic_{i}_rotate.ply" for i in range(n_parts)})
    return names


def load_gt(reader: Reader) -> GroundTruth | None:
    path = reader.root / "gt" / "trans.json"
    if not path.is_file():
        return None
    meta = reader.read_json(path)
    if meta is None:
        return None
    if not isinstance(meta, dict) or not isinstance(meta.get("trans_info"), list):
        reader.problem(path, "needs a 'trans_info' list")
        return None
    joints: list[GtJoint] = []
    for i, info in enumerate(meta["trans_info"]):
        joint = parse_joint(info)
        if isinstance(joint, str):
            reader.problem(path, f"trans_info[{i}]: {joint}")
        else:
            joints.append(joint)
    meshes: dict[str, dict[str, Path]] = {}
    for state in STATES:
        files = gt_mesh_files(state, len(joints))
        present = {
            key: reader.root / "gt" / state / name
            for key, name in files.items()
            if (reader.root / "gt" / state / name).is_file()
        }
        if present:
            meshes[state] = present
    return GroundTruth(joints, meshes)


def parse_joint(info: Any) -> GtJoint | str:
    """A GtJoint, or a description of what the trans_info entry lacks."""
    if not isinstance(info, dict):
        return "must be an object"
    axis = info.get("axis")
    if not isinstance(axis, dict):
        return "missing 'axis' with 'o' and 'd'"
    origin, direction = finite_vector(axis.get("o"), 3), finite_vector(axis.get("d"), 3)
    if origin is None:
        return "axis.o must be 3 finite numbers"
    if direction is None or np.linalg.norm(direction) < 1e-12:
        return "axis.d must be 3 finite numbers, not all zero"
    kind = info.get("type")
    if kind not in ("rotate", "translate"):
        return f"type must be 'rotate' or 'translate', got {kind!r}"
    limits = info.get(kind)
    if not isinstance(limits, dict):
        return f"missing '{kind}' with 'l' and 'r'"
    lr = finite_vector([limits.get("l"), limits.get("r")], 2) if "l" in limits else None
    if lr is None:
        return f"'{kind}' needs finite numbers 'l' and 'r'"
    scale = 1.0 if kind == "rotate" else float(np.linalg.norm(direction))
    return GtJoint(
        "revolute" if kind == "rotate" else "prismatic",
        origin,
        direction,
        float(lr[1] - lr[0]) * scale,
        float(lr[0]) * scale,
    )
