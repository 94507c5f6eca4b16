"""Rigid motion as unit dual quaternions (torch, any float dtype, broadcasting): quaternions,
dual quaternions, screw interpolation, blending and posing. Per-part motions and the joints read
off them are in gear.articulation.

Conventions: quaternions are (w, x, y, z); a rigid motion p -> R p + t is the unit dual
quaternion (qr, qd) with qr the rotation and qd = 1/2 (0, t) qr. Motions map the canonical state
to the target state. Every function is differentiable and stays finite (values and gradients) at
the identity, at 180 degree rotations and for either sign of the quaternion (q and -q are the same
rotation), which the learned motions pass through during training.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

# Below this squared sine of the half angle the closed forms are replaced by Taylor series:
# at sin^2 = 1e-6 the dropped terms are ~1e-12 relative, below float64 noise for our use.
_SMALL_SIN2 = 1e-6


# ---------------------------------------------------------------- quaternions


def quat_identity(
    shape: Sequence[int] = (),
    dtype: torch.dtype = torch.float32,
    device: torch.device | None = None,
) -> torch.Tensor:
    """Identity rotations, shape [*shape, 4]."""
    q = torch.zeros((*shape, 4), dtype=dtype, device=device)
    q[..., 0] = 1.0
    return q


def quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a * b (apply b first, then a)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )


def quat_conj(q: torch.Tensor) -> torch.Tensor:
    """Conjugate (the inverse of a unit quaternion)."""
    return torch.cat([q[..., :1], -q[..., 1:]], dim=-1)


def safe_norm(x: torch.Tensor, dim: int = -1, keepdim: bool = False) -> torch.Tensor:
    """Euclidean norm whose gradient is 0 (not NaN) at the zero vector."""
    sq = (x * x).sum(dim=dim, keepdim=keepdim)
    zero = sq <= 0
    return torch.where(zero, torch.zeros_like(sq), torch.sqrt(torch.where(zero, 1.0, sq)))


def quat_normalize(q: torch.Tensor) -> torch.Tensor:
    """Unit quaternion; a zero quaternion becomes the identity instead of NaN."""
    n = safe_norm(q, keepdim=True)
    ok = n > 0
    unit = q / torch.where(ok, n, 1.0)
    return torch.where(ok, unit, quat_identity(q.shape[:-1], q.dtype, q.device))


def quat_rotate(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotates vectors v [..., 3] by unit quaternions q [..., 4]."""
    shape = torch.broadcast_shapes(q.shape[:-1], v.shape[:-1])
    q, v = q.expand(*shape, 4), v.expand(*shape, 3)
    w, u = q[..., :1], q[..., 1:]
    uv = torch.linalg.cross(u, v, dim=-1)
    return v + 2.0 * (w * uv + torch.linalg.cross(u, uv, dim=-1))


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [..., 3, 3] of unit quaternions."""
    w, x, y, z = q.unbind(-1)
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return torch.stack([torch.stack(r, dim=-1) for r in rows], dim=-2)


def quat_from_matrix(m: torch.Tensor) -> torch.Tensor:
    """Unit quaternions (w >= 0) of rotation matrices [..., 3, 3].

    Each of the four algebraically equivalent formulas divides by one component; the one with the
    largest component is used, so 180 degree rotations (w = 0) are as accurate as small ones.
    """
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    # 4 * component^2 for w, x, y, z.
    four_sq = torch.stack(
        [1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1
    )
    # Row i is 4 * component_i * (w, x, y, z).
    candidates = torch.stack(
        [
            torch.stack([four_sq[..., 0], m21 - m12, m02 - m20, m10 - m01], -1),
            torch.stack([m21 - m12, four_sq[..., 1], m10 + m01, m02 + m20], -1),
            torch.stack([m02 - m20, m10 + m01, four_sq[..., 2], m12 + m21], -1),
            torch.stack([m10 - m01, m20 + m02, m21 + m12, four_sq[..., 3]], -1),
        ],
        dim=-2,
    )
    best = four_sq.argmax(dim=-1, keepdim=True)
    pick = torch.gather(candidates, -2, best[..., None].expand(*best.shape, 4)).squeeze(-2)
    q = quat_normalize(pick)
    return torch.where(q[..., :1] < 0, -q, q)


def quat_from_axis_angle(axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Rotation by `angle` radians (right-handed) about the unit `axis` [..., 3]."""
    half = torch.as_tensor(angle, dtype=axis.dtype, device=axis.device)[..., None] / 2
    return torch.cat([torch.cos(half), torch.sin(half) * axis], dim=-1)


def quat_axis_angle(q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(unit axis [..., 3], angle in [0, 2 pi) radians) of unit quaternions q [..., 4] with
    q = quat_from_axis_angle(axis, angle): the axis keeps the sign of q's vector part, so a
    motion moved onto a nearby axis of the same sign keeps its turn. The identity's axis is
    the zero vector (it has none)."""
    vector = q[..., 1:]
    length = safe_norm(vector, keepdim=True)
    axis = vector / length.clamp(min=torch.finfo(q.dtype).tiny)
    return axis, 2.0 * torch.atan2(length[..., 0], q[..., 0])


def quat_angle(q: torch.Tensor) -> torch.Tensor:
    """Rotation angle in [0, pi] of unit quaternions (the same for q and -q)."""
    return 2.0 * torch.atan2(safe_norm(q[..., 1:]), q[..., 0].abs())


def _sin_ratio(s: torch.Tensor, half: torch.Tensor, sin2: torch.Tensor) -> torch.Tensor:
    """sin(s * half) / sin(half), with its limit s * (1 + (1 - s^2) half^2 / 6) near half = 0."""
    small = sin2 < _SMALL_SIN2
    safe_half = torch.where(small, torch.ones_like(half), half)
    exact = torch.sin(s * safe_half) / torch.sin(safe_half)
    series = s * (1 + (1 - s * s) * sin2 / 6)
    return torch.where(small, series, exact)


def _half_angle(q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Half rotation angle in [0, pi/2] of a unit quaternion with w >= 0, and sin^2 of it."""
    sin2 = (q[..., 1:] ** 2).sum(-1)
    return torch.atan2(safe_norm(q[..., 1:]), q[..., 0]), sin2


# ---------------------------------------------------------------- dual quaternions


def dq_from_rt(quat: torch.Tensor, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit dual quaternion of the motion p -> R(quat) p + t."""
    qr = quat_normalize(quat)
    t4 = torch.cat([torch.zeros_like(t[..., :1]), t], dim=-1)
    return qr, 0.5 * quat_mul(t4, qr)


def dq_to_rt(qr: torch.Tensor, qd: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(rotation quaternion, translation [..., 3]) of a unit dual quaternion."""
    return qr, 2.0 * quat_mul(qd, quat_conj(qr))[..., 1:]


def dq_mul(
    a: tuple[torch.Tensor, torch.Tensor], b: tuple[torch.Tensor, torch.Tensor]
) -> tuple[torch.Tensor, torch.Tensor]:
    """Composition a * b: apply motion b, then motion a."""
    return quat_mul(a[0], b[0]), quat_mul(a[0], b[1]) + quat_mul(a[1], b[0])


def dq_conj(qr: torch.Tensor, qd: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Inverse of a unit dual quaternion (quaternion conjugate of both halves)."""
    return quat_conj(qr), quat_conj(qd)


def dq_normalize(qr: torch.Tensor, qd: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest unit dual quaternion: |qr| = 1 and qr . qd = 0."""
    n = safe_norm(qr, keepdim=True)
    ok = n > 0
    scale = torch.where(ok, n, 1.0)
    unit_r = torch.where(ok, qr / scale, quat_identity(qr.shape[:-1], qr.dtype, qr.device))
    unit_d = qd / scale
    unit_d = unit_d - (unit_r * unit_d).sum(-1, keepdim=True) * unit_r
    return unit_r, unit_d


def dq_apply(qr: torch.Tensor, qd: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Transforms points [..., 3] by unit dual quaternions (broadcast against the points)."""
    _, t = dq_to_rt(qr, qd)
    return quat_rotate(qr, points) + t


def dq_sclerp(
    qr: torch.Tensor, qd: torch.Tensor, s: float | torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Screw-linear interpolation from the identity (s = 0) to the motion (s = 1).

    The motion is the screw "rotate by theta about a line, slide d along it"; at s it is
    "rotate by s*theta about the same line, slide s*d". A pure rotation thus swings about its
    hinge and a pure translation slides. The shorter of the two screws q, -q is used.

    Closed form, smooth at theta = 0: with a = theta/2 and v the vector part of qr,
      qr(s) = (cos(s a), f(s) v),   f(c) = sin(c a) / sin(a),
      t(s)  = f(s) * rotate(theta (s-1)/2, t) + (s - f(s)) / sin^2(a) * (t . v) v,
    the rotation by theta (s-1)/2 about the axis being the quaternion
    (cos((s-1) a/2), f((s-1)/2) v).
    """
    qr, qd = dq_normalize(qr, qd)
    flip = qr[..., :1] < 0
    qr, qd = torch.where(flip, -qr, qr), torch.where(flip, -qd, qd)
    _, t = dq_to_rt(qr, qd)
    s = torch.as_tensor(s, dtype=qr.dtype, device=qr.device)
    half, sin2 = _half_angle(qr)
    v = qr[..., 1:]

    f_s = _sin_ratio(s, half, sin2)
    c = (s - 1) / 2
    q_back = torch.cat(
        [torch.cos(c * half)[..., None], _sin_ratio(c, half, sin2)[..., None] * v], -1
    )
    # (s - f(s)) / sin^2(a), with its series -s (1 - s^2) / 6 near a = 0.
    small = sin2 < _SMALL_SIN2
    slide = torch.where(small, -s * (1 - s * s) / 6, (s - f_s) / torch.where(small, 1.0, sin2))
    t_s = f_s[..., None] * quat_rotate(q_back, t) + (slide * (t * v).sum(-1))[..., None] * v
    qr_s = torch.cat([torch.cos(s * half)[..., None], f_s[..., None] * v], dim=-1)
    return dq_from_rt(qr_s, t_s)


def dq_blend(
    qr: torch.Tensor, qd: torch.Tensor, weights: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Linear dual-quaternion blending: part motions [K, 4] mixed by weights [N, K].

    Each part is first sign-aligned with the heaviest part of the point (q and -q are the same
    motion, but averaging q with -q would cancel), then blended and normalised.
    """
    if weights.shape[-1] != qr.shape[0]:
        raise ValueError(f"weights: expected [N, {qr.shape[0]}], got {list(weights.shape)}")
    lead = weights.argmax(dim=-1)
    # [N, K]: dot product of every part's rotation with the point's leading part's.
    agree = (qr[lead][:, None, :] * qr[None]).sum(-1)
    signed = weights * torch.where(agree < 0, -1.0, 1.0).to(weights.dtype)
    return dq_normalize(signed @ qr, signed @ qd)


def deform(
    means: torch.Tensor,
    quats: torch.Tensor,
    weights: torch.Tensor,
    qr: torch.Tensor,
    qd: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Moves Gaussians [N] by the blend of K part motions; returns (means', quats').

    Each Gaussian's own rotation is composed with the blended rotation (applied after it), so
    its shape turns with its part.
    """
    bqr, bqd = dq_blend(qr, qd, weights)
    return dq_apply(bqr, bqd, means), quat_mul(bqr, quats)



def pose_parts(
    means: torch.Tensor,
    quats: torch.Tensor,
    part_ids: torch.Tensor,
    qr: torch.Tensor,
    qd: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Moves each Gaussian rigidly with its part (hard assignment: part_ids [N] index the K
    motions qr, qd [K,4]); returns (means', quats') in the dtype of `means`. Training's
    M-step, the written outputs and the twin all pose this way."""
    weights = torch.nn.functional.one_hot(part_ids, qr.shape[0]).to(means.dtype)
    return deform(means, quats, weights, qr, qd)
