"""Render an articulated object into a scene (docs/scenes.md) with ground truth."""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import numpy as np
import torch

from gear.camera import Camera
from gear.data.scene import SPLITS, STATES, View
from gear.data.write import write_scene
from gear.synth import effects as fx
from gear.synth.cameras import sphere_cameras, up_rotation
from gear.synth.model import Articulated
from gear.synth.objects import build
from gear.synth.regions import clean_regions
from gear.synth.render import LIGHT_DIR, Packed, SolidTexture, pack, render

RENDERER_UP = (0.0, 0.0, 1.0)
_AXES = {"x": 0, "y": 1, "z": 2}


def parse_up(spec: str | tuple[float, ...] | np.ndarray | None) -> np.ndarray:
    """ "+y", "-x", "0,1,1" or three numbers -> the world's unit up vector (default +z)."""
    if spec is None:
        return np.array(RENDERER_UP)
    if isinstance(spec, str):
        text = spec.strip().lower()
        if len(text) == 2 and text[0] in "+-" and text[1] in _AXES:
            vector = np.zeros(3)
            vector[_AXES[text[1]]] = 1.0 if text[0] == "+" else -1.0
            return vector
        try:
            spec = tuple(float(x) for x in text.split(","))
        except ValueError:
            spec = ()
    vector = np.asarray(spec, dtype=np.float64).reshape(-1)
    if vector.shape != (3,) or not np.all(np.isfinite(vector)) or np.linalg.norm(vector) < 1e-9:
        raise ValueError(f"up axis {spec!r}: expected +x/-x/+y/-y/+z/-z or three numbers x,y,z "
                         "not all zero")
    return vector / np.linalg.norm(vector)


def _prepare_out(out: Path) -> None:
    """Refuse to write into a non-empty folder unless it holds a previously generated scene,
    whose generated files are then replaced (so no stale views survive)."""
    if out.exists() and any(out.iterdir()):
        if not (out / "synth.json").is_file():
            raise ValueError(f"{out}: exists and is not empty (and is not a generated scene)")
        for name in ("start", "end", "gt"):
            shutil.rmtree(out / name, ignore_errors=True)
        for f in out.glob("transforms_*.json"):
            f.unlink()
    out.mkdir(parents=True, exist_ok=True)


def bounds(obj: Articulated) -> tuple[np.ndarray, float]:
    """Centre and radius of a sphere holding the object in both states."""
    pts = np.concatenate([pack(obj, s).vertices for s in STATES])
    center = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
    return center, float(np.linalg.norm(pts - center, axis=1).max())


def render_scene(
    obj: Articulated,
    out_dir: str | Path,
    res: int = 256,
    views: int = 64,
    test_views: int = 16,
    seed: int = 0,
    effects: frozenset[str] = frozenset(),
    meta: dict | None = None,
    up: str | tuple[float, ...] | np.ndarray | None = None,
) -> Path:
    """Render `obj` (built z up) into a scene at `out_dir`. `up` rotates the whole world
    (object, joints, cameras, light) so that its up axis is `up` instead of the renderer's +z,
    as in a capture whose reconstruction frame is not gravity-aligned; the images stay those
    of the unrotated world, only the coordinates change."""
    up_vector = parse_up(up)
    if res < 8 or views < 1 or test_views < 0:
        raise ValueError(
            f"need res >= 8, views >= 1, test_views >= 0 (got {res}, {views}, {test_views})"
        )
    out = Path(out_dir)
    _prepare_out(out)
    center, radius = bounds(obj)  # before any rotation: the cameras frame the same sphere
    solid = SolidTexture.seeded(seed, 2 * radius)
    rotation = None if np.allclose(up_vector, RENDERER_UP) else up_rotation(up_vector)
    light = LIGHT_DIR
    if rotation is not None:
        obj, solid, light = obj.rotated(rotation), solid.rotated(rotation), rotation @ LIGHT_DIR
        center = rotation @ center
    counts = {"train": views, "test": test_views}
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny ops: one thread is faster, and fair to a shared machine
    t0 = time.perf_counter()
    try:
        scene_views = {}
        for si, state in enumerate(STATES):
            packed = pack(obj, state)
            scene_views[state] = {}
            for pi, split in enumerate(SPLITS):
                rng = np.random.default_rng([seed, si, pi])
                cams = sphere_cameras(counts[split], rng, center, radius, res, rotation)
                scene_views[state][split] = [
                    _view(packed, cam, solid, light, f"{state}/{split}/{k:04d}", effects, rng)
                    for k, cam in enumerate(cams)
                ]
    finally:
        torch.set_num_threads(threads)
    seconds = time.perf_counter() - t0
    info = {
        "object": obj.name,
        "res": res,
        "views": views,
        "test_views": test_views,
        "seed": seed,
        "effects": sorted(effects),
        "up": [float(x) for x in up_vector],
        "joints": [
            {"name": p.joint.name, "type": p.joint.type, "start": p.joint.start, "end": p.joint.end}
            for p in obj.parts
        ],
        "render_seconds": round(seconds, 3),
        **(meta or {}),
    }
    write_scene(
        out,
        scene_views,
        joints=[p.joint.gt() for p in obj.parts],
        meshes={s: obj.gt_meshes(s) for s in STATES},
        meta=info,
    )
    return out


def _view(
    packed: Packed,
    camera: Camera,
    solid: SolidTexture,
    light: np.ndarray,
    name: str,
    effects: frozenset[str],
    rng: np.random.Generator,
) -> View:
    """Render one view, then derive its region masks and apply the scene's effects."""
    image = render(packed, camera, solid, specular="specular" in effects, light_dir=light)
    if not image.alpha.any():
        raise ValueError(f"{name}: the object is not visible from this camera")
    if "background" in effects:
        fx.add_background(image, rng)
    regions = clean_regions(image.facets, rng)
    return View(
        name,
        camera,
        image.rgb,
        image.alpha,
        depth=fx.noisy_depth(image.depth, effects, rng),
        regions=fx.flawed_regions(regions, image.parts, effects, rng),
        parts=image.parts,
    )


def generate(
    object_name: str,
    out_dir: str | Path,
    res: int = 256,
    views: int = 64,
    test_views: int = 16,
    seed: int = 0,
    effects: str | list[str] | tuple[str, ...] | frozenset[str] = (),
) -> Path:
    """Render the built-in object `object_name` into a scene at `out_dir`; returns its path."""
    obj = build(object_name, seed)
    return render_scene(obj, out_dir, res, views, test_views, seed, fx.parse_effects(effects))
