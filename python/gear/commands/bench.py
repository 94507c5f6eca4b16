"""`gear bench TARGET`: benchmarks; each target is a module `gear.bench.<target>`.

A target module defines `add_arguments(parser)` and `run(args) -> int`. Benchmarks report
ratios against a baseline measured in the same run (the machine is shared and noisy).
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil

import gear.bench


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="run a benchmark (accuracy-vs-time, kernels, geometry)")
    targets = p.add_subparsers(dest="target", required=True, metavar="TARGET")
    for module in sorted(pkgutil.iter_modules(gear.bench.__path__), key=lambda m: m.name):
        target = importlib.import_module(f"gear.bench.{module.name}")
        tp = targets.add_parser(module.name, help=(target.__doc__ or "").strip().split("\n")[0])
        target.add_arguments(tp)
        tp.set_defaults(handler=target.run)
