"""Primitive surfaces (boxes, cylinders, hollow shells) with a simple varied appearance."""

from __future__ import annotations

import colorsys

import numpy as np
import trimesh

from gear.synth.model import Surface

FACE_JITTER = 0.08  # relative brightness spread between the flat faces of a primitive
PATTERN = 0.22  # default solid-texture amplitude: gives photometric losses gradients to follow


def tint(rng: np.random.Generator, hue: float, sat: float, val: float) -> np.ndarray:
    """An RGB colour near (hue, sat, val), varied by the seed."""
    h = (hue + rng.uniform(-0.03, 0.03)) % 1.0
    s = float(np.clip(sat + rng.uniform(-0.08, 0.08), 0, 1))
    v = float(np.clip(val + rng.uniform(-0.08, 0.08), 0.05, 0.95))
    return np.array(colorsys.hsv_to_rgb(h, s, v), dtype=np.float32)


def _faceted_colors(
    mesh: trimesh.Trimesh, color: np.ndarray, rng: np.random.Generator
) -> np.ndarray:
    """One brightness per flat side (faces grouped by dominant normal direction)."""
    normals = mesh.face_normals
    dominant = np.argmax(np.abs(normals), axis=1)
    side = dominant * 2 + (normals[np.arange(len(normals)), dominant] > 0)
    gains = 1.0 + rng.uniform(-FACE_JITTER, FACE_JITTER, size=6)
    return np.clip(color[None, :] * gains[side][:, None], 0.0, 1.0).astype(np.float32)


def box(
    size: tuple[float, float, float],
    center: tuple[float, float, float],
    color: np.ndarray,
    rng: np.random.Generator,
    pattern: float = PATTERN,
) -> Surface:
    mesh = trimesh.creation.box(extents=size)
    mesh.apply_translation(center)
    return Surface(mesh.vertices, mesh.faces, _faceted_colors(mesh, color, rng), pattern)


def cylinder(
    radius: float,
    length: float,
    center: tuple[float, float, float],
    axis: str,
    color: np.ndarray,
    rng: np.random.Generator,
    pattern: float = PATTERN,
    sections: int = 20,
) -> Surface:
    """A cylinder along the world axis "x", "y" or "z"."""
    mesh = trimesh.creation.cylinder(radius=radius, height=length, sections=sections)
    if axis == "x":
        mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    elif axis == "y":
        mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    mesh.apply_translation(center)
    return Surface(mesh.vertices, mesh.faces, _faceted_colors(mesh, color, rng), pattern)


def shell(
    size: tuple[float, float, float],
    center: tuple[float, float, float],
    wall: float,
    color: np.ndarray,
    rng: np.random.Generator,
    open_side: str = "-y",
) -> list[Surface]:
    """A hollow box with walls of thickness `wall`, open on `open_side` ("-y" front, "+z" top)."""
    w, d, h = size
    cx, cy, cz = center
    inner = tint(rng, *colorsys.rgb_to_hsv(*(color * 0.8)))
    walls = {
        "-x": ((wall, d, h), (cx - w / 2 + wall / 2, cy, cz)),
        "+x": ((wall, d, h), (cx + w / 2 - wall / 2, cy, cz)),
        "-y": ((w - 2 * wall, wall, h - 2 * wall), (cx, cy - d / 2 + wall / 2, cz)),
        "+y": ((w - 2 * wall, wall, h - 2 * wall), (cx, cy + d / 2 - wall / 2, cz)),
        "-z": ((w - 2 * wall, d, wall), (cx, cy, cz - h / 2 + wall / 2)),
        "+z": ((w - 2 * wall, d, wall), (cx, cy, cz + h / 2 - wall / 2)),
    }
    if open_side in ("-z", "+z"):  # a top/bottom opening: side walls span the full height
        for key in ("-y", "+y"):
            (sw, sd, sh), c = walls[key]
            walls[key] = ((sw, sd, h), c)
        for key in ("-z", "+z"):
            (sw, sd, sh), c = walls[key]
            walls[key] = ((sw, d - 2 * wall, sh), c)
    del walls[open_side]
    out = []
    for key, (s, c) in walls.items():
        out.append(box(s, c, color if key != "+y" else inner, rng))
    return out
