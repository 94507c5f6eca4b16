"""gear: articulated digital twins from two articulation states with Gaussian splatting."""

import os
import tempfile
from pathlib import Path


def _private_runtime_dir() -> None:
    """Mesa's Vulkan driver probes Wayland, which prints "error: XDG_RUNTIME_DIR is invalid or
    not set in the environment." twice when the variable is unset (headless machines, CI, cron
    jobs). gear never opens a window: where it is unset, give this process (and its children) a
    private one, 0700 and owned by the user as the XDG spec asks, before the GPU is touched."""
    if os.environ.get("XDG_RUNTIME_DIR") or os.name != "posix":
        return
    path = Path(tempfile.gettempdir()) / f"gear-runtime-{os.getuid()}"
    try:
        path.mkdir(mode=0o700, exist_ok=True)
        info = path.stat()
        private = info.st_uid == os.getuid() and info.st_mode & 0o077 == 0
    except OSError:
        private = False
    # A same-named folder someone else made is never used: a fresh one instead.
    os.environ["XDG_RUNTIME_DIR"] = str(path) if private else tempfile.mkdtemp(prefix="gear-rt-")


_private_runtime_dir()

# torch's OpenMP workers busy-wait after each parallel op by default, on the cores the CPU
# rasterizer's threads then need: at 90k Gaussians / 128x128 that cost a call through
# gear.splat.rasterize and autograd ~15 ms of a loss's small ops plus ~15% of the executor's
# own time. Passive workers sleep instead. It only takes effect when gear is imported before
# torch (as `python -m gear` does); a value the user set is kept.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def _has_avx2() -> bool:
    """Whether this is an x86-64 Linux machine whose CPU reports AVX2."""
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as info:
            return any(line.startswith("flags") and " avx2" in line for line in info)
    except OSError:
        return False


# torch picks its CPU kernels by the CPU's widest vectors (AVX-512 where there is one, else
# AVX2), and the two round differently: the same seeded training then gives different models
# on two x86 machines, and at small budgets a different joint type (the real suite at quick:
# three of its fifteen objects changed between an AVX-512 and an AVX2 machine with the same
# code; with AVX2 kernels on both, the same results). AVX2 kernels wherever the CPU has them
# make a run give the same result on any such machine. Like the policy above it only takes
# effect when gear is imported before torch; a value the user set is kept.
if "ATEN_CPU_CAPABILITY" not in os.environ and _has_avx2():
    os.environ["ATEN_CPU_CAPABILITY"] = "avx2"

from gear._core import __version__  # noqa: E402 (after the runtime dir: it may touch the GPU)

__all__ = ["__version__"]
