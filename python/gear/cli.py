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
from typing import NoReturn

import gear.commands
from gear import __version__
from gear.device import limit_torch_threads

Handler = Callable[[argparse.Namespace], int]


class UserError(Exception):
    """A problem the user can fix (bad input, missing file): printed as one line, exit 1."""


class Parser(argparse.ArgumentParser):
    """argparse, but a bad command line is one line on stderr (exit 2), not the usage block:
    the same shape as every other gear error. Subcommand parsers inherit the class."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
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
    except (UserError, RuntimeError, ValueError, OSError) as err:
        # Expected failures (bad input, a path that is not what it should be, an unwritable
        # folder, GPU unavailable): one line, no traceback.
        print(f"gear: error: {_message(err)}", file=sys.stderr)
        return 1


def _message(err: Exception) -> str:
    """The error's text; an OSError's as "path: what", without Python's "[Errno N]"."""
    if isinstance(err, OSError) and err.filename is not None and err.strerror:
        return f"{err.filename}: {err.strerror}"
    return str(err)
