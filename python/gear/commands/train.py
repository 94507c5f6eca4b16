"""`gear train SCENE_DIR --out OUT_DIR`: the whole method on one scene (docs/training.md)."""

from __future__ import annotations

import argparse
from pathlib import Path

from gear.config import PROFILES, SCHEDULES


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="reconstruct parts and joints of a two-state scene")
    p.add_argument("scene", type=Path,
                   help="scene folder: ArtGS/GEAR, nerfstudio or COLMAP (docs/scenes.md)")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--profile", choices=PROFILES, default=None,
                   help="schedule, with its measured cost at 128x128 on 2 CPU cores without a "
                        "GPU: quick (300+300 iterations, ~30 s; demo/CI), fast (10k+10k, "
                        "default, 18-28 min on a recent CPU, ~40 on an older one), "
                        "full (30k+30k, about 3x fast)")
    p.add_argument("--parts", type=int, default=None,
                   help="number of parts K including the static one (default: estimated)")
    p.add_argument("--config", type=Path, default=None,
                   help="JSON file of config fields overriding the profile")
    p.add_argument("--schedule", choices=SCHEDULES, default=None,
                   help="em (alternating, default), joint (no alternation), em-refine")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--resume", action="store_true",
                   help="continue the unfinished run in OUT (with the config saved there)")
    p.add_argument("--overwrite", action="store_true",
                   help="remove the run already in OUT before starting a new one")
    p.add_argument("--quiet", action="store_true", help="no progress bars; log.jsonl only")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from gear.cli import UserError
    from gear.config import load_config, load_overrides, make_config
    from gear.data import SceneError
    from gear.train import train

    overrides = load_overrides(args.config) if args.config else {}
    for field, value in (("num_parts", args.parts), ("schedule", args.schedule),
                         ("seed", args.seed)):
        if value is not None:
            overrides[field] = value
    saved = args.out / "config.json"
    if args.resume and args.profile is None and saved.is_file():
        # Resuming: the saved run's config, with only the options given here on top (train
        # refuses any that differ from the saved run).
        config = load_config(saved).replace(**overrides)
    else:
        config = make_config(args.profile or "fast", overrides)
    try:
        result = train(args.scene, args.out, config, resume=args.resume,
                       overwrite=args.overwrite, quiet=args.quiet)
    except SceneError as err:
        if len(err.problems) == 1:  # e.g. a path that is no scene: one line
            raise UserError(f"invalid scene: {err.problems[0]}") from err
        raise UserError("invalid scene:\n  " + "\n  ".join(err.problems)) from err
    print_result(result, args.scene, args.out)
    return 0


def _describe(joint: dict) -> str:
    axis = ", ".join(f"{a:+.3f}" for a in joint["axis"])
    origin = ", ".join(f"{o:+.3f}" for o in joint["origin"])
    amount = (f"{joint['angle_deg']:.1f} deg" if joint["type"] == "revolute"
              else f"{joint['distance']:.4f}")
    return f"{joint['type']:9s} axis ({axis}) origin ({origin}) {amount}"


def print_result(result, scene_dir: Path, out_dir: Path) -> None:  # noqa: ANN001 (TrainResult)
    """Recovered joints, next to the scene's ground truth and its errors when it has one."""
    from gear.data import load_scene
    from gear.evaluate import match_joints

    print(f"canonical state: {result.canonical}; outputs in {out_dir}")
    if not result.joints:
        print("no movable part found: the object is one static part")
    for joint in result.joints:
        print(f"  part {joint['part']}: {_describe(joint)}")
    scene = load_scene(scene_dir, splits=("train",))
    gt = scene.gt
    if gt is not None and gt.joints:
        print("ground truth (shown only for comparison; never used in training):")
        gt_dicts = [
            {"type": j.type, "axis": j.axis.tolist(), "origin": j.origin.tolist(),
             "angle_deg": j.amount if j.type == "revolute" else 0.0,
             "distance": j.amount if j.type == "prismatic" else 0.0}
            for j in gt.joints
        ]
        for i, joint in enumerate(gt_dicts):
            print(f"  joint {i}: {_describe(joint)}")
        matching = match_joints(out_dir, scene, result.joints)
        for (g, p), err in zip(matching.pairs, matching.errors, strict=True):
            mismatch = "" if err["type_match"] else "  (TYPE MISMATCH)"
            print(f"  gt {g} <-> part {p + 1}: axis ang {err['axis_ang']:.2f} deg, "
                  f"axis pos {err['axis_pos']:.3f}, geo dist {err['geo_dist']:.3f}{mismatch}")
        if matching.count_mismatch:
            print(f"  unmatched: gt {matching.unmatched_gt}, predicted {matching.unmatched_pred}")
    print("time: " + ", ".join(f"{k} {v:.1f}s" for k, v in result.timings.items()))
