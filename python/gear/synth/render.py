"""Shade rasterised fragments: albedo (face colour x texture x solid texture), Lambertian +
ambient lighting from a fixed world direction, optional Blinn-Phong specular."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gear.camera import Camera
from gear.data.scene import BACKGROUND_PART
from gear.synth.model import Articulated
from gear.synth.raster import rasterize

LIGHT_DIR = np.array([0.35, -0.55, 0.76]) / np.linalg.norm([0.35, -0.55, 0.76])
AMBIENT, DIFFUSE = 0.35, 0.65
SPECULAR, SHININESS = 0.35, 16.0


@dataclass
class Packed:
    """All surfaces of one state as flat arrays (one entry per vertex or per face)."""

    vertices: np.ndarray  # [N,3] world, posed
    rest: np.ndarray  # [N,3] coordinates at joint value 0 (the solid texture lives there)
    faces: np.ndarray  # [F,3]
    normals: np.ndarray  # [F,3] unit face normals, posed
    part: np.ndarray  # [F] uint8 part id (0 static, i+1 moved by joint i)
    facet: np.ndarray  # [F] int64 (surface, dominant rest-normal side): region-mask seeds
    colors: np.ndarray  # [F,3]
    pattern: np.ndarray  # [F]
    uv: np.ndarray  # [F,3,2]
    texture: np.ndarray  # [F] index into `textures`, -1 for none
    textures: list[np.ndarray]


def pack(obj: Articulated, state: str) -> Packed:
    groups = [(obj.static, np.eye(4))]
    for part in obj.parts:
        value = part.joint.start if state == "start" else part.joint.end
        groups.append((part.surfaces, part.joint.pose(value)))
    verts, rest, faces, part_ids, colors, pattern, uvs, tex = [], [], [], [], [], [], [], []
    surface_ids = []
    textures: list[np.ndarray] = []
    texture_index: dict[int, int] = {}  # id(image) -> index: shared images are sampled once
    offset = 0
    for pid, (surfaces, pose) in enumerate(groups):
        for s in surfaces:
            rest.append(s.vertices)
            verts.append(s.vertices @ pose[:3, :3].T + pose[:3, 3])
            faces.append(s.faces + offset)
            offset += len(s.vertices)
            n = len(s.faces)
            part_ids.append(np.full(n, pid, dtype=np.uint8))
            surface_ids.append(np.full(n, len(surface_ids), dtype=np.int64))
            colors.append(s.colors)
            pattern.append(np.full(n, s.pattern, dtype=np.float32))
            if s.texture is not None:
                uvs.append(np.asarray(s.uv, dtype=np.float32))
                if id(s.texture) not in texture_index:
                    texture_index[id(s.texture)] = len(textures)
                    textures.append(s.texture)
                tex.append(np.full(n, texture_index[id(s.texture)]))
            else:
                uvs.append(np.zeros((n, 3, 2), dtype=np.float32))
                tex.append(np.full(n, -1))
    vertices, rest_all, faces_all = (
        np.concatenate(verts),
        np.concatenate(rest),
        np.concatenate(faces),
    )
    part_all = np.concatenate(part_ids)
    return Packed(
        vertices,
        rest_all,
        faces_all,
        _face_normals(vertices, faces_all),
        part_all,
        np.concatenate(surface_ids) * 6 + _dominant_side(_face_normals(rest_all, faces_all)),
        np.concatenate(colors),
        np.concatenate(pattern),
        np.concatenate(uvs),
        np.concatenate(tex),
        textures,
    )


def _face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    tri = vertices[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.where(norm > 0, norm, 1.0)


def _dominant_side(normals: np.ndarray) -> np.ndarray:
    axis = np.argmax(np.abs(normals), axis=1)
    return axis * 2 + (normals[np.arange(len(normals)), axis] > 0)


@dataclass
class SolidTexture:
    """A smooth 3D pattern in [-1, 1]: a few sinusoids of seeded directions and frequencies."""

    waves: np.ndarray  # [K,3] wave vectors (radians per metre)
    phases: np.ndarray  # [K]

    @classmethod
    def seeded(cls, seed: int, size: float) -> SolidTexture:
        rng = np.random.default_rng(seed + 7919)
        dirs = rng.normal(size=(5, 3))
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        cycles = np.array([3.0, 5.0, 8.0, 13.0, 21.0]) / max(size, 1e-6)
        return cls(dirs * cycles[:, None] * 2 * np.pi, rng.uniform(0, 2 * np.pi, 5))

    def rotated(self, rotation: np.ndarray) -> SolidTexture:
        """The same pattern on an object rotated by `rotation` (3x3), so it moves along."""
        return SolidTexture(self.waves @ rotation.T, self.phases)

    def __call__(self, points: np.ndarray) -> np.ndarray:
        return np.sin(points @ self.waves.T + self.phases).mean(axis=1)


@dataclass
class Rendered:
    rgb: np.ndarray  # [H,W,3] float32 (0 where alpha is 0)
    alpha: np.ndarray  # [H,W] float32 (0 or 1)
    depth: np.ndarray  # [H,W] float32 camera z in metres, 0 = background
    parts: np.ndarray  # [H,W] uint8, 255 = background
    facets: np.ndarray  # [H,W] int64 facet key, -1 = background


def render(
    packed: Packed,
    camera: Camera,
    solid: SolidTexture,
    specular: bool = False,
    light_dir: np.ndarray = LIGHT_DIR,
) -> Rendered:
    frags = rasterize(packed.vertices, packed.faces, camera)
    hit = frags.face >= 0
    face = frags.face[hit]
    bary = frags.bary[hit].astype(np.float64)
    corners = packed.faces[face]  # [P,3]
    world = np.einsum("pk,pkc->pc", bary, packed.vertices[corners])
    rest = np.einsum("pk,pkc->pc", bary, packed.rest[corners])

    albedo = packed.colors[face].astype(np.float64)
    albedo *= (1.0 + packed.pattern[face] * solid(rest))[:, None]
    textured = packed.texture[face] >= 0
    if textured.any():
        albedo[textured] *= _sample_textures(packed, face[textured], bary[textured])

    normal = packed.normals[face]
    to_eye = camera.center[None, :] - world
    to_eye /= np.linalg.norm(to_eye, axis=1, keepdims=True)
    normal = np.where((np.sum(normal * to_eye, axis=1) < 0)[:, None], -normal, normal)  # two-sided
    shade = AMBIENT + DIFFUSE * np.clip(normal @ light_dir, 0.0, None)
    color = albedo * shade[:, None]
    if specular:
        half = to_eye + light_dir
        half /= np.linalg.norm(half, axis=1, keepdims=True)
        color += SPECULAR * np.clip(np.sum(normal * half, axis=1), 0.0, None)[:, None] ** SHININESS

    h, w = hit.shape
    rgb = np.zeros((h, w, 3), dtype=np.float32)
    rgb[hit] = np.clip(color, 0.0, 1.0)
    parts = np.full((h, w), BACKGROUND_PART, dtype=np.uint8)
    parts[hit] = packed.part[face]
    facets = np.full((h, w), -1, dtype=np.int64)
    facets[hit] = packed.facet[face]
    return Rendered(rgb, hit.astype(np.float32), np.where(hit, frags.depth, 0.0), parts, facets)


def _sample_textures(packed: Packed, face: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """Bilinear texture lookups (uv origin bottom-left, repeating) for textured fragments."""
    uv = np.einsum("pk,pkc->pc", bary, packed.uv[face].astype(np.float64))
    out = np.ones((len(face), 3))
    index = packed.texture[face]
    for t in np.unique(index):
        sel = index == t
        img = packed.textures[t]
        th, tw = img.shape[:2]
        x = (uv[sel, 0] % 1.0) * tw - 0.5
        y = (1.0 - uv[sel, 1] % 1.0) * th - 0.5
        x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
        fx, fy = (x - x0)[:, None], (y - y0)[:, None]
        xa, xb = x0 % tw, (x0 + 1) % tw
        ya, yb = np.clip(y0, 0, th - 1), np.clip(y0 + 1, 0, th - 1)
        out[sel] = (
            img[ya, xa] * (1 - fx) * (1 - fy)
            + img[ya, xb] * fx * (1 - fy)
            + img[yb, xa] * (1 - fx) * fy
            + img[yb, xb] * fx * fy
        )
    return out
