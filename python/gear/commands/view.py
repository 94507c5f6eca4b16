"""`gear view OUT_DIR`: the trained twin in the browser, with a slider per joint.

Serves a viser page (see docs/viewing.md) showing the Gaussians as splats, the part meshes and
joint axes, until Ctrl-C.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from gear.commands.render import UP_CHOICES, up_vector


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("view", help="show the trained twin in the browser, a slider per joint")
    p.add_argument("out_dir", type=Path, help="a trained run's output folder")
    p.add_argument("--port", type=int, default=8080, help="port to serve on (default 8080)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default 127.0.0.1, this machine only; "
                        "0.0.0.0 serves other machines too)")
    p.add_argument("--up", default="z", choices=UP_CHOICES,
                   help="world axis pointing up in the view (default z)")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from gear.cli import UserError
    from gear.run_folder import require_finished
    from gear.twin import Twin
    from gear.view.server import TwinViewer, port_is_free

    if not 1 <= args.port <= 65535:
        raise UserError(f"--port must be in 1..65535, got {args.port}")
    twin = Twin.load(require_finished(args.out_dir))
    if not port_is_free(args.host, args.port):
        raise UserError(f"port {args.port} on {args.host} is busy (another server?): "
                        "pass a free one with --port")
    viewer = TwinViewer(twin, args.out_dir, host=args.host, port=args.port,
                        up=up_vector(args.up))
    try:  # from here on Ctrl-C stops the server cleanly, even during the print
        print(f"gear view: {args.out_dir} ({len(twin.means)} Gaussians, {len(twin.joints)} "
              f"joint(s)) at {viewer.url}  (Ctrl-C stops)", flush=True)
        while True:
            time.sleep(0.5)
    except KeyboardInterrupt:
        pass
    finally:
        viewer.stop()
    print("gear view: stopped", flush=True)
    return 0
