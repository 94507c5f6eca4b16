"""`gear eval OUT_DIR SCENE_DIR`: score a training output against the scene's ground truth
(gear.evaluate), print the metrics as a table and write OUT_DIR/metrics.json
(docs/evaluation.md)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from gear.evaluate import BACKGROUNDS, evaluate, format_table


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("eval", help="score a training output against a scene's ground truth")
    p.add_argument("out_dir", type=Path, help="the output folder of `gear train`")
    p.add_argument("scene_dir", type=Path, help="the scene it was trained on (with gt/)")
    p.add_argument("--samples", type=int, default=10000,
                   help="surface samples per mesh for Chamfer distance (default 10000)")
    p.add_argument("--seed", type=int, default=0, help="surface sampling seed")
    p.add_argument("--background", choices=sorted(BACKGROUNDS), default="black",
                   help="colour the test renders were composited over (default black)")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from gear.cli import UserError
    from gear.run_folder import require_finished

    if args.samples < 1:
        raise UserError(f"--samples must be at least 1, got {args.samples}")
    require_finished(args.out_dir)
    try:
        metrics = evaluate(args.out_dir, args.scene_dir, samples=args.samples, seed=args.seed,
                           background=args.background)
    except FileNotFoundError as err:
        raise UserError(str(err)) from err
    path = Path(args.out_dir) / "metrics.json"
    path.write_text(json.dumps(metrics, indent=2) + "\n")
    print(format_table(metrics))
    print(f"written {path}")
    return 0
