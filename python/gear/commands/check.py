"""`gear check SCENE_DIR`: validate a scene; list every problem (exit 1) or summarise (exit 0)."""

from __future__ import annotations

import argparse

from gear.data.scene import Scene


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("check", help="validate a scene directory (METHOD.md §1 layout)")
    p.add_argument("scene", help="scene directory")
    p.set_defaults(handler=run)


def summary(scene: Scene) -> str:
    counts = ", ".join(
        f"{state} {'+'.join(str(len(vs)) for vs in splits.values())}"
        for state, splits in scene.views.items()
    )
    sizes = sorted({(v.camera.width, v.camera.height) for v in scene.all_views()})
    has = [
        name
        for name, flag in (
            ("depth", scene.has_depth),
            ("region masks", scene.has_regions),
            ("GT part ids", scene.has_parts),
        )
        if flag
    ]
    if scene.gt is not None:
        n_meshes = sum(len(m) for m in scene.gt.meshes.values())
        has.append(f"GT {len(scene.gt.joints)} joint(s), {n_meshes} mesh(es)")
    return (
        f"{scene.root}: ok, {len(scene.all_views())} views ({counts}; train+test), "
        f"{' / '.join(f'{w}x{h}' for w, h in sizes)}, has {', '.join(has) or 'RGBA only'}"
    )


def run(args: argparse.Namespace) -> int:
    from gear.data.load import load_and_validate

    scene, problems = load_and_validate(args.scene)
    for problem in problems:
        print(problem)
    if problems:
        print(f"{len(problems)} problem(s) found")
        return 1
    print(summary(scene))
    return 0
