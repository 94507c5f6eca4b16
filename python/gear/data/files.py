"""Reading the files of a scene while collecting problems (every scene layout shares these).

Validation never stops at the first problem: every file is checked and each problem is reported
as "file: what is wrong", so one run of `gear check` lists everything to fix.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image, UnidentifiedImageError

DEPTH_SCALE = 1000.0  # the ArtGS/GEAR layout's depth pngs store millimetres
DEPTH_PNG_MODES = ("I;16", "I;16B", "I;16L", "I")  # how Pillow opens a 16-bit grayscale png
# A mask pixel is grey (neither object nor background) between these fractions of the range;
# past GREY_MASK_FRACTION of such pixels the "mask" is more likely a photo or a depth map.
GREY_BAND = (0.1, 0.9)
GREY_MASK_FRACTION = 0.05


class Reader:
    """Collects problems while reading; each `read_*` returns None when the file is bad."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.problems: list[str] = []
        # inputs found but not used, or used with a doubt: said once by check and train
        self.warnings: list[str] = []
        # group (e.g. a transforms file) -> ((width, height), image that set it): the first image
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

    def check_size(self, path: Path, size: tuple[int, int], group: str) -> bool:
        """The images of one group share one size (its first image sets it): the group has one
        set of intrinsics. Different groups may differ from each other."""
        first = self.sizes.setdefault(group, (size, str(self._rel(path))))
        if size != first[0]:
            self.problem(
                path,
                f"size {size[0]}x{size[1]} differs from {first[1]} "
                f"({first[0][0]}x{first[0][1]}) of the same {group}",
            )
            return False
        return True

    def _rel(self, path: Path) -> Path:
        try:
            return path.relative_to(self.root)
        except ValueError:
            return path

    def read_rgba(self, path: Path, group: str) -> tuple[np.ndarray, np.ndarray] | None:
        """(rgb, alpha) of an image whose alpha channel is the object mask."""
        img = self._open(path)
        if img is None:
            return None
        if not has_alpha(img):
            self.problem(path, f"has no alpha channel (mode {img.mode}); alpha is the object mask")
            return None
        if not self.check_size(path, img.size, group):
            return None
        arr = np.asarray(img.convert("RGBA"), dtype=np.float32) / 255.0
        alpha = np.ascontiguousarray(arr[..., 3])
        if not alpha.any():
            self.problem(path, "alpha is empty (the object is not visible)")
            return None
        return np.ascontiguousarray(arr[..., :3]), alpha

    def read_object_image(
        self, path: Path, mask_path: Path | None, how: str
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """(rgb, object mask) of a JPEG/PNG: the mask from `mask_path` when there is one, else
        the image's alpha channel; `how` says how the layout gives a mask file."""
        if mask_path is None:
            if path.is_file() and not _file_has_alpha(path):
                self.problem(path, f"no object mask: give {how} (a binary image, white = "
                                   "object) or use an RGBA image")
                return None
            return self.read_rgba(path, str(path))
        rgb = self.read_rgb(path)
        if rgb is None:
            return None
        mask = self.read_mask(mask_path, rgb.shape[:2])
        return None if mask is None else (rgb, mask)

    def read_rgb(self, path: Path) -> np.ndarray | None:
        """[H,W,3] float32 colour of a JPEG/PNG (an alpha channel, if any, is ignored)."""
        img = self._open(path)
        if img is None:
            return None
        return np.asarray(img.convert("RGB"), dtype=np.float32) / 255.0

    def read_mask(self, path: Path, hw: tuple[int, int]) -> np.ndarray | None:
        """[H,W] float32 {0,1} object mask from a single-channel image: in a 0/1 mask 1 is the
        object, otherwise values above half the type's range (> 127 in 8 bits, so masks saved
        lossily keep their meaning)."""
        img = self._open(path)
        if img is None:
            return None
        if img.mode not in ("1", "L", "P", "I", "I;16"):
            self.problem(path, f"object mask must be a single-channel image, got mode {img.mode}")
            return None
        arr = np.asarray(img.convert("L") if img.mode == "P" else img)
        if not self.same_shape(path, arr.shape, hw):
            return None
        full = 255 if img.mode in ("1", "L", "P") else 65535
        low, high = int(arr.min(initial=0)), int(arr.max(initial=0))
        if low < 0 or high > full:
            self.problem(path, f"object mask values span {low}..{high}, outside 0..{full}")
            return None
        if 1 < high <= full // 2:
            self.problem(path, f"object mask values span {low}..{high}: a mask is 0/1 or black/"
                               f"white (0/{full}, white = object), this looks like a label image")
            return None
        if high > 1:
            grey = np.mean((arr > GREY_BAND[0] * full) & (arr < GREY_BAND[1] * full))
            if grey > GREY_MASK_FRACTION:
                self.warnings.append(f"{self._rel(path)}: object mask is not black and white "
                                     f"({100 * grey:.0f}% grey pixels); thresholded at half")
        mask = (arr > (0 if high <= 1 else full // 2)).astype(np.float32)
        if not mask.any():
            self.problem(path, "object mask is empty (the object is not visible)")
            return None
        return mask

    def same_shape(self, path: Path, shape: tuple[int, ...], hw: tuple[int, int]) -> bool:
        if tuple(shape) != hw:
            self.problem(
                path, f"shape {shape[0]}x{shape[1]} differs from its image {hw[0]}x{hw[1]}"
            )
            return False
        return True

    def read_depth(
        self, path: Path, hw: tuple[int, int], units_per_metre: float = DEPTH_SCALE
    ) -> np.ndarray | None:
        """Camera-space z in metres from a 16-bit png or a 2D .npy (0 = no depth)."""
        if path.suffix == ".npy":
            arr = self._load_npy(path)
            if arr is None:
                return None
            if arr.ndim != 2 or arr.dtype.kind not in "uif":
                self.problem(path, f"depth must be a 2D numeric array, got {arr.dtype} {arr.shape}")
                return None
        else:
            img = self._open(path)
            if img is None:
                return None
            if img.mode not in DEPTH_PNG_MODES:
                bits = "8-bit grayscale" if img.mode in ("L", "P", "1") else f"mode {img.mode}"
                self.problem(path, f"depth must be a single-channel 16-bit png (millimetres), "
                                   f"got {bits}")
                return None
            arr = np.asarray(img)
        if not self.same_shape(path, arr.shape, hw):
            return None
        if not np.all(np.isfinite(arr)) or arr.min() < 0:
            self.problem(path, "depth has negative or non-finite values")
            return None
        return arr.astype(np.float32) / np.float32(units_per_metre)

    def _load_npy(self, path: Path) -> np.ndarray | None:
        if not path.is_file():
            self.problem(path, "missing")
            return None
        try:
            return np.load(path, allow_pickle=False)
        except (OSError, ValueError) as err:
            self.problem(path, f"unreadable .npy ({err})")
            return None

    def read_regions(self, path: Path, hw: tuple[int, int]) -> np.ndarray | None:
        arr = self._load_npy(path)
        if arr is None:
            return None
        if arr.ndim != 2 or arr.dtype.kind not in "uib":
            self.problem(
                path, f"region mask must be a 2D integer array, got {arr.dtype} {arr.shape}"
            )
            return None
        if not self.same_shape(path, arr.shape, hw):
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
        if not self.same_shape(path, arr.shape, hw):
            return None
        return arr.copy()

    def read_json(self, path: Path) -> Any:
        try:
            return json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
            self.problem(path, f"unreadable json ({err})")
            return None


def has_alpha(img: Image.Image) -> bool:
    return "A" in img.getbands() or "transparency" in img.info


def _file_has_alpha(path: Path) -> bool:
    try:
        with Image.open(path) as img:
            return has_alpha(img)
    except OSError:
        return True  # unreadable: read_rgba reports it


def finite_vector(value: Any, n: int) -> np.ndarray | None:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return None
    return arr if arr.shape == (n,) and np.all(np.isfinite(arr)) else None
