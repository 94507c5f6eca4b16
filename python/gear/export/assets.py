"""The mesh files every model format of an export shares, written once per folder."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from gear.export.assembly import Assembly, Link

VISUAL_FOLDER = "meshes/visual"
COLLISION_FOLDER = "meshes/collision"


@dataclass
class LinkFiles:
    """Paths relative to the export folder of one link's meshes (in the link's frame)."""

    visual: str | None
    collision: list[str]


def write_link_meshes(assembly: Assembly, folder: Path) -> dict[str, LinkFiles]:
    """meshes/visual/<link>.obj (vertex colours, normals) and meshes/collision/<link>_<k>.obj
    (one convex piece each), all in their link's frame; link name -> its files."""
    (folder / VISUAL_FOLDER).mkdir(parents=True, exist_ok=True)
    (folder / COLLISION_FOLDER).mkdir(parents=True, exist_ok=True)
    return {link.name: _write_link(link, folder) for link in assembly.links}


def _write_link(link: Link, folder: Path) -> LinkFiles:
    visual = None
    if link.visual is not None:
        visual = f"{VISUAL_FOLDER}/{link.name}.obj"
        link.local(link.visual).export(folder / visual, file_type="obj", include_normals=True,
                                       include_color=True)
    collision = []
    for k, piece in enumerate(link.pieces):
        rel = f"{COLLISION_FOLDER}/{link.name}_{k}.obj"
        link.local(piece).export(folder / rel, file_type="obj", include_normals=False)
        collision.append(rel)
    return LinkFiles(visual, collision)
