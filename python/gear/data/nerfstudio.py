"""The nerfstudio layout: `start/transforms.json` and `end/transforms.json`, one capture per
state, in one world frame (docs/scenes.md).

Each file holds pixel intrinsics (`fl_x`, `fl_y`, `cx`, `cy`, `w`, `h`) at the top level or per
frame (a frame's own value wins), OpenGL camera-to-world `transform_matrix` per frame (the
axes of the ArtGS/GEAR layout too), JPEG/PNG images and an object mask per frame (`mask_path`,
or the image's alpha channel), optional depth (`depth_file_path`, times
`depth_unit_scale_factor`, default 0.001 as in nerfstudio: millimetres) and gear's optional
`region_mask_path` / `part_ids_path`. Paths are relative to the transforms file's folder.
"""

from __future__ import annotations

from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

from gear.camera import Camera
from gear.data.files import Reader
from gear.data.scene import SPLITS, STATES, View

NAME = "nerfstudio (start/transforms.json, end/transforms.json)"
DEFAULT_DEPTH_SCALE = 1e-3  # nerfstudio's default depth_unit_scale_factor: depth pngs in mm
CAMERA_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE")
DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")
INTRINSICS = ("fl_x", "fl_y", "cx", "cy", "w", "h")


def detect(root: Path) -> bool:
    return any((root / state / "transforms.json").is_file() for state in STATES)


def load(reader: Reader, splits: tuple[str, ...]) -> dict[str, dict[str, list[View]]]:
    views: dict[str, dict[str, list[View]]] = {}
    for state in STATES:
        by_split = _load_state(reader, state)
        views[state] = {split: by_split.get(split, []) for split in splits}
    return views


def _load_state(reader: Reader, state: str) -> dict[str, list[View]]:
    json_path = reader.root / state / "transforms.json"
    if not json_path.is_file():
        reader.problem(json_path, "missing (a nerfstudio scene needs one per state)")
        return {}
    meta = reader.read_json(json_path)
    if meta is None:
        return {}
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list):
        reader.problem(json_path, "needs a 'frames' list")
        return {}
    if not meta["frames"]:
        reader.problem(json_path, "has no frames")
    depth_scale = meta.get("depth_unit_scale_factor", DEFAULT_DEPTH_SCALE)
    if not isinstance(depth_scale, int | float) or not depth_scale > 0:
        reader.problem(json_path, f"depth_unit_scale_factor must be > 0, got {depth_scale!r}")
        return {}
    splits = _test_files(reader, json_path, meta)
    out: dict[str, list[View]] = {split: [] for split in SPLITS}
    seen: dict[str, int] = {}
    for k, frame in enumerate(meta["frames"]):
        if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str):
            reader.problem(json_path, f"frame {k} has no file_path")
            continue
        rel = _rel(frame["file_path"])
        split = _split_of(reader, json_path, k, frame, rel, splits)
        if split is None:
            continue
        name = f"{state}/{split}/{rel.stem}"
        if name in seen:
            reader.problem(json_path, f"frame {k} ({rel}): same name as frame {seen[name]}")
            continue
        seen[name] = k
        view = _load_frame(reader, json_path, k, meta, frame, name, float(depth_scale))
        if view is not None:
            out[split].append(view)
    if splits is not None:
        listed = set(splits)
        named = {_rel(f["file_path"]) for f in meta["frames"] if isinstance(f, dict)
                 and isinstance(f.get("file_path"), str)}
        for missing in sorted(listed - named):
            reader.problem(json_path, f"{missing} is listed in test_filenames but is no frame")
    return out


def _rel(file_path: str) -> PurePosixPath:
    return PurePosixPath(file_path.removeprefix("./"))


def _test_files(reader: Reader, json_path: Path, meta: dict) -> set[PurePosixPath] | None:
    """The images nerfstudio's `test_filenames` names, or None when the file has no such list
    (a frame's own "split" decides, default train)."""
    names = meta.get("test_filenames")
    if names is None:
        return None
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        reader.problem(json_path, "test_filenames must be a list of image paths")
        return None
    return {_rel(n) for n in names}


def _split_of(
    reader: Reader,
    json_path: Path,
    k: int,
    frame: dict,
    rel: PurePosixPath,
    test_files: set[PurePosixPath] | None,
) -> str | None:
    split = frame.get("split")
    if split is not None and split not in SPLITS:
        reader.problem(json_path, f"frame {k} ({rel}): split must be one of {SPLITS}, "
                                  f"got {split!r}")
        return None
    if test_files is not None:
        listed = "test" if rel in test_files else "train"
        if split is not None and split != listed:
            reader.problem(json_path, f"frame {k} ({rel}): split {split!r} contradicts "
                                      f"test_filenames")
            return None
        return listed
    return split or "train"


def _intrinsic(meta: dict, frame: dict, key: str) -> Any:
    return frame.get(key, meta.get(key))


def _camera_problem(meta: dict, frame: dict) -> str | None:
    """Why this frame's camera cannot be used as a pinhole camera, or None."""
    model = _intrinsic(meta, frame, "camera_model") or "OPENCV"
    if model not in CAMERA_MODELS:
        return f"camera_model {model!r} is not supported (one of {', '.join(CAMERA_MODELS)})"
    distortion = {k: _intrinsic(meta, frame, k) for k in DISTORTION}
    bad = {k: v for k, v in distortion.items() if v is not None and not isinstance(v, int | float)}
    if bad:
        return f"distortion coefficients must be numbers, got {bad}"
    nonzero = {k: v for k, v in distortion.items() if v}
    if nonzero:
        shown = ", ".join(f"{k}={v:g}" for k, v in nonzero.items())
        return (f"non-zero lens distortion ({shown}): undistort the images first (e.g. COLMAP's "
                "image_undistorter) and give their pinhole intrinsics")
    for key in INTRINSICS:
        value = _intrinsic(meta, frame, key)
        if value is not None and (not isinstance(value, int | float) or not np.isfinite(value)):
            return f"{key} must be a number, got {value!r}"
    if _intrinsic(meta, frame, "fl_x") is None:
        return "no focal length fl_x (at the top level or in the frame)"
    return None


def _load_frame(
    reader: Reader,
    json_path: Path,
    k: int,
    meta: dict,
    frame: dict,
    name: str,
    depth_scale: float,
) -> View | None:
    base = json_path.parent
    rel = _rel(frame["file_path"])
    where = f"frame {k} ({rel})"
    why = _camera_problem(meta, frame)
    if why is not None:
        reader.problem(json_path, f"{where}: {why}")
        return None
    try:
        matrix = np.asarray(frame.get("transform_matrix"), dtype=np.float64)
        Camera.from_gl(matrix, 1.0, 1.0, 0.0, 0.0, 1, 1)  # the pose alone
    except (TypeError, ValueError) as err:
        reader.problem(json_path, f"{where}: camera {err}")
        return None
    mask_path = frame.get("mask_path")
    if mask_path is not None and not isinstance(mask_path, str):
        reader.problem(json_path, f"{where}: mask_path must be a path, got {mask_path!r}")
        return None
    image = reader.read_object_image(base / rel, base / _rel(mask_path) if mask_path else None,
                                     "a mask_path")
    if image is None:
        return None
    rgb, alpha = image
    h, w = alpha.shape
    size = (_intrinsic(meta, frame, "w"), _intrinsic(meta, frame, "h"))
    if any(s is not None for s in size) and size != (w, h):
        reader.problem(base / rel, f"size {w}x{h} differs from the transforms file's w x h "
                                   f"{size[0]}x{size[1]}")
        return None
    fx = float(_intrinsic(meta, frame, "fl_x"))
    fy = float(_intrinsic(meta, frame, "fl_y") or fx)
    cx, cy = _intrinsic(meta, frame, "cx"), _intrinsic(meta, frame, "cy")
    try:
        camera = Camera.from_gl(matrix, fx, fy, w / 2.0 if cx is None else cx,
                                h / 2.0 if cy is None else cy, w, h)
    except ValueError as err:
        reader.problem(json_path, f"{where}: camera {err}")
        return None
    view = View(name, camera, rgb, alpha)
    extras = {key: frame.get(key) for key in
              ("depth_file_path", "region_mask_path", "part_ids_path")}
    for key, value in extras.items():
        if value is not None and not isinstance(value, str):
            reader.problem(json_path, f"{where}: {key} must be a path, got {value!r}")
            extras[key] = None
    if extras["depth_file_path"]:
        view.depth = reader.read_depth(base / _rel(extras["depth_file_path"]), (h, w),
                                       1.0 / depth_scale)
    if extras["region_mask_path"]:
        view.regions = reader.read_regions(base / _rel(extras["region_mask_path"]), (h, w))
    if extras["part_ids_path"]:
        view.parts = reader.read_parts(base / _rel(extras["part_ids_path"]), (h, w))
    return view
