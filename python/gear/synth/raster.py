"""A vectorised z-buffer triangle rasteriser (torch, CPU).

Every (triangle, pixel-in-its-bounding-box) pair is enumerated at once (after a coarse
tile-level rejection), tested against the
triangle's edge functions, and the nearest hit per pixel wins through one `scatter_reduce(amin)`
on a key that packs (depth bits, triangle index) into an int64: positive float32 bit patterns
order like the floats, so the minimum key is the nearest triangle. Pairs are processed in chunks
to bound memory. Triangles are two-sided; triangles with a vertex behind the near plane are
dropped (cameras always look at the object from outside its bounding sphere).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from gear.camera import Camera

_MAX_PAIRS = 1 << 22  # (triangle, pixel) pairs per chunk: ~200 MB of temporaries
_NO_HIT = torch.iinfo(torch.int64).max
_EDGE_EPS = -1e-7  # inclusive edges: shared edges leave no cracks (the z-buffer resolves ties)
TILE = 8  # coarse tiles reject most of the bounding box of long thin triangles cheaply


@dataclass
class Fragments:
    """Per-pixel rasterisation result for an H x W image."""

    face: np.ndarray  # [H,W] int64 triangle index, -1 where nothing is hit
    bary: np.ndarray  # [H,W,3] float32 perspective-correct barycentrics (0 where no hit)
    depth: np.ndarray  # [H,W] float32 camera-space z (0 where no hit)


def rasterize(
    vertices: np.ndarray, faces: np.ndarray, camera: Camera, near: float = 1e-3
) -> Fragments:
    """Rasterise world-space triangles (`vertices` [N,3], `faces` [F,3]) into `camera`."""
    w2c = torch.as_tensor(camera.world_to_cam, dtype=torch.float64)
    v = torch.as_tensor(np.asarray(vertices), dtype=torch.float64)
    cam = (v @ w2c[:3, :3].T + w2c[:3, 3]).to(torch.float32)
    f = torch.as_tensor(np.asarray(faces), dtype=torch.int64)
    width, height = camera.width, camera.height
    z = cam[:, 2]
    safe_z = torch.where(z > near, z, torch.ones_like(z))
    px = camera.fx * cam[:, 0] / safe_z + camera.cx
    py = camera.fy * cam[:, 1] / safe_z + camera.cy

    fx_, fy_, fz = px[f], py[f], z[f]  # [F,3]
    # Edge function of the edge opposite vertex i: e_i(x, y) = a_i x + b_i y + c_i.
    x0, x1, x2 = fx_.unbind(1)
    y0, y1, y2 = fy_.unbind(1)
    a = torch.stack([y1 - y2, y2 - y0, y0 - y1], 1)
    b = torch.stack([x2 - x1, x0 - x2, x1 - x0], 1)
    c = torch.stack([x1 * y2 - x2 * y1, x2 * y0 - x0 * y2, x0 * y1 - x1 * y0], 1)
    area = c.sum(1)  # twice the signed area (e_0 + e_1 + e_2 at any point)
    visible = (fz > near).all(1) & (area.abs() > 1e-10)
    inv_area = torch.where(visible, 1.0 / torch.where(visible, area, 1.0), 0.0)
    a, b, c = a * inv_area[:, None], b * inv_area[:, None], c * inv_area[:, None]
    inv_z = 1.0 / torch.where(fz > near, fz, 1.0)

    # Pixel (i, j) has its centre at (i + 0.5, j + 0.5); bounding boxes in tiles of TILE pixels.
    bx0 = torch.ceil(fx_.min(1).values - 0.5).clamp(0, width).to(torch.int64)
    bx1 = torch.floor(fx_.max(1).values - 0.5).clamp(-1, width - 1).to(torch.int64)
    by0 = torch.ceil(fy_.min(1).values - 0.5).clamp(0, height).to(torch.int64)
    by1 = torch.floor(fy_.max(1).values - 0.5).clamp(-1, height - 1).to(torch.int64)
    visible &= (bx1 >= bx0) & (by1 >= by0)
    tx0, ty0 = (
        torch.div(bx0, TILE, rounding_mode="floor"),
        torch.div(by0, TILE, rounding_mode="floor"),
    )
    tw = torch.div(bx1, TILE, rounding_mode="floor") - tx0 + 1
    th = torch.div(by1, TILE, rounding_mode="floor") - ty0 + 1
    count = tw * th * visible
    tris = torch.nonzero(count).squeeze(1)
    count = count[tris]
    tri = _Triangles(a, b, c, inv_z, bx0, bx1, by0, by1, tx0, ty0, tw)

    zbuf = torch.full((height * width,), _NO_HIT, dtype=torch.int64)
    ends = torch.cumsum(count, 0)
    budget = max(1, _MAX_PAIRS // (TILE * TILE))
    start = 0
    while start < len(tris):
        # Largest chunk of triangles whose tiles fit the budget (at least one triangle).
        base = ends[start - 1] if start else torch.tensor(0)
        stop = max(int(torch.searchsorted(ends, base + budget, right=True)), start + 1)
        _scatter_chunk(zbuf, tris[start:stop], count[start:stop], tri, width)
        start = stop

    hit = zbuf != _NO_HIT
    face = torch.where(hit, zbuf & 0xFFFFFFFF, torch.full_like(zbuf, -1))
    pix = torch.nonzero(hit).squeeze(1)
    t = face[pix]
    sx = (pix % width).to(torch.float32) + 0.5
    sy = torch.div(pix, width, rounding_mode="floor").to(torch.float32) + 0.5
    lin = (a[t] * sx[:, None] + b[t] * sy[:, None] + c[t]).clamp(min=0.0)
    persp = lin * inv_z[t]
    denom = persp.sum(1, keepdim=True)
    bary = torch.zeros((height * width, 3), dtype=torch.float32)
    depth = torch.zeros(height * width, dtype=torch.float32)
    bary[pix] = persp / denom
    depth[pix] = 1.0 / denom.squeeze(1)
    return Fragments(
        face.reshape(height, width).numpy(),
        bary.reshape(height, width, 3).numpy(),
        depth.reshape(height, width).numpy(),
    )


@dataclass
class _Triangles:
    """Per-triangle setup: normalised edge functions, 1/z per corner, pixel and tile boxes."""

    a: torch.Tensor  # [F,3] edge-function x coefficients (inside >= 0, summing to 1)
    b: torch.Tensor
    c: torch.Tensor
    inv_z: torch.Tensor  # [F,3]
    bx0: torch.Tensor  # [F] inclusive pixel bounding box, clipped to the image
    bx1: torch.Tensor
    by0: torch.Tensor
    by1: torch.Tensor
    tx0: torch.Tensor  # [F] first tile and tile-box width
    ty0: torch.Tensor
    tw: torch.Tensor


def _scatter_chunk(
    zbuf: torch.Tensor,
    tris: torch.Tensor,
    count: torch.Tensor,
    tri: _Triangles,
    width: int,
) -> None:
    """z-test the pixels of `tris` into `zbuf`: first discard tiles that the triangle cannot
    touch (an edge function negative at all four tile corners), then test each pixel of the
    remaining tiles."""
    t = torch.repeat_interleave(tris, count)
    first = torch.cumsum(count, 0) - count
    local = torch.arange(len(t), dtype=torch.int64) - torch.repeat_interleave(first, count)
    w = tri.tw[t]
    x0 = (tri.tx0[t] + local % w) * TILE
    y0 = (tri.ty0[t] + torch.div(local, w, rounding_mode="floor")) * TILE
    a, b, c = tri.a[t], tri.b[t], tri.c[t]
    # Max of each edge function over the tile's pixel centres is at one of its corners.
    xs = torch.where(a > 0, x0[:, None] + (TILE - 0.5), x0[:, None] + 0.5)
    ys = torch.where(b > 0, y0[:, None] + (TILE - 0.5), y0[:, None] + 0.5)
    keep = ((a * xs + b * ys + c) >= _EDGE_EPS).all(1)
    t, x0, y0 = t[keep], x0[keep], y0[keep]

    # Pixels of each kept tile that lie inside the triangle's bounding box (tiny triangles
    # cost only their few pixels).
    rx0, ry0 = torch.maximum(x0, tri.bx0[t]), torch.maximum(y0, tri.by0[t])
    rw = torch.minimum(x0 + TILE - 1, tri.bx1[t]) - rx0 + 1
    rh = torch.minimum(y0 + TILE - 1, tri.by1[t]) - ry0 + 1
    n = rw * rh
    pair = torch.repeat_interleave(torch.arange(len(t)), n)
    local = torch.arange(len(pair), dtype=torch.int64) - torch.repeat_interleave(
        torch.cumsum(n, 0) - n, n
    )
    w = rw[pair]
    ix = rx0[pair] + local % w
    iy = ry0[pair] + torch.div(local, w, rounding_mode="floor")
    t = t[pair]
    sx = ix.to(torch.float32) + 0.5
    sy = iy.to(torch.float32) + 0.5
    lin = tri.a[t] * sx[:, None] + tri.b[t] * sy[:, None] + tri.c[t]  # screen barycentrics
    inside = (lin >= _EDGE_EPS).all(1)
    inv_depth = (lin * tri.inv_z[t]).sum(1)
    inside &= inv_depth > 0
    depth = 1.0 / inv_depth[inside]
    key = (depth.view(torch.int32).to(torch.int64) << 32) | t[inside]
    zbuf.scatter_reduce_(0, (iy * width + ix)[inside], key, reduce="amin")
