"""Accuracy against training time: train scenes under several budgets and score every run.

Each (scene, budget[, ablation variant]) is trained with `gear.train.train`, scored with
`gear.evaluate` (docs/evaluation.md) and recorded with the wall time of every stage. Results go
to OUT/accuracy.csv, OUT/accuracy.md (a markdown table with the machine it ran on) and
OUT/accuracy.png (each metric against total training time, one line per scene).

Budgets: a profile name (quick, fast, full), an iteration count N, meaning the full profile's
schedule rescaled to N stage-1 + N stage-3 iterations the way `fast` rescales it to 10k + 10k,
or PROFILE:N, that profile's schedule rescaled the same way (e.g. quick:600). The default ladder,
quick, 1000, 3000 and fast (300 to 10k iterations per stage), spans what a user can afford on a
CPU. `--config` applies config fields on top of every budget (e.g. a Gaussian cap), labelling
the runs with them so that runs with and without share one table.
Scenes: built-in object names (generated once into the work folder with `gear synth` settings
given here) or paths to existing scene folders. `--suite real` runs the real-asset suite
instead (PartNet-Mobility objects under real-capture conditions, `gear.bench.accuracy.real`),
trained with automatic K, with a per-object table of the structure found.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from gear.bench.accuracy.records import (
    METRICS,
    VISIBLE_PX,
    Run,
    markdown_table,
    read_csv,
    suite_table,
    type_counts,
    write_csv,
    write_results,
)

if TYPE_CHECKING:  # the trainer is imported where it runs: `bench accuracy --help` stays light
    from gear.config import TrainConfig
    from gear.train import TrainResult

# The paper's EM intervals, studied on its 30k-iteration stage 3. A run with a shorter stage 3
# uses each at the same fraction of its schedule (scaled_em_interval), so a variant keeps the
# paper's number of E/M switches; unscaled, every interval from 500 on is a single E phase at
# the quick budget and the study would measure nothing.
EM_INTERVALS = (50, 250, 500, 2000, 3000)
FLAWED_MASKS = ("mask-over", "mask-under")
# Schedule fields placed at a fraction of the run; `fast` scales them by 1/3 with the iterations.
_SCALED_FIELDS = ("densify_until", "stage3_densify_until", "joint_classify_iteration",
                  "em_refine_joint_iterations")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenes", default="fridge,drawer_cabinet,storage7",
                        help="comma-separated built-in object names or scene folders")
    parser.add_argument("--profiles", "--profile", default=None,
                        help="comma-separated budgets: quick|fast|full, an iteration count N "
                        "(full rescaled) or PROFILE:N (default quick,1000,3000,fast; quick "
                        "with --suite)")
    parser.add_argument("--suite", choices=["real"], default=None,
                        help="real: the PartNet-Mobility objects rendered as a real capture "
                        "(+y up, other cameras per state, textures, highlights) instead of "
                        "--scenes")
    parser.add_argument("--objects", default="",
                        help="with --suite: comma-separated object names (default: all)")
    parser.add_argument("--assets", type=Path, default=None,
                        help="with --suite real: the PartNet-Mobility folder (default "
                        "$GEAR_PARTNET_ASSETS, else ../shared/assets/partnet-mobility next to "
                        "the repository)")
    parser.add_argument("--ablation", action="store_true",
                        help="instead of budgets: EM vs joint optimisation, EM interval "
                        f"{'/'.join(map(str, EM_INTERVALS))} (of a 30k-iteration stage 3, "
                        "scaled to the budget's), clean vs flawed masks, all at the first budget")
    parser.add_argument("--config", type=Path, default=None,
                        help="JSON file of config fields applied on top of every budget, e.g. "
                        '{"max_gaussians_per_pixel": 1.5}; the runs\' variant names them')
    parser.add_argument("--res", type=int, default=128, help="generated scenes' resolution")
    parser.add_argument("--views", type=int, default=None,
                        help="generated training views/state (default 48; 32 with --suite)")
    parser.add_argument("--test-views", type=int, default=8, help="generated test views/state")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=None,
                        help="folder for accuracy.csv/.md/.png (default ./bench, ./bench/real "
                        "with --suite real)")
    parser.add_argument("--append", action="store_true",
                        help="keep the runs already in OUT/accuracy.csv, skip those that "
                        "finished ok and resume those interrupted from their checkpoints "
                        "(extend or continue a long benchmark)")
    parser.add_argument("--work", type=Path, default=None,
                        help="folder for generated scenes and training outputs "
                        "(default OUT/accuracy_runs)")


def budget_config(budget: str, seed: int = 0) -> tuple[Any, int]:
    """(TrainConfig, iterations per stage) of a budget token: PROFILE, N or PROFILE:N."""
    from gear.config import PROFILES, make_config

    name, _, count = budget.partition(":") if ":" in budget else ("full", "", budget)
    if budget in PROFILES:
        config = make_config(budget, {"seed": seed})
        return config, config.stage1_iterations
    try:
        n = int(count)
    except ValueError:
        n = -1
    if name not in PROFILES or n < 0:
        raise ValueError(f"budget {budget!r}: expected one of {PROFILES}, an iteration count N "
                         "or PROFILE:N") from None
    if n < 10:
        raise ValueError(f"budget {budget!r}: at least 10 iterations")
    base = make_config(name)
    scale = n / base.stage1_iterations
    changes: dict[str, Any] = {"seed": seed, "stage1_iterations": n, "stage3_iterations": n}
    changes.update({f: max(1, round(getattr(base, f) * scale)) for f in _SCALED_FIELDS})
    # The densification warm-up is a fixed count of iterations (the fast profile keeps the full
    # one's), but a small budget's window would close before it ends and the run would never
    # densify: the warm-up takes at most the window's first third.
    changes["densify_from"] = min(base.densify_from, changes["densify_until"] // 3)
    return base.replace(**changes), n


def scaled_em_interval(paper_interval: int, config: Any) -> int:
    """The paper's EM interval at the same fraction of `config`'s stage 3 (at least 1)."""
    from gear.config import make_config

    paper_stage3 = make_config("full").stage3_iterations
    return max(1, round(paper_interval * config.stage3_iterations / paper_stage3))


def variants(ablation: bool) -> list[tuple[str, dict[str, Any], tuple[str, ...]]]:
    """(label, config overrides, scene effects) of each run per scene and budget."""
    if not ablation:
        return [("default", {}, ())]
    out: list[tuple[str, dict[str, Any], tuple[str, ...]]] = [
        ("em", {"schedule": "em"}, ()),
        ("joint", {"schedule": "joint"}, ()),
        ("em-refine", {"schedule": "em-refine"}, ()),
    ]
    out += [(f"em_interval={n}", {"em_interval": n}, ()) for n in EM_INTERVALS]
    out += [(f"masks:{effect}", {}, (effect,)) for effect in FLAWED_MASKS]
    return out


def _scene_dir(name: str, effects: tuple[str, ...], work: Path, args: argparse.Namespace) -> Path:
    """An existing scene folder, or the built-in object generated (once) into `work`."""
    if Path(name).is_dir():
        if effects:
            raise ValueError(f"{name}: flawed-mask variants need a built-in object name")
        return Path(name)
    from gear.synth import generate

    tag = "-".join((name, f"r{args.res}", f"v{args.views}", *effects))
    path = work / "scenes" / tag
    if not (path / "transforms_train_start.json").is_file():
        generate(name, path, res=args.res, views=args.views, test_views=args.test_views,
                 seed=args.seed, effects=effects)
    return path


def run_one(scene: str, scene_dir: Path, budget: str, variant: str, overrides: dict[str, Any],
            out_dir: Path, seed: int, fixed: dict[str, Any] | None = None,
            resume: bool = False) -> Run:
    """Train and score one configuration; failures are recorded, not raised. `fixed` fields
    (--config) apply to the budget as given, the variant's `overrides` after them. With
    `resume`, an interrupted run of the same configuration in `out_dir` continues from its
    checkpoint, and a finished one (a run trained before, or whose scoring was interrupted) is
    scored as it is (its CPU time unknown)."""
    from gear.evaluate import evaluate
    from gear.train import finished_run

    config, iterations = budget_config(budget, seed)
    config = config.replace(**(fixed or {})).replace(**overrides)
    if "em_interval" in overrides:
        config = config.replace(em_interval=scaled_em_interval(overrides["em_interval"], config))
    record = Run(scene, budget, variant, iterations)
    try:
        t0, cpu0 = time.perf_counter(), time.process_time()
        result = finished_run(scene_dir, Path(out_dir), config) if resume else None
        if result is None:
            result = train_or_resume(scene_dir, Path(out_dir), config, resume)
            record.cpu_seconds = time.process_time() - cpu0
        else:
            print("finished before, scored as it is: ", end="", flush=True)
        record.timings = dict(result.timings) or {"total": time.perf_counter() - t0}
        metrics = evaluate(out_dir, scene_dir)
        # Per-joint rows and skip reasons stay with the run, as `gear eval` leaves them.
        (Path(out_dir) / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
    except (RuntimeError, ValueError) as err:
        record.status = f"failed: {err}"
        return record
    record.metrics = {key: metrics.get(key) for key, _, _ in METRICS}
    record.type_mismatches = int(metrics.get("type_mismatches") or 0)
    record_structure(record, Path(out_dir), Path(scene_dir))
    return record


def train_or_resume(scene_dir: Path, out_dir: Path, config: TrainConfig,
                    resume: bool) -> TrainResult:
    """Trains `config` into `out_dir`, replacing an earlier run there; with `resume`, an
    interrupted run there (a checkpoint, no completion marker) continues instead, unless its
    checkpoint belongs to another scene or configuration (then it is replaced, and said)."""
    from gear.checkpoint import LAST
    from gear.run_folder import COMPLETE, RunFolderError
    from gear.train import train

    interrupted = (out_dir / "checkpoints" / LAST).is_file() and not (out_dir / COMPLETE).exists()
    if resume and interrupted:
        try:
            return train(scene_dir, out_dir, config, resume=True, quiet=True)
        except RunFolderError as err:
            print(f"not resumed ({err}); starting over: ", end="", flush=True)
    return train(scene_dir, out_dir, config, overwrite=True, quiet=True)


def record_structure(record: Run, out_dir: Path, scene_dir: Path) -> None:
    """Part count K (static included) and joint types, found (joints.json) and true
    (gt/trans.json), and how far each true part moves in the images, when those files exist."""
    from gear.bench.accuracy.visibility import part_motion_pixels
    from gear.data import load_scene

    gt = scene_dir / "gt" / "trans.json"
    if gt.is_file():
        types = [j["type"] for j in json.loads(gt.read_text())["trans_info"]]
        record.parts_true, record.types_true = 1 + len(types), type_counts(types)
        moved = part_motion_pixels(load_scene(scene_dir)) or []
        # (a trans_info entry the loader could not read leaves the two lists unpaired)
        record.part_motion_px = moved if len(moved) == len(types) else []
        if record.part_motion_px:
            record.types_visible = type_counts(
                [t for t, px in zip(types, record.part_motion_px, strict=True)
                 if px >= VISIBLE_PX])
    found = out_dir / "joints.json"
    if found.is_file():
        types = [j["type"] for j in json.loads(found.read_text())["joints"]]
        record.parts_found, record.types_found = 1 + len(types), type_counts(types)


def config_label(fixed: dict[str, Any]) -> str:
    """The variant name of --config fields: "field=value,..." ("" for none)."""
    return ",".join(f"{name}={value}" for name, value in sorted(fixed.items()))


def run_label(variant: str, fixed: dict[str, Any]) -> str:
    """A run's variant as recorded: the ablation variant and/or the --config fields."""
    label = config_label(fixed)
    if not label:
        return variant
    return label if variant == "default" else f"{variant};{label}"


def _resolve_defaults(args: argparse.Namespace) -> None:
    """Defaults that depend on --suite."""
    suite = args.suite is not None
    if args.profiles is None:
        args.profiles = "quick" if suite else "quick,1000,3000,fast"
    if args.views is None:
        args.views = 32 if suite else 48
    if args.out is None:
        args.out = Path("bench") / args.suite if suite else Path("bench")
    if args.objects and not suite:
        raise ValueError("--objects selects objects of a --suite; use --scenes otherwise")
    if suite and args.ablation:
        raise ValueError("--ablation runs on --scenes (built-in objects), not on a --suite")


def _suite_scenes(args: argparse.Namespace, work: Path) -> list[tuple[str, Any]]:
    """(name, callable(effects) giving the rendered scene folder) per suite object."""
    from gear.bench.accuracy import real

    assets = real.assets_dir(args.assets)
    if not assets.is_dir():
        raise ValueError(f"{assets}: PartNet-Mobility assets not found (give --assets or set "
                         f"${real.ASSETS_ENV})")
    chosen = real.select(real.real_scenes(assets, args.seed), args.objects)

    def renderer(scene: real.RealScene) -> Any:
        def render(effects: tuple[str, ...]) -> Path:  # the suite fixes its own effects
            path = work / "scenes" / f"{scene.name}-r{args.res}-v{args.views}"
            if not (path / "transforms_train_start.json").is_file():
                real.render_real(scene, assets, path, args.res, args.views, args.test_views,
                                 args.seed)
            return path
        return render

    return [(s.name, renderer(s)) for s in chosen]


def _named_scenes(args: argparse.Namespace, work: Path) -> list[tuple[str, Any]]:
    """(name, callable(effects) giving the scene folder) per --scenes entry."""

    def finder(scene: str) -> Any:
        return lambda effects: _scene_dir(scene, effects, work, args)

    return [(Path(s).name, finder(s)) for s in args.scenes.split(",") if s]


def run(args: argparse.Namespace) -> int:
    from gear.config import load_overrides

    _resolve_defaults(args)
    budgets = [b for b in args.profiles.split(",") if b]
    # Bad budget tokens and config files fail before any training starts.
    fixed = load_overrides(args.config) if args.config else {}
    for b in budgets:
        budget_config(b)[0].replace(**fixed)
    if args.ablation:
        budgets = budgets[:1]
    work = args.work or args.out / "accuracy_runs"
    suite = args.suite is not None
    scenes = _suite_scenes(args, work) if suite else _named_scenes(args, work)
    machine = machine_description()
    previous = args.out / "accuracy.csv"
    records = read_csv(previous) if args.append and previous.is_file() else []
    finished = {(r.scene, r.budget, r.variant) for r in records if r.status == "ok"}
    table = suite_table if suite else markdown_table
    records = [r for r in records if (r.scene, r.budget, r.variant) in finished]
    for name, scene_dir_of in scenes:
        for budget in budgets:
            for base_variant, overrides, effects in variants(args.ablation):
                variant = run_label(base_variant, fixed)
                print(f"[{name} / {budget} / {variant}] ", end="", flush=True)
                if (name, budget, variant) in finished:
                    print("already in the table", flush=True)
                    continue
                try:
                    scene_dir = scene_dir_of(effects)
                except ValueError as err:
                    record = Run(name, budget, variant, status=f"skipped: {err}")
                else:
                    out_dir = work / "outputs" / f"{name}-{budget}-{variant}"
                    record = run_one(name, scene_dir, budget, variant, overrides, out_dir,
                                     args.seed, fixed, resume=args.append)
                records.append(record)
                print(f"{record.status}, {record.total_seconds:.1f} s", flush=True)
                # Table and CSV after every run, so a long benchmark can be read as it goes.
                args.out.mkdir(parents=True, exist_ok=True)
                write_csv(records, args.out / "accuracy.csv")
                (args.out / "accuracy.md").write_text(table(records, machine))
    write_results(records, args.out, machine, suite=suite)
    print(table(records, machine))
    return 1 if any(r.status.startswith("failed") for r in records) else 0


# --- outputs ---------------------------------------------------------------------------------

def machine_description() -> str:
    """CPU, core count and GPU adapter, so a table says where its times come from."""
    cpu = platform.processor() or platform.machine()
    try:
        from gear.device import adapter_info

        info = adapter_info()
        adapter = f"{info['name']} ({info['backend']})"
    except (ImportError, RuntimeError) as err:
        adapter = f"unavailable ({err})"
    return f"{cpu}, {os.cpu_count()} cores, {platform.system()}; adapter {adapter}"
