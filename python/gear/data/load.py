"""Read and validate a scene directory in any of the layouts of docs/scenes.md.

Each layout has its module (`artgs`, `nerfstudio`, `colmap`) that turns its files into views;
this one picks the layout, adds the ground truth and checks what every layout must satisfy.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

from gear.data import artgs, colmap, nerfstudio
from gear.data.files import Reader
from gear.data.gt import load_gt
from gear.data.scene import SPLITS, Scene, SceneError

LAYOUTS = (artgs, nerfstudio, colmap)  # in detection order


def _read(path: str | Path, splits: tuple[str, ...]) -> tuple[Scene, list[str]]:
    root = Path(path)
    reader = Reader(root)
    if not root.is_dir():
        return Scene(root, {}), [f"{root}: not a directory"]
    unknown = [s for s in splits if s not in SPLITS]
    if unknown:
        raise ValueError(f"splits must be among {SPLITS}, got {unknown}")
    layout = next((m for m in LAYOUTS if m.detect(root)), None)
    if layout is None:
        return Scene(root, {}), [
            f"{root}: no scene found: expected transforms_train_start.json (ArtGS/GEAR), "
            "start/transforms.json and end/transforms.json (nerfstudio), or a COLMAP model in "
            "sparse/0 or start/sparse/0 and end/sparse/0 (see docs/scenes.md)"
        ]
    views = layout.load(reader, splits)
    counts = Counter(v.name for splits_ in views.values() for vs in splits_.values() for v in vs)
    for name, n in sorted(counts.items()):
        if n > 1:
            reader.problem(root, f"{n} images are named {name} (image names must differ within "
                                 "a state and split)")
    scene = Scene(root, views, load_gt(reader), layout.NAME, reader.warnings)
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
