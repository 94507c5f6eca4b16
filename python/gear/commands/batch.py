"""`gear batch SCENES --out RUNS`: the whole pipeline (train, export, eval when the scene has
ground truth) on many scenes, one Ray task each, on this machine or a Ray cluster
(docs/batch.md)."""

from __future__ import annotations

import argparse
from pathlib import Path

from gear.commands.export import add_model_options
from gear.config import PROFILES

DEFAULT_MEMORY_GB = 4.0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("batch", help="train, export and evaluate many scenes on Ray (this "
                                     "machine or a cluster)")
    p.add_argument("scenes", type=Path,
                   help="a folder of scene folders, or a text file listing scene folders")
    p.add_argument("--out", type=Path, required=True,
                   help="folder of the runs: RUNS/<scene>/, summary.csv, summary.md")
    p.add_argument("--profile", choices=PROFILES, default="fast",
                   help="training schedule of every run (default fast; see gear train)")
    p.add_argument("--config", type=Path, default=None,
                   help="JSON file of config fields overriding the profile")
    p.add_argument("--address", default=None,
                   help="Ray cluster to run on: 'auto', HOST:PORT of `ray start --head`, or "
                        "ray://HOST:10001 (default: a Ray started on this machine)")
    p.add_argument("--cpus-per-run", type=int, default=1,
                   help="CPUs each run reserves and uses (its thread count; default 1)")
    p.add_argument("--memory-per-run", type=float, default=DEFAULT_MEMORY_GB, metavar="GB",
                   help=f"memory each run reserves (default {DEFAULT_MEMORY_GB:g} GB)")
    p.add_argument("--retries", type=int, default=1,
                   help="times a crashed run (or one whose worker died) is retried, continuing "
                        "from its last checkpoint (default 1)")
    p.add_argument("--resume", action="store_true",
                   help="continue an earlier batch in RUNS: finished scenes are skipped, "
                        "interrupted ones continue")
    add_model_options(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar; a line per scene")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from gear.batch.outcome import DONE
    from gear.batch.plan import plan_batch
    from gear.batch.progress import BatchProgress
    from gear.batch.scheduler import INSTALL_HINT, ray_available, run_scenes
    from gear.batch.summary import metric_means, write_summary
    from gear.cli import UserError
    from gear.commands.export import model_options
    from gear.config import load_overrides, make_config
    from gear.evaluate import SUMMARY

    if not ray_available():
        raise UserError(INSTALL_HINT)
    for name, value, least in (("--cpus-per-run", args.cpus_per_run, 1),
                               ("--retries", args.retries, 0)):
        if value < least:
            raise UserError(f"{name} must be at least {least}, got {value}")
    if not args.memory_per_run > 0:
        raise UserError(f"--memory-per-run must be positive, got {args.memory_per_run:g}")
    options = model_options(args)
    options.check()
    overrides = load_overrides(args.config) if args.config else {}
    config = make_config(args.profile, overrides)
    plan = plan_batch(args.scenes, args.out, resume=args.resume)
    print(plan.describe(args.cpus_per_run), flush=True)

    outcomes = {o.scene: o for o in plan.settled}

    def settled(outcome) -> None:  # noqa: ANN001 (Outcome)
        outcome.save(args.out / outcome.scene)
        outcomes[outcome.scene] = outcome

    progress = BatchProgress(len(plan.todo), quiet=args.quiet or not plan.todo)
    try:
        if plan.todo:
            run_scenes(plan.todo, args.out, config.to_json(), options, address=args.address,
                       cpus=args.cpus_per_run, memory_gb=args.memory_per_run,
                       retries=args.retries, progress=progress, settled=settled)
    finally:  # also after Ctrl-C or a lost cluster: the scenes settled so far
        progress.close()
        write_summary(args.out, list(outcomes.values()))
    done = sum(o.status == DONE for o in outcomes.values())
    means = metric_means(list(outcomes.values()))
    shown = ", ".join(f"{label} {means[key]:.4g}" for key, label in SUMMARY
                      if means[key] is not None)
    print(f"{done} of {len(outcomes)} scene(s) done" + (f"; means: {shown}" if shown else ""))
    print(f"summary: {args.out / 'summary.md'} and {args.out / 'summary.csv'}")
    return 0 if done == len(outcomes) else 1
