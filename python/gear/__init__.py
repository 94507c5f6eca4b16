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

from gear._core import __version__  # noqa: E402 (after the runtime dir: it may touch the GPU)

__all__ = ["__version__"]
