"""A binary glTF (GLB) of the whole twin in one state: one node per link with its coloured
visual mesh, for any 3D viewer."""

from __future__ import annotations

from pathlib import Path

import trimesh

from gear.export.assembly import Assembly


def write_glb(assembly: Assembly, fraction: float, path: Path) -> None:
    """The visual meshes with every joint at `fraction` of its observed start -> end motion
    (0: the start state, 1: the end state)."""
    scene = trimesh.Scene()
    movers = {joint.child: joint.motion(fraction * joint.end) for joint in assembly.joints}
    for link in assembly.links:
        if link.visual is None:
            continue
        mesh = link.visual.copy()
        if link.name in movers:
            mesh.apply_transform(movers[link.name])
        scene.add_geometry(mesh, node_name=link.name, geom_name=link.name)
    path.write_bytes(scene.export(file_type="glb"))
