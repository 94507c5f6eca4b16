"""`gear export OUT_DIR --urdf DIR`: the trained twin as a URDF for robotics (docs/export.md)."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help="write the trained twin as a URDF (links, joints, meshes)")
    p.add_argument("out_dir", type=Path, help="a trained run's output folder")
    p.add_argument("--urdf", type=Path, required=True, metavar="DIR",
                   help="folder to write <name>.urdf and meshes/*.obj into")
    p.add_argument("--name", default=None, help="robot name (default: OUT_DIR's folder name)")
    p.add_argument("--density", type=float, default=1000.0,
                   help="density for link masses, per cubic scene unit (default 1000: water "
                        "in kg/m^3 when the scene is in metres)")
    p.add_argument("--effort", type=float, default=100.0,
                   help="joint effort limit written to every joint (default 100)")
    p.add_argument("--velocity", type=float, default=1.0,
                   help="joint velocity limit written to every joint (default 1)")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from gear.export import export_urdf, roundtrip_errors

    result = export_urdf(args.out_dir, args.urdf, name=args.name, density=args.density,
                         effort=args.effort, velocity=args.velocity)
    for note in result.notes:
        print(f"note: {note}")
    print(f"wrote {result.urdf} ({len(result.joints)} joint(s))")
    for j in result.joints:
        amount = f"{j.amount:.2f} deg" if j.type == "revolute" else f"{j.amount:.4f}"
        print(f"  joint_{j.part - 1}: {j.type}, axis {j.axis.round(4).tolist()}, "
              f"through {j.origin.round(4).tolist()}, 0 -> {amount}")
    try:
        errors = roundtrip_errors(result)
    except ValueError as err:  # e.g. a moving link without geometry, which the reader refuses
        print(f"round-trip check skipped: gear's URDF reader refused the file ({err})")
        return 0
    if errors:
        for e in errors:
            print(f"round-trip check: {e}")
        return 1
    print("round-trip check: gear's URDF reader gives the same joints")
    return 0
