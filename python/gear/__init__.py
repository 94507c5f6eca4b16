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

from gear._core import __version__  # noqa: E402 (after the runtime dir: it may touch the GPU)

__all__ = ["__version__"]
