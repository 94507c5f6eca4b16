"""The ArtGS/GEAR layout: `transforms_{split}_{state}.json` at the root, RGBA images (alpha =
object mask) with depth/mask/parts companions beside them (docs/scenes.md)."""

from __future__ import annotations

from pathlib import Path, PurePosixPath

import numpy as np

from gear.camera import Camera
from gear.data.files import Reader
from gear.data.scene import SPLITS, STATES, View

NAME = "ArtGS/GEAR (transforms_{split}_{state}.json)"


def transforms_name(split: str, state: str) -> str:
    return f"transforms_{split}_{state}.json"


def detect(root: Path) -> bool:
    return any((root / transforms_name(sp, st)).is_file() for sp in SPLITS for st in STATES)


def companion_path(rgba_path: PurePosixPath, kind: str) -> PurePosixPath | None:
    """The depth/mask/parts file that sits next to an `.../rgba/NNNN.png` image (None if the
    image is not in an `rgba` folder, so the scene has no companions)."""
    parts = list(rgba_path.parts)
    if "rgba" not in parts:
        return None
    i = len(parts) - 1 - parts[::-1].index("rgba")
    parts[i] = kind
    suffix = ".npy" if kind == "mask" else ".png"
    return PurePosixPath(*parts).with_suffix(suffix)


def load(reader: Reader, splits: tuple[str, ...]) -> dict[str, dict[str, list[View]]]:
    return {
        state: {split: _load_split(reader, state, split, split == "train") for split in splits}
        for state in STATES
    }


def _load_split(reader: Reader, state: str, split: str, required: bool) -> list[View]:
    json_path = reader.root / transforms_name(split, state)
    if not json_path.is_file():
        if required:
            reader.problem(json_path, "missing")
        return []
    meta = reader.read_json(json_path)
    if meta is None:
        return []
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list):
        reader.problem(json_path, "needs a 'frames' list")
        return []
    angle_x, angle_y = meta.get("camera_angle_x"), meta.get("camera_angle_y")
    for name, angle in (("camera_angle_x", angle_x), ("camera_angle_y", angle_y)):
        if angle is None and name == "camera_angle_y":
            continue
        if not isinstance(angle, int | float) or not 0 < angle < np.pi:
            hint = (
                " (fl_x/fl_y intrinsics are nerfstudio's layout: put each state's "
                "transforms.json in start/ and end/)"
                if "fl_x" in meta
                else ""
            )
            reader.problem(json_path, f"{name} must be a number in (0, pi), got {angle!r}{hint}")
            return []
    if not meta["frames"]:
        reader.problem(json_path, "has no frames")
    views: list[View] = []
    for k, frame in enumerate(meta["frames"]):
        file_path = frame.get("file_path") if isinstance(frame, dict) else None
        if not isinstance(file_path, str):
            reader.problem(json_path, f"frame {k} has no file_path")
            continue
        rel = PurePosixPath(file_path.removeprefix("./"))
        if not rel.suffix:
            rel = rel.with_suffix(".png")
        rgba = reader.read_rgba(reader.root / rel, json_path.name)
        try:
            matrix = np.asarray(frame.get("transform_matrix"), dtype=np.float64)
            Camera.from_blender(matrix, angle_x, 1, 1, angle_y)  # the pose alone, any image
        except (TypeError, ValueError) as err:
            reader.problem(json_path, f"frame {k} ({rel}): camera {err}")
            continue
        if rgba is None:
            continue
        rgb, alpha = rgba
        h, w = alpha.shape
        camera = Camera.from_blender(matrix, angle_x, w, h, angle_y)
        view = View(f"{state}/{split}/{rel.stem}", camera, rgb, alpha)
        companions = {k2: companion_path(rel, k2) for k2 in ("depth", "mask", "parts")}
        if companions["depth"] and (reader.root / companions["depth"]).exists():
            view.depth = reader.read_depth(reader.root / companions["depth"], (h, w))
        if companions["mask"] and (reader.root / companions["mask"]).exists():
            view.regions = reader.read_regions(reader.root / companions["mask"], (h, w))
        if companions["parts"] and (reader.root / companions["parts"]).exists():
            view.parts = reader.read_parts(reader.root / companions["parts"], (h, w))
        views.append(view)
    return views
