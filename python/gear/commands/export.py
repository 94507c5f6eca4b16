"""`gear export OUT_DIR --urdf DIR --mjcf DIR`: the trained twin as simulation-ready models
(docs/export.md)."""

from __future__ import annotations

import argparse
from pathlib import Path

from gear.export import defaults


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help="write the trained twin as URDF / MJCF for simulators, "
                                      "plus a GLB per state and a Gaussian PLY per part")
    p.add_argument("out_dir", type=Path, help="a trained run's output folder")
    p.add_argument("--urdf", type=Path, metavar="DIR", help="folder for NAME.urdf and its files")
    p.add_argument("--mjcf", type=Path, metavar="DIR",
                   help="folder for NAME.xml (MuJoCo) and its files (may be the --urdf folder)")
    p.add_argument("--name", default=None, help="model name (default: OUT_DIR's folder name)")
    add_model_options(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(handler=run)


def add_model_options(p: argparse.ArgumentParser) -> None:
    """The options shaping the exported model (`gear export` and `gear batch` share them)."""
    p.add_argument("--faces", type=int, default=defaults.FACES,
                   help=f"visual mesh faces per link (default {defaults.FACES})")
    mass = p.add_mutually_exclusive_group()
    mass.add_argument("--density", type=float, default=None,
                      help=f"kg per cubic scene unit for link masses (default {defaults.DENSITY:g},"
                           " for scenes in metres)")
    mass.add_argument("--mass", type=float, default=None,
                      help="total mass in kg, spread over the links by volume")
    p.add_argument("--widen", type=float, default=0.0, metavar="FRACTION",
                   help="widen each joint's limits past the observed start and end by this "
                        "fraction of the observed range (default 0)")
    p.add_argument("--damping", type=float, default=defaults.DAMPING,
                   help=f"joint damping, N*m*s/rad or N*s/m (default {defaults.DAMPING:g})")
    p.add_argument("--friction", type=float, default=defaults.FRICTION,
                   help=f"joint friction, N*m or N (default {defaults.FRICTION:g})")
    p.add_argument("--effort", type=float, default=defaults.EFFORT,
                   help=f"URDF joint effort limit (default {defaults.EFFORT:g})")
    p.add_argument("--velocity", type=float, default=defaults.VELOCITY,
                   help=f"URDF joint velocity limit (default {defaults.VELOCITY:g})")
    p.add_argument("--concavity", type=float, default=defaults.CONCAVITY,
                   help="convex decomposition tolerance, a fraction of the part's size "
                        f"(default {defaults.CONCAVITY:g}; smaller = more, tighter pieces)")
    p.add_argument("--max-pieces", type=int, default=defaults.MAX_PIECES,
                   help=f"convex pieces per link at most (default {defaults.MAX_PIECES})")


def model_options(args: argparse.Namespace):  # noqa: ANN201 (ExportOptions, imported lazily)
    """The ExportOptions given by `add_model_options`' arguments."""
    from gear.export.assembly import ExportOptions

    return ExportOptions(
        faces=args.faces, density=args.density, mass=args.mass, widen=args.widen,
        damping=args.damping, friction=args.friction, effort=args.effort,
        velocity=args.velocity, concavity=args.concavity, max_pieces=args.max_pieces)


def run(args: argparse.Namespace) -> int:
    from gear.export.bundle import export_twin
    from gear.export.urdf import roundtrip_errors
    from gear.run_folder import require_finished

    require_finished(args.out_dir)
    result = export_twin(args.out_dir, args.urdf, args.mjcf, name=args.name,
                         options=model_options(args), quiet=args.quiet)
    for note in result.notes:
        print(f"note: {note}")
    a = result.assembly
    for path in (result.urdf, result.mjcf):
        if path is not None:
            print(f"wrote {path}")
    print(f"every file holds the twin in its {a.state} state (joint value 0); "
          f"density {a.density:.4g} kg per cubic unit; {result.seconds:.1f} s")
    for link in a.links:
        faces = 0 if link.visual is None else len(link.visual.faces)
        print(f"  {link.name}: {link.inertial.mass:.3g} kg, {faces} visual faces, "
              f"{len(link.pieces)} convex pieces")
    for j in a.joints:
        unit = "rad" if j.type == "revolute" else "units"
        print(f"  {j.name}: {j.type}, axis {j.axis.round(4).tolist()}, through "
              f"{j.origin.round(4).tolist()}, limits [{j.lower:.4g}, {j.upper:.4g}] {unit}, "
              f"observed end {j.end:.4g}")
    if result.urdf is None:
        return 0
    try:
        errors = roundtrip_errors(result.urdf, a)
    except ValueError as err:  # e.g. a moving link without geometry, which the reader refuses
        print(f"round-trip check skipped: gear's URDF reader refused the file ({err})")
        return 0
    for e in errors:
        print(f"round-trip check: {e}")
    if not errors:
        print("round-trip check: gear's URDF reader gives the same joints")
    return 1 if errors else 0
