"""The fused deformation (Rust) against the torch reference gear.kinematics.deform: values and
gradients in float64 and float32, torch.autograd.gradcheck in float64, held motions, hard
cases and bad input."""

from __future__ import annotations

import pytest
import torch

from gear.fused_deform import fused_deform
from gear.kinematics import deform, dq_from_rt


def _scene(n: int, k: int, dtype: torch.dtype, seed: int = 0) -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    quat = torch.randn(k, 4, generator=g, dtype=torch.float64)
    qr, qd = dq_from_rt(quat, 0.3 * torch.randn(k, 3, generator=g, dtype=torch.float64))
    # Every other motion with the opposite sign: the same motion, which the blend must align.
    flip = torch.tensor([(-1.0) ** p for p in range(k)], dtype=torch.float64)[:, None]
    qr, qd = qr * flip, qd * flip
    means = torch.randn(n, 3, generator=g, dtype=torch.float64)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    weights = torch.softmax(2 * torch.randn(n, k, generator=g, dtype=torch.float64), dim=1)
    return [t.to(dtype).requires_grad_() for t in (means, quats, weights, qr, qd)]


def _both(inputs: list[torch.Tensor], op) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """Outputs and input gradients of sum(out * fixed probes) through `op`."""
    outs = op(*inputs)
    g = torch.Generator().manual_seed(7)
    probes = [torch.randn(o.shape, generator=g, dtype=torch.float64).to(o.dtype) for o in outs]
    loss = sum((o * p).sum() for o, p in zip(outs, probes, strict=True))
    # An input the loss does not depend on (quats, when only the means are used) gets zeros.
    grads = torch.autograd.grad(loss, inputs, allow_unused=True, materialize_grads=True)
    return [o.detach() for o in outs], list(grads)


@pytest.mark.parametrize("k", [1, 2, 5])
def test_matches_reference_float64(k: int) -> None:
    inputs = _scene(200, k, torch.float64, seed=k)
    outs, grads = _both(inputs, fused_deform)
    ref_outs, ref_grads = _both(inputs, deform)
    for a, b in zip(outs + grads, ref_outs + ref_grads, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


def test_matches_reference_float32() -> None:
    # Tolerances: float32 rounding of a few dozen operations per Gaussian.
    inputs = _scene(5000, 4, torch.float32, seed=3)
    outs, grads = _both(inputs, fused_deform)
    ref_outs, ref_grads = _both([t.detach().double().requires_grad_() for t in inputs], deform)
    for a, b in zip(outs, ref_outs, strict=True):
        torch.testing.assert_close(a.double(), b, rtol=0, atol=3e-6)
    for a, b in zip(grads, ref_grads, strict=True):
        err = torch.linalg.norm(a.double() - b) / torch.linalg.norm(b)
        assert err < 1e-5, f"relative L2 error {err:.2e}"


def test_gradcheck_float64() -> None:
    inputs = _scene(6, 3, torch.float64, seed=11)
    assert torch.autograd.gradcheck(fused_deform, inputs, eps=1e-6, atol=1e-8)


def test_held_motions_get_no_gradient() -> None:
    means, quats, weights, qr, qd = _scene(50, 3, torch.float32, seed=5)
    qr, qd = qr.detach(), qd.detach()
    m, q = fused_deform(means, quats, weights, qr, qd)
    (m.sum() + q.sum()).backward()
    assert qr.grad is None and qd.grad is None
    assert all(t.grad is not None and torch.isfinite(t.grad).all() for t in (means, quats, weights))


def test_one_output_used() -> None:
    inputs = _scene(30, 2, torch.float64, seed=2)
    only_means = lambda *xs: (fused_deform(*xs)[0],)  # noqa: E731
    reference = lambda *xs: (deform(*xs)[0],)  # noqa: E731
    _, grads = _both(inputs, only_means)
    _, ref_grads = _both(inputs, reference)
    for a, b in zip(grads, ref_grads, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


def test_hard_cases_stay_finite() -> None:
    # Zero weights (the blend vanishes: identity), ±50 weights, half turns (w = 0) of both
    # signs, a zero Gaussian rotation, and no Gaussians at all.
    half = torch.tensor([[0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0, -1.0]])
    weights = torch.tensor([[0.0, 0.0], [50.0, -50.0], [0.5, 0.5]], requires_grad=True)
    means = torch.randn(3, 3, requires_grad=True)
    quats = torch.zeros(3, 4, requires_grad=True)
    qr, qd = half.clone().requires_grad_(), torch.full((2, 4), 0.1, requires_grad=True)
    m, q = fused_deform(means, quats, weights, qr, qd)
    (m.sum() + q.sum()).backward()
    for t in (m, q, means.grad, quats.grad, weights.grad, qr.grad, qd.grad):
        assert torch.isfinite(t).all()
    torch.testing.assert_close(m[0], means[0].detach())
    empty = [torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 2), half, half]
    m, q = fused_deform(*empty)
    assert m.shape == (0, 3) and q.shape == (0, 4)


def test_bad_input_is_one_clear_error() -> None:
    means, quats, weights, qr, qd = (t.detach() for t in _scene(4, 2, torch.float32))
    with pytest.raises(TypeError, match="all be float32 or all float64"):
        fused_deform(means.double(), quats, weights, qr, qd)
    with pytest.raises(ValueError, match="argument 'weights': expected shape"):
        fused_deform(means, quats, weights[:, :1], qr, qd)
    means[1, 2] = float("nan")
    with pytest.raises(ValueError, match="deform means has a non-finite value at flat index 5"):
        fused_deform(means, quats, weights, qr, qd)


@pytest.mark.parametrize("k", [1, 2, 4])
def test_logits_match_the_reference_through_softmax(k: int) -> None:
    inputs = _scene(150, k, torch.float64, seed=20 + k)
    logits = (3 * torch.randn(150, k, dtype=torch.float64)).requires_grad_()
    fused = [*inputs[:2], logits, *inputs[3:]]

    def reference(means, quats, lg, qr, qd):
        return deform(means, quats, torch.softmax(lg, dim=1), qr, qd)

    want_out, want_grads = _both(fused, reference)
    got_out, got_grads = _both(fused, lambda *a: fused_deform(*a, softmax=True))
    for got, want in zip(got_out + got_grads, want_out + want_grads, strict=True):
        assert torch.allclose(got, want, rtol=0, atol=1e-10)
    small = [t.detach()[:6].clone().requires_grad_() for t in fused[:3]]
    motions = [t.detach().clone().requires_grad_() for t in fused[3:]]
    assert torch.autograd.gradcheck(
        lambda *a: fused_deform(*a, softmax=True), (*small, *motions))
