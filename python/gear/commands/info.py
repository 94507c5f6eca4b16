"""`gear info`: the adapter, its optional features and limits, the rasterizer executor
GEAR_BACKEND selects (and why) and the CPU executor's threads; `--check` runs a kernel."""

from __future__ import annotations

import argparse
import os

from gear import __version__


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("info", help="show the GPU adapter, its features and limits, and the "
                                    "rasterizer executor in use")
    p.add_argument("--check", action="store_true", help="also run a GPU kernel self-check")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from gear import _core
    from gear.device import adapter_info, self_check
    from gear.splat import auto_backend, resolve_backend

    info = adapter_info()
    features = [k for k in ("float32_atomics", "subgroups", "timestamps") if info[k]]
    print(f"gear {__version__}")
    print(f"adapter   {info['name']} ({info['backend']}, {info['device_type']})")
    print(f"driver    {info['driver']}")
    print(f"features  {', '.join(features) or 'none of the optional ones'}")
    print(
        f"limits    max storage binding {info['max_storage_binding_bytes'] / 2**20:.0f} MiB, "
        f"max workgroups/dim {info['max_workgroups_per_dim']}, "
        f"storage buffers/stage {info['max_storage_buffers_per_stage']}"
    )
    executor, reason = auto_backend()
    chosen = resolve_backend()
    requested = os.environ.get("GEAR_BACKEND", "").strip() or "auto"
    why = reason if requested.lower() == "auto" else f"GEAR_BACKEND={requested}"
    print(f"raster    {chosen} executor ({why}); auto picks {executor}")
    print(f"threads   {_core.cpu_threads()} (CPU executor; GEAR_THREADS, default every core)")
    if args.check:
        gpu, ref = self_check()
        ok = abs(gpu - ref) <= 1e-4 * max(1.0, abs(ref)) + 1e-2
        print(f"kernel    GPU sum {gpu:.4f} vs float64 {ref:.4f}: {'ok' if ok else 'MISMATCH'}")
        return 0 if ok else 1
    return 0
