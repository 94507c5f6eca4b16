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
    tri = _Triangles(
        torch.cat([a, b, c, inv_z], 1),
        torch.stack([bx0, bx1, by0, by1, tx0, ty0, tw], 1),
    )

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
    """Per-triangle setup, packed so that one gather fetches everything a stage needs."""

    coef: torch.Tensor  # [F,12] float: edge functions a(3), b(3), c(3) (inside >= 0, summing
    # to 1), then 1/z of the three corners
    box: torch.Tensor  # [F,7] int64: pixel box x0, x1, y0, y1 (inclusive, clipped), first
    # tile tx0, ty0 and the tile-box width


def _expand(count: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """For items with `count` sub-items each: (item index, index within the item) per sub-item."""
    item = torch.repeat_interleave(torch.arange(len(count)), count)
    first = torch.cumsum(count, 0) - count
    return item, torch.arange(len(item), dtype=torch.int64) - first.index_select(0, item)


def _scatter_chunk(
    zbuf: torch.Tensor, tris: torch.Tensor, count: torch.Tensor, tri: _Triangles, width: int
) -> None:
    """z-test the pixels of `tris` into `zbuf`: first discard tiles that the triangle cannot
    touch (an edge function negative at all four tile corners), then test each pixel of the
    remaining tiles that lies in the triangle's bounding box."""
    item, local = _expand(count)
    t = tris.index_select(0, item)
    box = tri.box.index_select(0, t)
    x0 = (box[:, 4] + local % box[:, 6]) * TILE
    y0 = (box[:, 5] + torch.div(local, box[:, 6], rounding_mode="floor")) * TILE
    coef = tri.coef.index_select(0, t)
    a, b, c = coef[:, 0:3], coef[:, 3:6], coef[:, 6:9]
    # Max of each edge function over the tile's pixel centres is at one of its corners.
    xs = torch.where(a > 0, x0[:, None] + (TILE - 0.5), x0[:, None] + 0.5)
    ys = torch.where(b > 0, y0[:, None] + (TILE - 0.5), y0[:, None] + 0.5)
    keep = torch.nonzero(((a * xs + b * ys + c) >= _EDGE_EPS).all(1)).squeeze(1)
    t, box = t.index_select(0, keep), box.index_select(0, keep)
    x0, y0 = x0.index_select(0, keep), y0.index_select(0, keep)

    # The kept tiles' pixels inside the bounding box (tiny triangles cost only their pixels).
    rx0, ry0 = torch.maximum(x0, box[:, 0]), torch.maximum(y0, box[:, 2])
    rw = torch.minimum(x0 + TILE - 1, box[:, 1]) - rx0 + 1
    rh = torch.minimum(y0 + TILE - 1, box[:, 3]) - ry0 + 1
    item, local = _expand(rw * rh)
    rect = torch.stack([rx0, ry0, rw, t], 1).index_select(0, item)
    ix = rect[:, 0] + local % rect[:, 2]
    iy = rect[:, 1] + torch.div(local, rect[:, 2], rounding_mode="floor")
    t = rect[:, 3]
    coef = tri.coef.index_select(0, t)
    sx = ix.to(torch.float32)[:, None] + 0.5
    sy = iy.to(torch.float32)[:, None] + 0.5
    lin = coef[:, 0:3] * sx + coef[:, 3:6] * sy + coef[:, 6:9]  # screen barycentrics
    inv_depth = (lin * coef[:, 9:12]).sum(1)
    inside = (lin >= _EDGE_EPS).all(1) & (inv_depth > 0)
    depth_bits = (1.0 / inv_depth.clamp(min=1e-30)).view(torch.int32).to(torch.int64)
    key = torch.where(inside, (depth_bits << 32) | t, _NO_HIT)
    zbuf.scatter_reduce_(0, iy * width + ix, key, reduce="amin")
