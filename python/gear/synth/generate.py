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
from gear.synth.cameras import sphere_cameras
from gear.synth.model import Articulated
from gear.synth.objects import build
from gear.synth.regions import clean_regions
from gear.synth.render import Packed, SolidTexture, pack, render


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
) -> Path:
    if res < 8 or views < 1 or test_views < 0:
        raise ValueError(
            f"need res >= 8, views >= 1, test_views >= 0 (got {res}, {views}, {test_views})"
        )
    out = Path(out_dir)
    _prepare_out(out)
    center, radius = bounds(obj)
    solid = SolidTexture.seeded(seed, 2 * radius)
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
                cams = sphere_cameras(counts[split], rng, center, radius, res)
                scene_views[state][split] = [
                    _view(packed, cam, solid, f"{state}/{split}/{k:04d}", effects, rng)
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
    name: str,
    effects: frozenset[str],
    rng: np.random.Generator,
) -> View:
    """Render one view, then derive its region masks and apply the scene's effects."""
    image = render(packed, camera, solid, specular="specular" in effects)
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
