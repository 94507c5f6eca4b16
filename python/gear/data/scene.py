"""In-memory scene: posed views of one object in two articulation states, plus optional GT.

`gear.data.load` reads the on-disk layouts of docs/scenes.md; `gear.data.write` writes the
ArtGS/GEAR one.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gear.camera import Camera

STATES = ("start", "end")
SPLITS = ("train", "test")
BACKGROUND_PART = 255  # part-id value of pixels that show no object


def other_state(state: str) -> str:
    """The state that is not `state` (one of STATES)."""
    return STATES[1 - STATES.index(state)]


class SceneError(ValueError):
    """A malformed scene; `.problems` lists every "file: what is wrong" found."""

    def __init__(self, root: Path, problems: list[str]) -> None:
        self.problems = list(problems)
        shown = "; ".join(self.problems[:5])
        more = f" (and {len(self.problems) - 5} more)" if len(self.problems) > 5 else ""
        super().__init__(f"scene {root} has {len(self.problems)} problem(s): {shown}{more}")


@dataclass
class View:
    name: str  # "start/train/0003"
    camera: Camera  # OpenCV axes
    rgb: np.ndarray  # [H,W,3] float32 in [0,1], straight (un-premultiplied) colour
    alpha: np.ndarray  # [H,W] float32 in [0,1], the object mask
    depth: np.ndarray | None = None  # [H,W] float32 metres of camera-space z, 0 = missing
    regions: np.ndarray | None = None  # [H,W] int32 SAM-style region ids, 0 = no region
    parts: np.ndarray | None = None  # [H,W] uint8 GT part ids (evaluation only)

    @property
    def state(self) -> str:
        return self.name.split("/")[0]


@dataclass
class GtJoint:
    type: str  # "revolute" | "prismatic"
    origin: np.ndarray  # [3] a point on the axis
    axis: np.ndarray  # [3] unit direction
    amount: float  # start -> end: degrees (revolute, right-hand rule about axis) or distance
    start: float = 0.0  # joint value in the start state (trans.json "l"; same units as amount)

    def __post_init__(self) -> None:
        if self.type not in ("revolute", "prismatic"):
            raise ValueError(f"joint type must be 'revolute' or 'prismatic', got {self.type!r}")
        self.origin = np.asarray(self.origin, dtype=np.float64).reshape(3)
        axis = np.asarray(self.axis, dtype=np.float64).reshape(3)
        norm = float(np.linalg.norm(axis))
        if not np.isfinite(norm) or norm < 1e-12:
            raise ValueError(f"joint axis must be a finite non-zero vector, got {axis}")
        self.axis = axis / norm
        self.amount = float(self.amount)
        self.start = float(self.start)

    def motion(self, fraction: float = 1.0) -> np.ndarray:
        """4x4 rigid transform of the moved part from the start state, `fraction` of the way."""
        out = np.eye(4)
        if self.type == "prismatic":
            out[:3, 3] = self.axis * self.amount * fraction
            return out
        angle = np.deg2rad(self.amount * fraction)
        k = np.array(
            [
                [0, -self.axis[2], self.axis[1]],
                [self.axis[2], 0, -self.axis[0]],
                [-self.axis[1], self.axis[0], 0],
            ]
        )
        rot = np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)
        out[:3, :3] = rot
        out[:3, 3] = self.origin - rot @ self.origin
        return out


@dataclass
class GroundTruth:
    joints: list[GtJoint]  # trans_info order; joint i moves part i+1
    meshes: dict[str, dict[str, Path]] = field(default_factory=dict)
    # state -> {"whole": p, "static": p, "part_0": p, ...} (only those present)


@dataclass
class Scene:
    root: Path
    views: dict[str, dict[str, list[View]]]  # state -> split -> views
    gt: GroundTruth | None = None
    layout: str = "ArtGS/GEAR"  # the on-disk layout it was read from (docs/scenes.md)
    warnings: list[str] = field(default_factory=list)  # inputs the loader found but did not use

    def train(self, state: str) -> list[View]:
        return self.views.get(state, {}).get("train", [])

    def test(self, state: str) -> list[View]:
        return self.views.get(state, {}).get("test", [])

    def all_views(self) -> list[View]:
        return [v for splits in self.views.values() for vs in splits.values() for v in vs]

    @property
    def has_depth(self) -> bool:
        views = self.all_views()
        return bool(views) and all(v.depth is not None for v in views)

    @property
    def has_regions(self) -> bool:
        views = self.all_views()
        return bool(views) and all(v.regions is not None for v in views)

    @property
    def has_parts(self) -> bool:
        views = self.all_views()
        return bool(views) and all(v.parts is not None for v in views)
