"""Read and validate a METHOD.md §1 scene directory.

Validation never stops at the first problem: every file is checked and each problem is reported
as "file: what is wrong", so one run of `gear check` lists everything to fix.
"""

from __future__ import annotations

import json
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np
from PIL import Image, UnidentifiedImageError

from gear.camera import Camera
from gear.data.scene import (
    SPLITS,
    STATES,
    GroundTruth,
    GtJoint,
    Scene,
    SceneError,
    View,
)

DEPTH_SCALE = 1000.0  # depth pngs store millimetres


def transforms_name(split: str, state: str) -> str:
    return f"transforms_{split}_{state}.json"


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


def gt_mesh_files(state: str, n_parts: int) -> dict[str, str]:
    """METHOD.md §1 GT mesh names: key ("whole", "static", "part_i") -> file under gt/{state}/."""
    names = {"whole": f"{state}_rotate.ply", "static": f"{state}_static_rotate.ply"}
    if n_parts == 1:
        names["part_0"] = f"{state}_dynamic_rotate.ply"
    else:
        names.update({f"part_{i}": f"{state}_dynamic_{i}_rotate.ply" for i in range(n_parts)})
    return names


class _Reader:
    """Collects problems while reading; each `read_*` returns None when the file is bad."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.problems: list[str] = []
        # transforms file -> ((width, height), image that set it): the first image read
        self.sizes: dict[str, tuple[tuple[int, int], str]] = {}

    def problem(self, path: Path | str, what: str) -> None:
        rel = Path(path)
        try:
            rel = rel.relative_to(self.root)
        except ValueError:
            pass
        self.problems.append(f"{rel}: {what}")

    def _open(self, path: Path) -> Image.Image | None:
        if not path.is_file():
            self.problem(path, "missing")
            return None
        try:
            img = Image.open(path)
            img.load()
            return img
        except (OSError, UnidentifiedImageError) as err:
            self.problem(path, f"unreadable image ({err.__class__.__name__})")
            return None

    def _check_size(self, path: Path, size: tuple[int, int], group: str) -> bool:
        """The rgba images of one transforms file share one size (its first image sets it): the
        file has one set of intrinsics. The states and splits may differ from each other."""
        first = self.sizes.setdefault(group, (size, str(path.relative_to(self.root))))
        if size != first[0]:
            self.problem(
                path,
                f"size {size[0]}x{size[1]} differs from {first[1]} "
                f"({first[0][0]}x{first[0][1]}) of the same {group}",
            )
            return False
        return True

    def read_rgba(self, path: Path, group: str) -> tuple[np.ndarray, np.ndarray] | None:
        img = self._open(path)
        if img is None:
            return None
        if "A" not in img.getbands() and "transparency" not in img.info:
            self.problem(path, f"has no alpha channel (mode {img.mode}); alpha is the object mask")
            return None
        if not self._check_size(path, img.size, group):
            return None
        arr = np.asarray(img.convert("RGBA"), dtype=np.float32) / 255.0
        alpha = np.ascontiguousarray(arr[..., 3])
        if not alpha.any():
            self.problem(path, "alpha is empty (the object is not visible)")
            return None
        return np.ascontiguousarray(arr[..., :3]), alpha

    def _same_shape(self, path: Path, shape: tuple[int, ...], hw: tuple[int, int]) -> bool:
        if tuple(shape) != hw:
            self.problem(
                path, f"shape {shape[0]}x{shape[1]} differs from its image {hw[0]}x{hw[1]}"
            )
            return False
        return True

    def read_depth(self, path: Path, hw: tuple[int, int]) -> np.ndarray | None:
        img = self._open(path)
        if img is None:
            return None
        arr = np.asarray(img)
        if arr.ndim != 2 or arr.dtype.kind not in "ui":
            self.problem(path, f"depth must be a single-channel 16-bit png, got mode {img.mode}")
            return None
        if not self._same_shape(path, arr.shape, hw):
            return None
        if arr.min() < 0:
            self.problem(path, "depth has negative values")
            return None
        return arr.astype(np.float32) / DEPTH_SCALE

    def read_regions(self, path: Path, hw: tuple[int, int]) -> np.ndarray | None:
        if not path.is_file():
            self.problem(path, "missing")
            return None
        try:
            arr = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as err:
            self.problem(path, f"unreadable .npy ({err})")
            return None
        if arr.ndim != 2 or arr.dtype.kind not in "uib":
            self.problem(
                path, f"region mask must be a 2D integer array, got {arr.dtype} {arr.shape}"
            )
            return None
        if not self._same_shape(path, arr.shape, hw):
            return None
        if arr.min() < 0:
            self.problem(path, "region ids must be >= 0")
            return None
        return arr.astype(np.int32)

    def read_parts(self, path: Path, hw: tuple[int, int]) -> np.ndarray | None:
        img = self._open(path)
        if img is None:
            return None
        arr = np.asarray(img)
        if arr.ndim != 2 or arr.dtype != np.uint8:
            self.problem(path, f"part ids must be a single-channel 8-bit png, got mode {img.mode}")
            return None
        if not self._same_shape(path, arr.shape, hw):
            return None
        return arr.copy()


def _read_json(reader: _Reader, path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        reader.problem(path, f"unreadable json ({err})")
        return None


def _finite_vector(value: Any, n: int) -> np.ndarray | None:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return None
    return arr if arr.shape == (n,) and np.all(np.isfinite(arr)) else None


def _load_split(reader: _Reader, state: str, split: str, required: bool) -> list[View]:
    json_path = reader.root / transforms_name(split, state)
    if not json_path.is_file():
        if required:
            reader.problem(json_path, "missing")
        return []
    meta = _read_json(reader, json_path)
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
            reader.problem(json_path, f"{name} must be a number in (0, pi), got {angle!r}")
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


def _load_gt(reader: _Reader) -> GroundTruth | None:
    path = reader.root / "gt" / "trans.json"
    if not path.is_file():
        return None
    meta = _read_json(reader, path)
    if meta is None:
        return None
    if not isinstance(meta, dict) or not isinstance(meta.get("trans_info"), list):
        reader.problem(path, "needs a 'trans_info' list")
        return None
    joints: list[GtJoint] = []
    for i, info in enumerate(meta["trans_info"]):
        joint = _parse_joint(info)
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


def _parse_joint(info: Any) -> GtJoint | str:
    """A GtJoint, or a description of what the trans_info entry lacks."""
    if not isinstance(info, dict):
        return "must be an object"
    axis = info.get("axis")
    if not isinstance(axis, dict):
        return "missing 'axis' with 'o' and 'd'"
    origin, direction = _finite_vector(axis.get("o"), 3), _finite_vector(axis.get("d"), 3)
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
    lr = _finite_vector([limits.get("l"), limits.get("r")], 2) if "l" in limits else None
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


def _read(path: str | Path, splits: tuple[str, ...]) -> tuple[Scene, list[str]]:
    root = Path(path)
    reader = _Reader(root)
    if not root.is_dir():
        return Scene(root, {}), [f"{root}: not a directory"]
    unknown = [s for s in splits if s not in SPLITS]
    if unknown:
        raise ValueError(f"splits must be among {SPLITS}, got {unknown}")
    views = {
        state: {split: _load_split(reader, state, split, split == "train") for split in splits}
        for state in STATES
    }
    scene = Scene(root, views, _load_gt(reader))
    return scene, reader.problems


def load_scene(path: str | Path, splits: tuple[str, ...] = SPLITS) -> Scene:
    """Load a scene; raises SceneError listing every problem if anything is malformed."""
    scene, problems = _read(path, splits)
    if problems:
        raise SceneError(Path(path), problems)
    return scene


def validate_scene(path: str | Path) -> list[str]:
    """Every problem of the scene at `path` ("file: what is wrong"); empty when it is valid."""
    return _read(path, SPLITS)[1]


def load_and_validate(path: str | Path) -> tuple[Scene, list[str]]:
    """The scene read as far as possible, and its problems (used by `gear check`)."""
    return _read(path, SPLITS)
