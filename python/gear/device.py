"""The GPU adapter gear runs on, and a kernel self-check."""

from __future__ import annotations

import numpy as np

from gear import _core


def adapter_info() -> dict:
    """Name, backend, type, optional features and limits of the adapter in use."""
    return dict(_core.adapter_info())


def gpu_sum(values: np.ndarray) -> float:
    """Sum of a 1-D array on the GPU (float32)."""
    return float(_core.sum_f32(np.ascontiguousarray(values, dtype=np.float32).ravel()))


def self_check(n: int = 1_000_003, seed: int = 0) -> tuple[float, float]:
    """Runs the GPU reduction on random data; returns (gpu, float64 reference)."""
    values = np.random.default_rng(seed).standard_normal(n).astype(np.float32)
    return gpu_sum(values), float(values.astype(np.float64).sum())
