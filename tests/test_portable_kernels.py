"""`import gear` asks torch for its AVX2 CPU kernels on a machine that has them (the same
rounding on any x86-64 machine, so a seeded run gives the same result), unless the user chose."""

import os
import subprocess
import sys

import pytest

from gear import _has_avx2

SHOW = "import gear, os, torch; print(os.environ.get('ATEN_CPU_CAPABILITY')); " \
       "print(torch.backends.cpu.get_cpu_capability())"


def run(env_value: str | None) -> list[str]:
    env = {k: v for k, v in os.environ.items() if k != "ATEN_CPU_CAPABILITY"}
    if env_value is not None:
        env["ATEN_CPU_CAPABILITY"] = env_value
    out = subprocess.run([sys.executable, "-c", SHOW], env=env, capture_output=True, text=True,
                         check=True)
    return out.stdout.split()


@pytest.mark.skipif(not _has_avx2(), reason="the CPU has no AVX2 (or this is not Linux)")
def test_gear_asks_torch_for_avx2_kernels():
    assert run(None) == ["avx2", "AVX2"]


def test_a_capability_the_user_set_is_kept():
    assert run("default") == ["default", "DEFAULT"]
