"""The real-asset suite: PartNet-Mobility objects rendered with what a real capture brings and
the procedural scenes lack (docs/evaluation.md, "Real-asset suite").

Each object is imported from its `mobility.urdf` (textures included) and rendered with the
world's up axis along +y instead of the renderer's +z, different cameras in the two states,
and view-dependent (Blinn-Phong) highlights. Every movable joint with limits goes from its
rest value (0, or the limit nearest to it) to a seeded fraction in [0.2, 0.7] of its range,
towards the farther limit; continuous joints (knobs turning about their own axis) stay put.
Nested joints (the stapler) give one scene per joint, the other one held at rest; the fridge
has a second scene with one door at 176 degrees.
"""

from __future__ import annotations

import os
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ASSETS_ENV = "GEAR_PARTNET_ASSETS"
# Relative to the repository root: the assets are read in place, never copied.
DEFAULT_ASSETS = Path("..") / "shared" / "assets" / "partnet-mobility"
REAL_UP = "+y"
REAL_EFFECTS = ("specular",)
MOTION_FRACTION = (0.2, 0.7)
WIDE_OPEN_DEG = 176.0


@dataclass(frozen=True)
class RealScene:
    """One suite scene: an asset folder and the joints' (start, end) values (rad or m)."""

    name: str
    folder: str
    joints: dict[str, tuple[float, float]] = field(default_factory=dict)

    @property
    def parts(self) -> int:
        """True part count K, the static body included."""
        return 1 + sum(start != end for start, end in self.joints.values())


def repo_root() -> Path:
    return Path(__file__).resolve().parents[4]


def assets_dir(given: str | Path | None = None) -> Path:
    """The PartNet-Mobility folder: `given`, else $GEAR_PARTNET_ASSETS, else the documented
    default next to the repository."""
    if given is not None:
        return Path(given)
    if os.environ.get(ASSETS_ENV):
        return Path(os.environ[ASSETS_ENV])
    return repo_root() / DEFAULT_ASSETS


def _rest(lower: float, upper: float) -> float:
    """A joint's rest value: 0 (the modelled pose) or the limit nearest to it."""
    return float(np.clip(0.0, lower, upper))


def _moved(lower: float, upper: float, rng: np.random.Generator) -> tuple[float, float]:
    """(rest, rest + a seeded fraction of the range towards the farther limit)."""
    rest = _rest(lower, upper)
    amount = rng.uniform(*MOTION_FRACTION) * (upper - lower)
    if upper - rest >= rest - lower:
        return rest, min(rest + amount, upper)
    return rest, max(rest - amount, lower)


def _movable(urdf: Path) -> list[tuple[str, str, str, float, float]]:
    """(name, parent link, child link, lower, upper) of each limited movable joint."""
    from gear.synth.urdf import _parse

    robot = _parse(urdf)
    return [(j.name, j.parent, j.child, j.lower, j.upper) for j in robot.joints.values()
            if j.type in ("revolute", "prismatic")]


def _nested_groups(joints: list[tuple[str, str, str, float, float]]) -> list[list[str]]:
    """Joint names split so no joint shares a scene with a joint below it (one per chain)."""
    by_child = {child: name for name, _, child, _, _ in joints}
    below = {name for name, parent, _, _, _ in joints if parent in by_child}
    above = {by_child[parent] for _, parent, _, _, _ in joints if parent in by_child}
    free = [name for name, *_ in joints if name not in below | above]
    chained = [name for name, *_ in joints if name in below | above]
    return [[*free, name] for name in chained] if chained else [free]


def real_scenes(assets: Path, seed: int = 0) -> list[RealScene]:
    """Every suite scene whose asset is present, in folder order."""
    out: list[RealScene] = []
    folders = sorted(p.name for p in assets.iterdir() if (p / "mobility.urdf").is_file())
    for folder in folders:
        joints = _movable(assets / folder / "mobility.urdf")
        limits = {name: (lower, upper) for name, _, _, lower, upper in joints}
        rng = np.random.default_rng([seed, zlib.crc32(folder.encode())])
        drawn = {name: _moved(*limits[name], rng) for name in limits}
        base = folder.rsplit("_", 1)[0]
        groups = _nested_groups(joints)
        for group in groups:
            values = {name: drawn[name] if name in group else (_rest(*limits[name]),) * 2
                      for name in limits}
            name = base if len(groups) == 1 else f"{base}-{group[-1]}"
            out.append(RealScene(name, folder, values))
        if base == "fridge":
            first = next(iter(limits))
            wide = dict(drawn)
            rest = _rest(*limits[first])
            wide[first] = (rest, float(min(rest + np.deg2rad(WIDE_OPEN_DEG), limits[first][1])))
            out.append(RealScene(f"{base}-180", folder, wide))
    return out


def select(scenes: list[RealScene], names: str | None) -> list[RealScene]:
    """The scenes named in "fridge,scissors", in that order (a scene name, or an asset's base
    name or folder for all of its scenes); all when `names` is empty."""
    if not names:
        return scenes

    def matches(name: str, scene: RealScene) -> bool:
        return name in (scene.name, scene.folder) or scene.name.startswith(f"{name}-")

    wanted = [n.strip() for n in names.split(",") if n.strip()]
    unknown = [n for n in wanted if not any(matches(n, s) for s in scenes)]
    if unknown:
        raise ValueError(f"unknown real-suite object(s) {', '.join(unknown)}; known: "
                         f"{', '.join(s.name for s in scenes)}")
    chosen = {s.name: s for n in wanted for s in scenes if matches(n, s)}  # once each, in order
    return list(chosen.values())


def render_real(scene: RealScene, assets: Path, out: Path, res: int, views: int,
                test_views: int, seed: int = 0) -> Path:
    """Import the asset with the scene's joint values and render it with the suite's
    conditions; returns the scene folder."""
    from gear.synth import render_scene
    from gear.synth.effects import parse_effects
    from gear.synth.urdf import load_urdf

    start = {name: v[0] for name, v in scene.joints.items()}
    end = {name: v[1] for name, v in scene.joints.items()}
    obj = load_urdf(assets / scene.folder / "mobility.urdf", start, end)
    obj.name = scene.name
    return render_scene(obj, out, res, views, test_views, seed, parse_effects(REAL_EFFECTS),
                        meta={"suite": "real", "asset": scene.folder}, up=REAL_UP)
