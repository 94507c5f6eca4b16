"""COLMAP sparse models of the two states, read with pycolmap (docs/scenes.md).

Two ways to have both states in one world frame:
- one model of both states' images (`sparse/0`, images under `images/start/` and
  `images/end/`): COLMAP registers the states itself through the static background they share;
- one model per state (`start/sparse/0`, `end/sparse/0`, images in `start/images/`,
  `end/images/`) and `end_to_start.json`, a 4x4 similarity taking the end model's coordinates
  into the start model's.
Object masks are `masks/IMAGE_NAME.png` beside `images/` (COLMAP's own mask naming; a mask
named after the image's stem, `masks/0001.png`, is accepted too), or the image's alpha channel.
COLMAP cameras are OpenCV-axed world-to-camera poses, gear's own convention. Lens distortion
must be zero (undistort with COLMAP's image_undistorter first).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import numpy as np

from gear.camera import Camera
from gear.data.files import Reader
from gear.data.scene import STATES, View

NAME = "COLMAP sparse model"
TRANSFORM_FILE = "end_to_start.json"
TEST_LIST = "test_images.txt"
# Camera models that are a pinhole once their distortion parameters are zero.
PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")
INSTALL_HINT = "COLMAP scenes need pycolmap: pip install pycolmap (or the package's [colmap] extra)"


@dataclass
class _Model:
    """One COLMAP model and where its images and masks are."""

    path: Path  # folder with cameras/images/points3D
    images: Path
    masks: Path
    state: str | None  # the state of all its images, or None: image names start with a state


def _model_dir(folder: Path) -> Path | None:
    for candidate in (folder, folder / "0"):
        if any((candidate / f"cameras.{ext}").is_file() for ext in ("bin", "txt")):
            return candidate
    return None


def detect(root: Path) -> bool:
    return any(_model_dir(d) is not None for d in [root / "sparse"] +
               [root / s / "sparse" for s in STATES])


def _models(reader: Reader) -> list[_Model] | None:
    root = reader.root
    joint = _model_dir(root / "sparse")
    if joint is not None:
        return [_Model(joint, root / "images", root / "masks", None)]
    models = []
    for state in STATES:
        path = _model_dir(root / state / "sparse")
        if path is None:
            reader.problem(root / state / "sparse", "no COLMAP model (cameras/images/points3D) "
                                                    "for this state")
            continue
        models.append(_Model(path, root / state / "images", root / state / "masks", state))
    return models if len(models) == len(STATES) else None


def _similarity(reader: Reader) -> np.ndarray | None:
    """The end model -> start model 4x4 similarity of `end_to_start.json`, or None."""
    path = reader.root / TRANSFORM_FILE
    if not path.is_file():
        reader.problem(path, "missing: separate start and end COLMAP models need the transform "
                             "from end to start coordinates ({\"matrix\": 4x4}), or reconstruct "
                             "both states' images in one model (the static background registers "
                             "them)")
        return None
    meta = reader.read_json(path)
    if meta is None:
        return None
    try:
        m = np.asarray(meta["matrix"] if isinstance(meta, dict) else None, dtype=np.float64)
    except (KeyError, TypeError, ValueError):
        m = np.zeros(0)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        reader.problem(path, "needs 'matrix': a 4x4 array of finite numbers")
        return None
    scale = np.cbrt(np.linalg.det(m[:3, :3]))
    rot = m[:3, :3] / scale if scale > 0 else m[:3, :3]
    if scale <= 0 or np.abs(rot @ rot.T - np.eye(3)).max() > 1e-4 or \
            np.abs(m[3] - [0, 0, 0, 1]).max() > 1e-9:
        reader.problem(path, "matrix must be a similarity: scale * rotation, translation, last "
                             "row 0 0 0 1")
        return None
    return m


def _test_names(reader: Reader) -> set[str]:
    path = reader.root / TEST_LIST
    if not path.is_file():
        return set()
    return {line.strip() for line in path.read_text().splitlines() if line.strip()}


def load(reader: Reader, splits: tuple[str, ...]) -> dict[str, dict[str, list[View]]]:
    views: dict[str, dict[str, list[View]]] = {s: {sp: [] for sp in splits} for s in STATES}
    try:
        import pycolmap
    except ImportError:
        reader.problem(reader.root, INSTALL_HINT)
        return views
    models = _models(reader)
    if models is None:
        return views
    to_start = _similarity(reader) if len(models) > 1 else None
    if len(models) > 1 and to_start is None:
        return views
    test_names = _test_names(reader)
    used_tests: set[str] = set()
    for model in models:
        try:
            rec = pycolmap.Reconstruction(str(model.path))
        except (RuntimeError, ValueError) as err:
            reader.problem(model.path, f"unreadable COLMAP model ({err})")
            return views
        similarity = to_start if model.state == "end" else None
        registered = set()
        for image in sorted(rec.images.values(), key=lambda im: im.name):
            registered.add(image.name)
            state, name = _state_of(model, image.name)
            if state is None:
                reader.warnings.append(f"{model.path.relative_to(reader.root)}: image "
                                       f"{image.name} is in neither start/ nor end/: not used")
                continue
            split = "test" if image.name in test_names else "train"
            used_tests |= {image.name} & test_names
            if split not in splits:
                continue
            view = _view(reader, model, rec, image, state, split, name, similarity)
            if view is not None:
                views[state][split].append(view)
        _warn_unregistered(reader, model, registered)
    for name in sorted(test_names - used_tests):
        reader.problem(reader.root / TEST_LIST, f"{name} is no image of the model")
    return views


def _state_of(model: _Model, image_name: str) -> tuple[str | None, PurePosixPath]:
    name = PurePosixPath(image_name)
    if model.state is not None:
        return model.state, name
    state = name.parts[0] if len(name.parts) > 1 else None
    return (state if state in STATES else None), name


def _pose(image) -> np.ndarray:  # noqa: ANN001 (pycolmap.Image)
    """The image's 4x4 world-to-camera matrix (pycolmap >= 3.12 makes cam_from_world a method)."""
    pose = image.cam_from_world
    pose = pose() if callable(pose) else pose
    out = np.eye(4)
    out[:3] = pose.matrix()
    return out


def _view(
    reader: Reader,
    model: _Model,
    rec,  # noqa: ANN001 (pycolmap.Reconstruction)
    image,  # noqa: ANN001 (pycolmap.Image)
    state: str,
    split: str,
    name: PurePosixPath,
    similarity: np.ndarray | None,
) -> View | None:
    camera = rec.cameras[image.camera_id]
    where = f"image {image.name}: camera {camera.camera_id}"
    if camera.model_name not in PINHOLE_MODELS:
        reader.problem(model.path, f"{where}: model {camera.model_name} is not a pinhole; "
                                   "undistort with COLMAP's image_undistorter first")
        return None
    extra = [float(camera.params[i]) for i in camera.extra_params_idxs()]
    if any(extra):
        reader.problem(model.path, f"{where}: {camera.model_name} has non-zero lens distortion "
                                   f"{extra}; undistort with COLMAP's image_undistorter first")
        return None
    img_path = model.images / image.name
    mask_path = next((p for p in (model.masks / f"{image.name}.png",
                                  (model.masks / image.name).with_suffix(".png")) if p.is_file()),
                     None)
    masks_rel = model.masks.relative_to(reader.root)
    read = reader.read_object_image(img_path, mask_path, f"{masks_rel}/{image.name}.png")
    if read is None:
        return None
    rgb, alpha = read
    h, w = alpha.shape
    if (w, h) != (camera.width, camera.height):
        reader.problem(img_path, f"size {w}x{h} differs from its COLMAP camera's "
                                 f"{camera.width}x{camera.height}")
        return None
    w2c = _pose(image)
    if similarity is not None:
        # x_start = s R x_end + t; camera coordinates scaled by s project to the same pixels,
        # so the pose stays rigid: diag(s, s, s, 1) * w2c_end * similarity^-1.
        scale = np.cbrt(np.linalg.det(similarity[:3, :3]))
        w2c = np.diag([scale, scale, scale, 1.0]) @ w2c @ np.linalg.inv(similarity)
    cam = Camera(w2c, camera.focal_length_x, camera.focal_length_y, camera.principal_point_x,
                 camera.principal_point_y, w, h)
    view_name = f"{state}/{split}/{name.stem}"
    return View(view_name, cam, rgb, alpha)


def _warn_unregistered(reader: Reader, model: _Model, registered: set[str]) -> None:
    """Images in the images folder that COLMAP did not register are not used: say so."""
    if not model.images.is_dir():
        return
    on_disk = {p.relative_to(model.images).as_posix() for p in model.images.rglob("*")
               if p.suffix.lower() in (".jpg", ".jpeg", ".png")}
    missing = sorted(on_disk - registered)
    if missing:
        shown = ", ".join(missing[:3]) + (" ..." if len(missing) > 3 else "")
        folder = model.images.relative_to(reader.root)
        reader.warnings.append(f"{folder}: {len(missing)} image(s) not in the COLMAP model (not "
                               f"registered), not used: {shown}")
