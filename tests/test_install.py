"""Install-facing behaviour: no driver noise without XDG_RUNTIME_DIR, and the package metadata
(a distribution name other than PyPI's unrelated "gear", torch as a range, Python 3.11-3.12)."""

import os
import stat
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _without_runtime_dir(tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "XDG_RUNTIME_DIR"}
    env["TMPDIR"] = str(tmp_path)  # the private runtime dir goes here, not in the shared /tmp
    return env


@pytest.mark.skipif(os.name != "posix", reason="Mesa's runtime-dir probe is a POSIX matter")
def test_gpu_commands_print_no_driver_noise_without_xdg_runtime_dir(tmp_path):
    out = subprocess.run([sys.executable, "-m", "gear", "info"], capture_output=True, text=True,
                         env=_without_runtime_dir(tmp_path), timeout=300)
    assert out.returncode == 0, out.stderr
    assert "XDG_RUNTIME_DIR" not in out.stderr + out.stdout
    assert "adapter" in out.stdout  # the GPU was touched
    runtime = tmp_path / f"gear-runtime-{os.getuid()}"
    assert stat.S_IMODE(runtime.stat().st_mode) == 0o700


@pytest.mark.skipif(os.name != "posix", reason="Mesa's runtime-dir probe is a POSIX matter")
def test_runtime_dir_someone_else_could_read_is_not_used(tmp_path):
    shared = tmp_path / f"gear-runtime-{os.getuid()}"
    shared.mkdir(mode=0o777)
    shared.chmod(0o777)
    code = "import os, gear; print(os.environ['XDG_RUNTIME_DIR'])"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env=_without_runtime_dir(tmp_path), timeout=300, check=True)
    used = Path(out.stdout.strip())
    assert used != shared and used.parent == tmp_path
    assert stat.S_IMODE(used.stat().st_mode) == 0o700
    # A set variable is left alone.
    env = {**os.environ, "XDG_RUNTIME_DIR": str(tmp_path)}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                         timeout=300, check=True)
    assert out.stdout.strip() == str(tmp_path)


def test_distribution_metadata():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert project["name"] != "gear"  # PyPI's "gear" is another package; import name stays
    torch = next(d for d in project["dependencies"] if d.startswith("torch"))
    assert "==" not in torch and ">=" in torch and "<" in torch  # a tested range, not a pin
    assert project["requires-python"] == ">=3.11,<3.13"
    assert "pycolmap" in " ".join(project["optional-dependencies"]["colmap"])
