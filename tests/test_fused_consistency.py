"""The fused KNN consistency term against the torch reference (gear.losses)."""

from __future__ import annotations

import pytest
import torch

from gear.fused_consistency import fused_knn_consistency
from gear.losses import knn_consistency_loss


def _scene(n: int, k: int, per_point: int, dtype: torch.dtype, seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    logits = (4 * torch.rand(n, k, generator=gen, dtype=dtype) - 2).requires_grad_()
    neighbours = torch.randint(0, n, (n, per_point), generator=gen)
    neighbours[torch.rand(n, per_point, generator=gen) < 0.1] = -1  # padding
    return logits, neighbours


def _value_and_grad(fn, logits, neighbours):
    x = logits.detach().clone().requires_grad_()
    loss = fn(x, neighbours)
    loss.backward()
    return loss.detach(), x.grad


@pytest.mark.parametrize("k", [1, 2, 5])
def test_matches_the_reference_in_float64(k: int) -> None:
    logits, neighbours = _scene(300, k, 4, torch.float64)
    want, want_grad = _value_and_grad(knn_consistency_loss, logits, neighbours)
    got, got_grad = _value_and_grad(fused_knn_consistency, logits, neighbours)
    assert got.dtype == torch.float64
    assert abs(got.item() - want.item()) <= 1e-12 * want.item()
    assert torch.allclose(got_grad, want_grad, rtol=0, atol=1e-14)


def test_float32_agrees_with_the_reference() -> None:
    logits, neighbours = _scene(20_000, 2, 3, torch.float32, seed=1)
    want, want_grad = _value_and_grad(knn_consistency_loss, logits.double(), neighbours)
    got, got_grad = _value_and_grad(fused_knn_consistency, logits, neighbours)
    assert got.dtype == torch.float32
    assert abs(got.item() - want.item()) <= 1e-6 * want.item()
    rel = (got_grad.double() - want_grad).norm() / want_grad.norm()
    assert rel < 1e-5


def test_gradcheck() -> None:
    logits, neighbours = _scene(30, 3, 3, torch.float64, seed=2)
    assert torch.autograd.gradcheck(lambda x: fused_knn_consistency(x, neighbours), (logits,))


def test_scaled_by_the_upstream_gradient_and_hand_value() -> None:
    logits = torch.tensor([[0.0, 0.0], [3.0, 4.0], [0.0, 0.0]], requires_grad=True)
    neighbours = torch.tensor([[1, 2], [0, -1], [0, 1]])
    loss = fused_knn_consistency(logits, neighbours)
    assert loss.item() == pytest.approx(3.0)
    (0.5 * loss).backward()
    ref = logits.detach().clone().requires_grad_()
    (0.5 * knn_consistency_loss(ref, neighbours)).backward()
    assert torch.allclose(logits.grad, ref.grad, atol=1e-7)


def test_degenerate_inputs_are_finite_zeros() -> None:
    same = torch.ones(4, 3, requires_grad=True)
    loss = fused_knn_consistency(same, torch.tensor([[1], [2], [3], [0]]))
    loss.backward()
    assert loss.item() == 0 and (same.grad == 0).all()
    padded = torch.zeros(2, 1, requires_grad=True)
    assert fused_knn_consistency(padded, torch.full((2, 2), -1)).item() == 0
    empty = torch.zeros(0, 2, requires_grad=True)
    fused_knn_consistency(empty, torch.zeros(0, 3, dtype=torch.int64)).backward()
    assert empty.grad.shape == (0, 2)


def test_bad_inputs_are_one_line_errors() -> None:
    logits = torch.zeros(3, 2)
    with pytest.raises(ValueError, match="index 3 >= N = 3"):
        fused_knn_consistency(logits, torch.tensor([[3], [0], [1]]))
    with pytest.raises(ValueError, match="non-finite"):
        fused_knn_consistency(torch.tensor([[float("nan")], [0.0]]), torch.tensor([[1], [0]]))
    with pytest.raises(ValueError, match=r"\[N, n\]"):
        fused_knn_consistency(logits, torch.tensor([[1], [0]]))
    with pytest.raises(TypeError, match="integer"):
        fused_knn_consistency(logits, torch.zeros(3, 1))
    with pytest.raises(TypeError, match="float32 or float64"):
        fused_knn_consistency(logits.half(), torch.zeros(3, 1, dtype=torch.int64))
