"""`gear check SCENE_DIR`: validate a scene; list every problem (exit 1) or explain what was
found (exit 0): layout, views, intrinsics, which views have depth and masks, and warnings where
training would use an input only in part."""

from __future__ import annotations

import argparse
from pathlib import Path

from gear.data.scene import STATES, Scene, View

SHOWN_CAMERAS = 3  # distinct intrinsics listed before "..."


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "check", help="validate a scene folder (ArtGS/GEAR, nerfstudio or COLMAP layout)"
    )
    p.add_argument("scene", help="scene directory")
    p.set_defaults(handler=run)


def _intrinsics(views: list[View]) -> str:
    cams = sorted({
        (v.camera.width, v.camera.height, round(v.camera.fx, 3), round(v.camera.fy, 3),
         round(v.camera.cx, 3), round(v.camera.cy, 3))
        for v in views
    })
    shown = "; ".join(f"{w}x{h} fx {fx:g} fy {fy:g} cx {cx:g} cy {cy:g}"
                      for w, h, fx, fy, cx, cy in cams[:SHOWN_CAMERAS])
    more = " ..." if len(cams) > SHOWN_CAMERAS else ""
    return f"{len(cams)} distinct ({shown}{more})" if len(cams) > 1 else shown


def _coverage(scene: Scene, kind: str) -> str:
    from gear.data.coverage import count

    per_state = [(s, count(scene.views.get(s, {}).get(sp, []), kind),
                  len(scene.views.get(s, {}).get(sp, [])), sp)
                 for s in STATES for sp in scene.views.get(s, {})]
    if all(n == 0 for _, n, _, _ in per_state):
        return "none"
    if all(n == total for _, n, total, _ in per_state):
        return "every view"
    return ", ".join(f"{s} {sp} {n}/{total}" for s, n, total, sp in per_state if total)


def _depth_on_object(scene: Scene) -> str:
    from gear.data.coverage import depth_on_object

    fraction = depth_on_object(scene.all_views())
    return "" if fraction is None else f" ({100 * fraction:.0f}% of object pixels)"


def summary(scene: Scene) -> str:
    """What the scene holds, one aspect per line (the first line says it is ok)."""
    counts = ", ".join(
        f"{state} {' + '.join(f'{len(vs)} {split}' for split, vs in splits.items())}"
        for state, splits in scene.views.items()
    )
    lines = [
        f"{scene.root}: ok, {len(scene.all_views())} views",
        f"  layout:        {scene.layout}",
        f"  views:         {counts}",
        f"  intrinsics:    {_intrinsics(scene.all_views())}",
        "  object masks:  every view",
        f"  depth:         {_coverage(scene, 'depth')}{_depth_on_object(scene)}",
        f"  region masks:  {_coverage(scene, 'regions')}",
        f"  GT part ids:   {_coverage(scene, 'parts')}",
    ]
    if scene.gt is not None:
        n_meshes = sum(len(m) for m in scene.gt.meshes.values())
        lines.append(f"  ground truth:  {len(scene.gt.joints)} joint(s), {n_meshes} mesh(es)")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from gear.cli import UserError
    from gear.data.coverage import input_warnings
    from gear.data.load import load_and_validate

    # A path that is no folder at all is a mistyped argument, not a scene with problems.
    if not Path(args.scene).exists():
        raise UserError(f"{args.scene}: no such scene folder")
    if not Path(args.scene).is_dir():
        raise UserError(f"{args.scene}: is a file, not a scene folder")
    scene, problems = load_and_validate(args.scene)
    for problem in problems:
        print(problem)
    if problems:
        print(f"{len(problems)} problem(s) found")
        return 1
    print(summary(scene))
    for warning in input_warnings(scene):
        print(f"warning: {warning}")
    return 0
