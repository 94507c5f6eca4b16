"""The fused SSIM (Rust) against the torch form gear.losses.ssim_reference."""

from __future__ import annotations

import pytest
import torch

from gear.fused_ssim import fused_ssim
from gear.losses import photometric, ssim, ssim_reference


def _images(h: int, w: int, c: int, dtype: torch.dtype, seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    a = torch.rand(h, w, c, generator=gen, dtype=dtype)
    b = (0.7 * a + 0.3 * torch.rand(h, w, c, generator=gen, dtype=dtype)).clamp(0, 1)
    return a.requires_grad_(), b


def _value_and_grad(fn, a, b):
    x = a.detach().clone().requires_grad_()
    value = fn(x, b)
    value.backward()
    return value.detach(), x.grad


@pytest.mark.parametrize("shape", [(16, 16, 3), (23, 9, 1), (5, 40, 4)])
def test_matches_the_reference_in_float64(shape: tuple[int, int, int]) -> None:
    a, b = _images(*shape, torch.float64)
    want, want_grad = _value_and_grad(ssim_reference, a, b)
    got, got_grad = _value_and_grad(fused_ssim, a, b)
    assert got.dtype == torch.float64
    assert abs(got.item() - want.item()) < 1e-13
    assert torch.allclose(got_grad, want_grad, rtol=0, atol=1e-13)


def test_float32_agrees_with_the_reference() -> None:
    a, b = _images(128, 96, 3, torch.float32, seed=1)
    want, want_grad = _value_and_grad(ssim_reference, a.double(), b.double())
    got, got_grad = _value_and_grad(fused_ssim, a, b)
    assert abs(got.item() - want.item()) < 1e-6
    assert (got_grad.double() - want_grad).norm() / want_grad.norm() < 1e-4


def test_gradcheck() -> None:
    a, b = _images(13, 11, 2, torch.float64, seed=2)
    assert torch.autograd.gradcheck(lambda x: fused_ssim(x, b), (a,))


def test_the_loss_uses_the_fused_op_and_falls_back_for_a_trained_target() -> None:
    a, b = _images(20, 20, 3, torch.float32, seed=3)
    # Through photometric (the training loss), scaled by upstream factors.
    x = a.detach().clone().requires_grad_()
    photometric(x, b, 0.2).backward()
    y = a.detach().clone().requires_grad_()
    l1 = (y - b).abs().mean()
    (0.8 * l1 + 0.2 * (1 - ssim_reference(y, b))).backward()
    assert torch.allclose(x.grad, y.grad, atol=1e-7)
    # A second image that trains gets its gradient from the torch form.
    target = b.detach().clone().requires_grad_()
    ssim(a, target).backward()
    assert target.grad is not None and target.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="second image"):
        fused_ssim(a, target)
    with torch.no_grad():
        assert ssim(a, a).item() == pytest.approx(1.0, abs=1e-6)


def test_hard_cases_and_errors() -> None:
    zeros = torch.zeros(12, 12, 3, requires_grad=True)
    value = fused_ssim(zeros, torch.ones(12, 12, 3))
    value.backward()
    assert torch.isfinite(value) and torch.isfinite(zeros.grad).all()
    with pytest.raises(ValueError, match="non-finite"):
        fused_ssim(torch.full((4, 4, 1), float("nan")), torch.zeros(4, 4, 1))
    with pytest.raises(ValueError, match="shape"):
        fused_ssim(torch.zeros(4, 4, 1), torch.zeros(4, 5, 1))
    with pytest.raises(TypeError, match="float32"):
        fused_ssim(torch.zeros(4, 4, 1), torch.zeros(4, 4, 1, dtype=torch.float64))


def test_a_non_finite_image_gives_a_nan_loss_not_an_error() -> None:
    """Training checks each loss term and names the one that went non-finite: the loss must
    carry the NaN there rather than the native op raising first."""
    bad = torch.zeros(8, 8, 3)
    bad[2, 3, 1] = float("nan")
    assert torch.isnan(ssim(bad.requires_grad_(), torch.zeros(8, 8, 3)))
    assert torch.isnan(photometric(torch.zeros(8, 8, 3), bad.detach(), 0.2))
