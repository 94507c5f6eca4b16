"""The rasterizer contract in pure torch: the yardstick of gear.splat, differentiable by autograd.

Every Gaussian is evaluated against every pixel (`rasterize_dense`), or against the pixels of
each block it may touch (`rasterize_tiled`, for scenes too big for a dense [pixels, N] table).
The maths is the one of docs/raster-contract.md, step by step: culling, EWA projection
with the clamped Jacobian and the 0.3 low-pass, the opacity-aware tile rectangle, alpha clamped
to 0.999, the 1/255 skip and the transmittance cut-off. Works in any float dtype (float64 for
gradient checks); the hard cut-offs are piecewise constant, so autograd treats them as the
contract does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch
from torch import Tensor

from gear.camera import Camera
from gear.kinematics import quat_to_matrix as _rotation
from gear.splat import RenderOutput, check_held

NEAR = 0.01
FAR = 1e4
LOW_PASS = 0.3
MIN_ALPHA = 1.0 / 255.0
MAX_ALPHA = 0.999
MIN_TRANSMITTANCE = 1e-4
CLAMP_FACTOR = 1.3
QUAT_EPS = 1e-12
TILE = 16


@dataclass
class Projected:
    """Per-Gaussian screen-space quantities; rows where `valid` is False contribute nothing."""

    depth: Tensor  # [N] camera-space z
    mean2d: Tensor  # [N,2] pixels
    conic: Tensor  # [N,3] (a, b, c) of inverse(Σ2D) = [[a, b], [b, c]]
    opacity: Tensor  # [N]
    features: Tensor  # [N,C]
    valid: Tensor  # [N] bool
    tiles: Tensor  # [N,4] int64: first and last tile column, first and last tile row

    def select(self, index: Tensor) -> Projected:
        """The rows picked by `index` (a permutation or a boolean mask)."""
        return Projected(*(getattr(self, f.name)[index] for f in fields(self)))


def _camera_tensors(camera: Camera, like: Tensor) -> tuple[Tensor, Tensor]:
    w2c = torch.as_tensor(camera.world_to_cam, dtype=like.dtype, device=like.device)
    return w2c[:3, :3], w2c[:3, 3]


def _project_values(
    means: Tensor,
    quats: Tensor,
    log_scales: Tensor,
    opacity_logits: Tensor,
    camera: Camera,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The differentiable projection: camera-space mean [N,3], 2D mean, Σ2D entries [N,3],
    determinant and opacity (no culling)."""
    rot_w, trans_w = _camera_tensors(camera, means)
    t = means @ rot_w.T + trans_w
    tx, ty, tz = t.unbind(-1)

    norm = torch.linalg.vector_norm(quats, dim=-1, keepdim=True)
    rot = _rotation(quats / norm.clamp_min(QUAT_EPS))
    factor = rot * torch.exp(log_scales)[:, None, :]  # R diag(s)
    cov3d = factor @ factor.transpose(1, 2)

    # Jacobian at the direction clamped to 1.3x the frustum; the clamped coordinate is a
    # constant (no gradient through the clamp), t.z keeps its own terms.
    def clamped(t_xy: Tensor, limit: float) -> Tensor:
        ratio = t_xy / tz
        outside = ratio.abs() > limit
        return torch.where(outside, (tz * ratio.clamp(-limit, limit)).detach(), t_xy)

    x_c = clamped(tx, CLAMP_FACTOR * 0.5 * camera.width / camera.fx)
    y_c = clamped(ty, CLAMP_FACTOR * 0.5 * camera.height / camera.fy)
    zero = torch.zeros_like(tz)
    jacobian = torch.stack(
        [
            torch.stack([camera.fx / tz, zero, -camera.fx * x_c / (tz * tz)], -1),
            torch.stack([zero, camera.fy / tz, -camera.fy * y_c / (tz * tz)], -1),
        ],
        1,
    )
    jw = jacobian @ rot_w
    cov2d = jw @ cov3d @ jw.transpose(1, 2)
    a = cov2d[:, 0, 0] + LOW_PASS
    b = cov2d[:, 0, 1]
    c = cov2d[:, 1, 1] + LOW_PASS
    det = a * c - b * b
    mean2d = torch.stack([camera.fx * tx / tz + camera.cx, camera.fy * ty / tz + camera.cy], -1)
    return t, mean2d, torch.stack([a, b, c], -1), det, torch.sigmoid(opacity_logits)


def _tile_rect(
    mean2d: Tensor, cov2d: Tensor, det: Tensor, opacity: Tensor, camera: Camera
) -> Tensor:
    """Tiles the box [u ± r] x [v ± r] overlaps, clipped to the image: [N,4] int64
    (x0, x1, y0, y1), empty when x0 > x1 or y0 > y1. No gradient."""
    a, c = cov2d[:, 0], cov2d[:, 2]
    mid = 0.5 * (a + c)
    lambda_max = mid + (mid * mid - det).clamp_min(0).sqrt()
    extent = 2 * torch.log(opacity / MIN_ALPHA).clamp_min(0) * lambda_max
    radius = extent.sqrt().ceil()
    tiles_x = math.ceil(camera.width / TILE)
    tiles_y = math.ceil(camera.height / TILE)
    u, v = mean2d.unbind(-1)
    x0 = torch.floor((u - radius) / TILE).clamp_min(0)
    x1 = torch.floor((u + radius) / TILE).clamp_max(tiles_x - 1)
    y0 = torch.floor((v - radius) / TILE).clamp_min(0)
    y1 = torch.floor((v + radius) / TILE).clamp_max(tiles_y - 1)
    rect = torch.stack([x0, x1, y0, y1], -1)
    # Huge or non-finite rows are culled by the caller; keep their casts defined.
    return torch.nan_to_num(rect, nan=-1.0).clamp(-1, 1 << 30).to(torch.int64)


def _validity(
    finite: Tensor,
    t: Tensor,
    mean2d: Tensor,
    cov2d: Tensor,
    det: Tensor,
    opacity: Tensor,
    rect: Tensor,
) -> Tensor:
    tz = t[:, 2]
    ok = finite & (tz >= NEAR) & (tz <= FAR) & (opacity >= MIN_ALPHA)
    ok &= (det > 0) & torch.isfinite(det)
    ok &= torch.isfinite(mean2d).all(-1) & torch.isfinite(cov2d).all(-1)
    ok &= (rect[:, 0] <= rect[:, 1]) & (rect[:, 2] <= rect[:, 3])
    return ok


def project(
    means: Tensor,
    quats: Tensor,
    log_scales: Tensor,
    opacity_logits: Tensor,
    features: Tensor,
    camera: Camera,
) -> Projected:
    """Culling and projection of every Gaussian (the contract's per-Gaussian stage).

    Validity is decided on the raw inputs without gradient; the differentiable pass then runs
    on inputs whose culled rows are replaced by a harmless Gaussian, so a culled row (NaN,
    overflowing scale, behind the camera) gets exactly zero gradient, never NaN.
    """
    inputs = (means, quats, log_scales, opacity_logits[:, None], features)
    finite = torch.stack([torch.isfinite(x).all(-1) for x in inputs]).all(0)
    with torch.no_grad():
        t, mean2d, cov2d, det, opacity = _project_values(
            means, quats, log_scales, opacity_logits, camera
        )
        rect = _tile_rect(mean2d, cov2d, det, opacity, camera)
        valid = _validity(finite, t, mean2d, cov2d, det, opacity, rect)

    rot_w, trans_w = _camera_tensors(camera, means)
    in_front = (torch.tensor([0.0, 0.0, 1.0], dtype=means.dtype) - trans_w) @ rot_w
    keep = valid[:, None]
    safe_means = torch.where(keep, means, in_front)
    safe_quats = torch.where(keep, quats, torch.tensor([1.0, 0, 0, 0], dtype=quats.dtype))
    safe_log_scales = torch.where(keep, log_scales, torch.zeros_like(log_scales))
    safe_logits = torch.where(valid, opacity_logits, torch.zeros_like(opacity_logits))
    safe_features = torch.where(keep, features, torch.zeros_like(features))

    t, mean2d, cov2d, det, opacity = _project_values(
        safe_means, safe_quats, safe_log_scales, safe_logits, camera
    )
    a, b, c = cov2d.unbind(-1)
    conic = torch.stack([c / det, -b / det, a / det], -1)
    return Projected(t[:, 2], mean2d, conic, opacity, safe_features, valid, rect)


def _blend(
    proj: Projected, cols: Tensor, rows: Tensor, background: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Front-to-back blend of the pixels (cols[k], rows[k]) over the Gaussians of `proj`,
    which must already be in increasing depth order. Returns features [P,C], alpha [P],
    depth [P]."""
    dx = (cols.to(proj.mean2d.dtype) + 0.5)[:, None] - proj.mean2d[:, 0]
    dy = (rows.to(proj.mean2d.dtype) + 0.5)[:, None] - proj.mean2d[:, 1]
    ca, cb, cc = proj.conic.unbind(-1)
    power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
    # Clamping power at 0 keeps exp finite where the guard skips anyway (power > 0).
    alpha = (proj.opacity * torch.exp(power.clamp_max(0))).clamp_max(MAX_ALPHA)

    tile_x, tile_y = (cols // TILE)[:, None], (rows // TILE)[:, None]
    x0, x1, y0, y1 = proj.tiles.unbind(-1)
    in_rect = (tile_x >= x0) & (tile_x <= x1) & (tile_y >= y0) & (tile_y <= y1)
    used = proj.valid & in_rect & (power <= 0) & (alpha >= MIN_ALPHA)
    alpha = torch.where(used, alpha, torch.zeros_like(alpha))

    # Stop before T would fall below the cut-off: T after k is non-increasing in k, so the
    # blended Gaussians are exactly those whose own T_next stays at or above it.
    with torch.no_grad():
        blended = torch.cumprod(1 - alpha, dim=1) >= MIN_TRANSMITTANCE
    alpha = torch.where(blended, alpha, torch.zeros_like(alpha))
    after = torch.cumprod(1 - alpha, dim=1)
    before = torch.cat([torch.ones_like(after[:, :1]), after[:, :-1]], dim=1)
    weights = alpha * before
    t_final = after[:, -1] if after.shape[1] > 0 else torch.ones_like(cols, dtype=dx.dtype)
    features = weights @ proj.features + t_final[:, None] * background
    return features, 1 - t_final, weights @ proj.depth


def _prepare(
    arrays: tuple[Tensor, ...], camera: Camera, background: Tensor | None
) -> tuple[Projected, Tensor]:
    """Projection of `arrays` (means, quats, log_scales, opacity_logits, features), depth order
    (stable: ties keep index order) and the background."""
    proj = project(*arrays, camera)
    features = arrays[4]
    order = torch.argsort(proj.depth.detach(), stable=True)
    proj = proj.select(order)
    if background is None:
        background = torch.zeros(features.shape[1], dtype=features.dtype)
    return proj, background.to(features.dtype)


def _hold(arrays: tuple[Tensor, ...], held: int) -> tuple[Tensor, ...]:
    """`arrays` with their first `held` rows cut from the graph (the caller's constants)."""
    held = check_held(held, arrays[0].shape[0])
    if held == 0:
        return arrays
    return tuple(torch.cat([a[:held].detach(), a[held:]]) for a in arrays)


def rasterize_dense(
    means: Tensor,
    quats: Tensor,
    log_scales: Tensor,
    opacity_logits: Tensor,
    features: Tensor,
    camera: Camera,
    background: Tensor | None = None,
    depth: bool = False,
    held: int = 0,
) -> RenderOutput:
    """Every Gaussian against every pixel: memory grows as H·W·N, for small scenes. The first
    `held` Gaussians pass no gradient (as gear.splat.rasterize)."""
    arrays = _hold((means, quats, log_scales, opacity_logits, features), held)
    proj, background = _prepare(arrays, camera, background)
    h, w = camera.height, camera.width
    rows, cols = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    image, alpha, depth_image = _blend(proj, cols.reshape(-1), rows.reshape(-1), background)
    return RenderOutput(
        features=image.reshape(h, w, -1),
        alpha=alpha.reshape(h, w),
        depth=depth_image.reshape(h, w) if depth else None,
    )


def rasterize_tiled(
    means: Tensor,
    quats: Tensor,
    log_scales: Tensor,
    opacity_logits: Tensor,
    features: Tensor,
    camera: Camera,
    background: Tensor | None = None,
    depth: bool = False,
    block: int = 16,
    held: int = 0,
) -> RenderOutput:
    """As `rasterize_dense`, one block of block x block pixels at a time, each against only the
    Gaussians whose tile rectangle meets it (block must be a multiple of the 16-pixel tile).
    Single 16-pixel tiles were the fastest blocks measured (10k Gaussians at 256x256: 2x faster
    than 32, 6x faster than 64): a pixel only meets the Gaussians of its own tile."""
    if block <= 0 or block % TILE:
        raise ValueError(f"block must be a positive multiple of {TILE}, got {block}")
    arrays = _hold((means, quats, log_scales, opacity_logits, features), held)
    proj, background = _prepare(arrays, camera, background)
    h, w = camera.height, camera.width
    per_tile = block // TILE
    x0, x1, y0, y1 = proj.tiles.unbind(-1)
    band_rows = []
    for top in range(0, h, block):
        band = []
        for left in range(0, w, block):
            bx, by = left // TILE, top // TILE
            meets = proj.valid & (x0 < bx + per_tile) & (x1 >= bx) & (y0 < by + per_tile)
            meets &= y1 >= by
            subset = proj.select(meets)
            bh, bw = min(block, h - top), min(block, w - left)
            rows, cols = torch.meshgrid(
                torch.arange(top, top + bh), torch.arange(left, left + bw), indexing="ij"
            )
            out = _blend(subset, cols.reshape(-1), rows.reshape(-1), background)
            band.append(
                torch.cat([out[0], out[1][:, None], out[2][:, None]], 1).reshape(bh, bw, -1)
            )
        band_rows.append(torch.cat(band, 1))
    stacked = torch.cat(band_rows, 0)
    channels = features.shape[1]
    return RenderOutput(
        features=stacked[..., :channels],
        alpha=stacked[..., channels],
        depth=stacked[..., channels + 1] if depth else None,
    )
