"""Articulated objects as the generator sees them: a static body plus rigid parts, each moved by
one joint attached to the static body, with geometry given at joint value 0."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import trimesh

from gear.data.scene import GtJoint


@dataclass
class Surface:
    """A coloured triangle mesh (world coordinates at joint value 0).

    Colour = face colour x (texture sample, if any) x (1 + pattern x solid texture); the solid
    texture is evaluated at these rest coordinates, so it moves with the part.
    """

    vertices: np.ndarray  # [V,3] float64
    faces: np.ndarray  # [F,3] int64
    colors: np.ndarray  # [F,3] float32 in [0,1]
    pattern: float = 0.0
    uv: np.ndarray | None = None  # [F,3,2] per-corner texture coordinates
    texture: np.ndarray | None = None  # [h,w,3] float32 in [0,1]

    def __post_init__(self) -> None:
        self.vertices = np.asarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        self.faces = np.asarray(self.faces, dtype=np.int64).reshape(-1, 3)
        colors = np.asarray(self.colors, dtype=np.float32)
        self.colors = np.broadcast_to(colors, (len(self.faces), 3)).copy()
        if (self.uv is None) != (self.texture is None):
            raise ValueError("a textured surface needs both uv and texture")

    def transformed(self, matrix: np.ndarray) -> Surface:
        v = self.vertices @ matrix[:3, :3].T + matrix[:3, 3]
        return Surface(v, self.faces, self.colors, self.pattern, self.uv, self.texture)


@dataclass
class Joint:
    """One degree of freedom; values in radians (revolute) or metres (prismatic)."""

    name: str
    type: str  # "revolute" | "prismatic"
    origin: np.ndarray  # [3] a point on the axis (world)
    axis: np.ndarray  # [3] direction (world)
    lower: float
    upper: float
    start: float  # value in the start state
    end: float  # value in the end state

    def __post_init__(self) -> None:
        for key, value in (("start", self.start), ("end", self.end)):
            if not self.lower - 1e-9 <= value <= self.upper + 1e-9:
                raise ValueError(
                    f"joint {self.name}: {key} value {value:.4g} is outside its limits "
                    f"[{self.lower:.4g}, {self.upper:.4g}]"
                )

    def gt(self) -> GtJoint:
        """The start -> end motion as ground truth (degrees for revolute joints)."""
        scale = 180.0 / np.pi if self.type == "revolute" else 1.0
        return GtJoint(
            self.type, self.origin, self.axis, (self.end - self.start) * scale, self.start * scale
        )

    def transformed(self, rotation: np.ndarray) -> Joint:
        """The same joint in a world rotated by `rotation` (3x3) about the origin."""
        return replace(self, origin=rotation @ self.origin, axis=rotation @ self.axis)

    def pose(self, value: float) -> np.ndarray:
        """4x4 transform of the part at joint `value` (from its geometry at value 0)."""
        scale = 180.0 / np.pi if self.type == "revolute" else 1.0
        return GtJoint(self.type, self.origin, self.axis, value * scale).motion()


@dataclass
class Part:
    joint: Joint
    surfaces: list[Surface]


@dataclass
class Articulated:
    name: str
    static: list[Surface]
    parts: list[Part] = field(default_factory=list)

    def posed(self, state: str) -> list[list[Surface]]:
        """Surfaces per part id (0 static, i+1 = parts[i]) in `state` ("start" | "end")."""
        out = [self.static]
        for part in self.parts:
            value = part.joint.start if state == "start" else part.joint.end
            pose = part.joint.pose(value)
            out.append([s.transformed(pose) for s in part.surfaces])
        return out

    def rotated(self, rotation: np.ndarray) -> Articulated:
        """The object in a world rotated by `rotation` (3x3) about the origin: geometry and
        joints alike, so every pose is the rotated pose."""
        matrix = np.eye(4)
        matrix[:3, :3] = rotation
        return Articulated(
            self.name,
            [s.transformed(matrix) for s in self.static],
            [Part(p.joint.transformed(rotation), [s.transformed(matrix) for s in p.surfaces])
             for p in self.parts],
        )

    def gt_meshes(self, state: str) -> dict[str, trimesh.Trimesh]:
        """GT meshes of `state`: "whole", "static", "part_i" (docs/scenes.md names)."""
        groups = self.posed(state)
        meshes = {"static": _merge(groups[0])}
        meshes.update({f"part_{i}": _merge(g) for i, g in enumerate(groups[1:])})
        meshes["whole"] = _merge([s for g in groups for s in g])
        return meshes


def _merge(surfaces: list[Surface]) -> trimesh.Trimesh:
    if not surfaces:
        return trimesh.Trimesh()
    offsets = np.cumsum([0] + [len(s.vertices) for s in surfaces[:-1]])
    return trimesh.Trimesh(
        np.concatenate([s.vertices for s in surfaces]),
        np.concatenate([s.faces + o for s, o in zip(surfaces, offsets, strict=True)]),
        process=False,
    )
