"""`python -m gear <command>`: the single command-line entry point.

Each command lives in its own module under `gear.commands` and exposes
`register(subparsers)`, which adds its parser and sets `handler` (args -> exit code).
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
from collections.abc import Callable, Sequence

import gear.commands
from gear import __version__
from gear.device import limit_torch_threads

Handler = Callable[[argparse.Namespace], int]


class UserError(Exception):
    """A problem the user can fix (bad input, missing file): printed as one line, exit 1."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="gear", description="Articulated digital twins from two states."
    )
    parser.add_argument("--version", action="version", version=f"gear {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module in sorted(pkgutil.iter_modules(gear.commands.__path__), key=lambda m: m.name):
        importlib.import_module(f"gear.commands.{module.name}").register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    handler: Handler = args.handler
    try:
        limit_torch_threads()
        return handler(args)
    except KeyboardInterrupt:
        print("gear: interrupted", file=sys.stderr)
        return 130
    except (UserError, RuntimeError, ValueError, FileNotFoundError) as err:
        # Expected failures (bad input, GPU unavailable): one line, no traceback.
        print(f"gear: error: {err}", file=sys.stderr)
        return 1
