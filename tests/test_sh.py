"""The spherical-harmonic colour op (gear.sh): both executors against an independent float64
torch implementation (forward and autograd gradients), gradcheck of the op's float64 path,
the hard cases (zero and tiny directions, huge coefficients, N = 0) and its errors."""

from __future__ import annotations

import pytest
import torch

from gear import splat
from gear.sh import MAX_DEGREE, SH_C0, coefficient_count, sh_to_rgb

C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
      0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
      -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def torch_unclamped(dirs: torch.Tensor, coeffs: torch.Tensor) -> torch.Tensor:
    """The op before its clamp at 0, written out in torch (3D Gaussian Splatting's
    formulas), for autograd."""
    norm = dirs.norm(dim=1, keepdim=True)
    short = norm < 1e-12
    u = torch.where(short, 0.0, dirs / torch.where(short, 1.0, norm))
    x, y, z = u[:, 0:1], u[:, 1:2], u[:, 2:3]
    xx, yy, zz = x * x, y * y, z * z
    basis = [torch.full_like(x, SH_C0), -C1 * y, C1 * z, -C1 * x,
             C2[0] * x * y, C2[1] * y * z, C2[2] * (2 * zz - xx - yy), C2[3] * x * z,
             C2[4] * (xx - yy),
             C3[0] * y * (3 * xx - yy), C3[1] * x * y * z, C3[2] * y * (4 * zz - xx - yy),
             C3[3] * z * (2 * zz - 3 * xx - 3 * yy), C3[4] * x * (4 * zz - xx - yy),
             C3[5] * z * (xx - yy), C3[6] * x * (xx - 3 * yy)]
    k = coeffs.shape[1]
    return 0.5 + sum(basis[j] * coeffs[:, j] for j in range(k))


def inputs(n: int, degree: int, scale: float = 1.0, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    dirs = torch.randn(n, 3, generator=g) * torch.rand(n, 1, generator=g).add(0.1) * 5
    if n >= 4:
        dirs[0] = 0.0  # the camera at the centre
        dirs[1] = 1e-14  # below the 1e-12 cut-off
        dirs[2] *= 1e-9  # just above it
    coeffs = (torch.rand(n, coefficient_count(degree), 3, generator=g) * 2 - 1) * scale
    return dirs, coeffs


@pytest.mark.parametrize("backend", splat.BACKENDS)
@pytest.mark.parametrize("degree", range(MAX_DEGREE + 1))
@pytest.mark.parametrize(("n", "scale"), [(0, 1.0), (1, 1.0), (500, 1.0), (200, 1e5)])
def test_executors_match_torch_float64(backend, degree, n, scale):
    dirs, coeffs = inputs(n, degree, scale, seed=degree)
    upstream = torch.randn(n, 3, generator=torch.Generator().manual_seed(9))

    d32, c32 = dirs.clone().requires_grad_(True), coeffs.clone().requires_grad_(True)
    rgb = sh_to_rgb(d32, c32, backend=backend)
    (rgb * upstream).sum().backward()

    d64 = dirs.double().requires_grad_(True)
    c64 = coeffs.double().requires_grad_(True)
    pre = torch_unclamped(d64, c64)
    (pre.clamp_min(0.0) * upstream.double()).sum().backward()
    want_dirs = torch.zeros_like(d64) if d64.grad is None else d64.grad  # degree 0: no path

    assert rgb.dtype == torch.float32 and rgb.shape == (n, 3)
    magnitude = 1 + coeffs.double().abs().sum(dim=(1, 2))  # per Gaussian
    want = pre.detach().clamp_min(0.0)
    assert torch.all((rgb.double() - want).abs() <= 2e-6 * magnitude[:, None])
    assert torch.isfinite(c32.grad).all() and torch.isfinite(d32.grad).all()
    # A Gaussian with a channel within rounding of the clamp may take either side of it in
    # float32: its gradients are not compared.
    far = (pre.detach().abs() > 1e-4 * magnitude[:, None]).all(dim=1)
    assert torch.all((c32.grad.double() - c64.grad)[far].abs() <= 2e-6)
    norm = dirs.double().norm(dim=1)
    bound = torch.where(norm > 0, magnitude / norm.clamp_min(1e-300), 0.0)
    err = (d32.grad.double() - want_dirs).abs().max(dim=1).values
    assert torch.all(err[far] <= 2e-5 * bound[far])


@pytest.mark.parametrize("degree", range(MAX_DEGREE + 1))
def test_float64_path_passes_gradcheck(degree):
    # Central differences of the Rust f64 reference against its own backward.
    dirs, coeffs = inputs(12, degree, seed=3 + degree)
    dirs = dirs[4:].double().requires_grad_(True)  # smooth directions only (no cut-off)
    coeffs = (coeffs[4:].double() * 0.3).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda d, c: sh_to_rgb(d, c), (dirs, coeffs))


@pytest.mark.parametrize("backend", splat.BACKENDS)
def test_short_directions_give_finite_colours_and_zero_direction_gradients(backend):
    dirs = torch.tensor([[0.0, 0.0, 0.0], [1e-14, 0.0, -1e-14]], requires_grad=True)
    coeffs = torch.randn(2, 16, 3, generator=torch.Generator().manual_seed(1))
    coeffs.requires_grad_(True)
    rgb = sh_to_rgb(dirs, coeffs, backend=backend)
    rgb.sum().backward()
    expected = (0.5 + SH_C0 * coeffs.detach()[:, 0]).clamp_min(0)
    torch.testing.assert_close(rgb.detach(), expected)
    assert torch.equal(dirs.grad, torch.zeros(2, 3))
    assert torch.isfinite(coeffs.grad).all()


def test_bad_inputs_are_one_line_errors():
    dirs, coeffs = torch.zeros(3, 3), torch.zeros(3, 4, 3)
    with pytest.raises(ValueError, match=r"'coeffs' must have shape \[3, K, 3\]"):
        sh_to_rgb(dirs, torch.zeros(3, 5, 3))
    with pytest.raises(ValueError, match=r"'dirs' must have shape \[N, 3\]"):
        sh_to_rgb(torch.zeros(3, 2), coeffs)
    with pytest.raises(TypeError, match="share a dtype"):
        sh_to_rgb(dirs.double(), coeffs)
    with pytest.raises(TypeError, match="float32 or float64"):
        sh_to_rgb(dirs.half(), coeffs.half())
    bad = dirs.clone()
    bad[1, 2] = float("nan")
    for backend in splat.BACKENDS:
        with pytest.raises(ValueError, match="dirs has a non-finite value"):
            sh_to_rgb(bad, coeffs, backend=backend)
    with pytest.raises(ValueError, match="'backend'"):
        sh_to_rgb(dirs, coeffs, backend="tpu")
