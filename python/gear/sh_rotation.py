"""Turning spherical-harmonic colour with a rotation: the coefficients c' with
c'(d) = c(R^T d) for every view direction d, so Gaussians stored posed look as they did in the
frame their coefficients were learned in.

Each SH band is closed under rotation, so c' is a linear map of c. It is found by least squares
on sample directions with the basis of gear.sh itself (evaluated through the op, so the two can
never disagree on a constant or an ordering), exact to float64 rounding.
"""

from __future__ import annotations

import math

import torch

from gear.sh import sh_to_rgb

SAMPLES = 64  # directions to fit on: far more than the 16 coefficients of degree 3
# Coefficient used to read out one basis function: small enough that 0.5 + BASIS_PROBE * Y
# stays positive (|Y| < 1 up to degree 3), so the op's clamp at 0 never acts.
BASIS_PROBE = 0.1


def sample_directions(count: int = SAMPLES) -> torch.Tensor:
    """[count, 3] float64 unit vectors spread evenly over the sphere (Fibonacci lattice)."""
    i = torch.arange(count, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * i / count
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    r = torch.sqrt(1.0 - z * z)
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=1)


def sh_basis(dirs: torch.Tensor, count: int) -> torch.Tensor:
    """[M, count] float64: the first `count` basis functions of gear.sh at directions [M, 3]."""
    m = len(dirs)
    coeffs = torch.zeros(m, count, count, 3, dtype=torch.float64)
    coeffs[:, torch.arange(count), torch.arange(count), 0] = BASIS_PROBE
    rgb = sh_to_rgb(dirs.double().repeat_interleave(count, dim=0).contiguous(),
                    coeffs.reshape(m * count, count, 3))
    return ((rgb[:, 0] - 0.5) / BASIS_PROBE).reshape(m, count)


def rotation_matrix(rotation: torch.Tensor, count: int) -> torch.Tensor:
    """[count, count] float64 M with c' = M c for the rotation [3, 3] (count = (d+1)^2)."""
    dirs = sample_directions()
    rotated = dirs @ rotation.double()  # row i is R^T d_i
    return torch.linalg.lstsq(sh_basis(dirs, count), sh_basis(rotated, count)).solution


def rotate_sh(rest: torch.Tensor, rotation: torch.Tensor) -> torch.Tensor:
    """Bands 1..d [N, (d+1)^2 - 1, 3] turned by `rotation` [3, 3], same dtype (the degree-0
    term does not depend on direction and needs no turning)."""
    count = rest.shape[1] + 1
    m = rotation_matrix(rotation, count)[1:, 1:].to(rest.dtype)
    return torch.einsum("ij,njc->nic", m, rest)
