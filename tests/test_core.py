"""The plumbing: adapter info, a GPU kernel against numpy, and argument checks at the FFI."""

import subprocess
import sys

import numpy as np
import pytest

from gear import _core
from gear.device import adapter_info, gpu_sum


def test_adapter_reports_name_and_limits():
    info = adapter_info()
    assert info["name"]
    assert info["backend"] in {"Vulkan", "Metal", "Dx12", "Gl"}
    assert info["max_storage_binding_bytes"] >= 2**27
    assert info["max_workgroups_per_dim"] >= 65535


@pytest.mark.parametrize("n", [1, 255, 2048, 2049, 1_234_567])
def test_gpu_sum_matches_numpy(n):
    values = np.random.default_rng(n).uniform(-1, 1, n).astype(np.float32)
    ref = values.astype(np.float64).sum()
    assert abs(gpu_sum(values) - ref) <= 1e-5 * np.abs(values).sum() + 1e-6


def test_wrong_dtype_names_argument():
    with pytest.raises(TypeError, match=r"'values'.*float32"):
        _core.sum_f32(np.ones(4, dtype=np.float64))


def test_wrong_shape_names_argument():
    with pytest.raises(ValueError, match=r"'values'.*shape \[N\]"):
        _core.sum_f32(np.ones((2, 2), dtype=np.float32))


def test_non_contiguous_is_rejected():
    with pytest.raises(ValueError, match="C-contiguous"):
        _core.sum_f32(np.ones(8, dtype=np.float32)[::2])


def test_not_an_array_is_a_type_error():
    with pytest.raises(TypeError, match="'values'"):
        _core.sum_f32([1.0, 2.0])


def test_info_command_runs_check():
    out = subprocess.run(
        [sys.executable, "-m", "gear", "info", "--check"], capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr
    assert "adapter" in out.stdout and ": ok" in out.stdout


def test_torch_thread_count_comes_from_the_environment(monkeypatch):
    import torch

    from gear.device import limit_torch_threads

    before = torch.get_num_threads()
    try:
        monkeypatch.setenv("GEAR_TORCH_THREADS", "2")
        assert limit_torch_threads() == 2 and torch.get_num_threads() == 2
        monkeypatch.delenv("GEAR_TORCH_THREADS")
        assert limit_torch_threads() == 1 and torch.get_num_threads() == 1
        for bad in ("0", "two", "-1"):
            monkeypatch.setenv("GEAR_TORCH_THREADS", bad)
            with pytest.raises(ValueError, match="GEAR_TORCH_THREADS"):
                limit_torch_threads()
    finally:
        torch.set_num_threads(before)
