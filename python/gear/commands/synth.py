"""`gear synth`: render a built-in procedural object or a URDF asset into a scene with GT."""

from __future__ import annotations

import argparse

from gear.cli import UserError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "synth",
        help="generate a two-state scene of an articulated object (built-in or URDF)",
        description="Render an articulated object in two states into a scene directory "
        "(docs/scenes.md layout) with depth, region masks, GT part ids, trans.json and GT meshes.",
    )
    p.add_argument("object", nargs="?", help="built-in object name (see --list)")
    p.add_argument("--list", action="store_true", help="list the built-in objects and effects")
    p.add_argument("--urdf", metavar="FILE", help="render this URDF (e.g. a mobility.urdf)")
    p.add_argument(
        "--start", nargs="+", default=[], metavar="J=V", help="URDF joint values of the start state"
    )
    p.add_argument(
        "--end", nargs="+", default=[], metavar="J=V", help="URDF joint values of the end state"
    )
    p.add_argument("--out", metavar="DIR", help="output scene directory")
    p.add_argument("--res", type=int, default=256, help="image width and height (default 256)")
    p.add_argument("--views", type=int, default=64, help="training views per state (default 64)")
    p.add_argument("--test-views", type=int, default=16, help="test views per state (default 16)")
    p.add_argument("--seed", type=int, default=0, help="cameras, colours and effects seed")
    p.add_argument("--effects", default="", help="comma-separated effects (see --list)")
    p.add_argument("--up", default=None, help="world up axis: +x/-x/+y/-y/+z/-z or x,y,z "
                   "(default +z; the whole world is rotated, the images stay the same)")
    p.set_defaults(handler=run)


def _joint_values(items: list[str], flag: str) -> dict[str, float]:
    values = {}
    for item in items:
        name, sep, value = item.partition("=")
        try:
            values[name] = float(value)
        except ValueError:
            raise UserError(f"{flag} expects J=V with a number V, got {item!r}") from None
        if not sep or not name:
            raise UserError(f"{flag} expects J=V, got {item!r}")
    return values


def run(args: argparse.Namespace) -> int:
    from gear.synth import EFFECTS, describe, parse_effects, render_scene
    from gear.synth.objects import build

    if args.list:
        print("objects:")
        for name, text in describe():
            print(f"  {name:15s} {text}")
        print("effects (--effects a,b,...):")
        for name, text in EFFECTS.items():
            print(f"  {name:15s} {text}")
        return 0
    if (args.object is None) == (args.urdf is None):
        raise UserError("give exactly one of OBJECT or --urdf FILE (or --list)")
    if args.out is None:
        raise UserError("--out DIR is required")
    if (args.start or args.end) and not args.urdf:
        raise UserError("--start/--end apply to --urdf objects only")
    for name, value, low in (("--res", args.res, 8), ("--views", args.views, 1),
                             ("--test-views", args.test_views, 0)):
        if value < low:
            raise UserError(f"{name} must be at least {low}, got {value}")
    effects = parse_effects(args.effects)
    if args.urdf:
        from gear.synth.urdf import load_urdf

        obj = load_urdf(
            args.urdf, _joint_values(args.start, "--start"), _joint_values(args.end, "--end")
        )
        meta = {"urdf": str(args.urdf)}
    else:
        obj, meta = build(args.object, args.seed), None
    out = render_scene(
        obj, args.out, args.res, args.views, args.test_views, args.seed, effects, meta, args.up
    )
    print(
        f"wrote {out} ({obj.name}: {len(obj.parts)} moving part(s), {args.res}x{args.res}, "
        f"{args.views}+{args.test_views} views per state)"
    )
    return 0
