"""MJCF writer (MuJoCo's XML): the base body welded to the world, one child body per movable
part with a hinge or slide joint, one collision geom per convex piece, a visual geom per link
that does not collide, and no contact between the base and the parts hinged on it (their
pieces meet at hinges and slides by design)."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

from gear.export.assembly import Assembly, Link
from gear.export.assets import LinkFiles
from gear.export.urdf import num, state_comment, xyz

VISUAL_GROUP = "2"  # MuJoCo's viewer shows groups 0-2 by default and hides 3
COLLISION_GROUP = "3"


def _body(parent: ET.Element, link: Link, pos: str) -> ET.Element:
    body = ET.SubElement(parent, "body", name=link.name, pos=pos)
    i = link.inertial.inertia
    ET.SubElement(body, "inertial", pos=xyz(link.inertial.com - link.frame),
                  mass=num(link.inertial.mass),
                  fullinertia=" ".join(num(v) for v in (i[0, 0], i[1, 1], i[2, 2], i[0, 1],
                                                         i[0, 2], i[1, 2])))
    return body


def _geoms(body: ET.Element, link: Link, files: LinkFiles) -> None:
    if files.visual is not None:
        ET.SubElement(body, "geom", name=f"{link.name}_visual", mesh=f"{link.name}_visual",
                      **{"class": "visual"}, rgba=xyz(link.rgba))
    for k in range(len(files.collision)):
        ET.SubElement(body, "geom", name=f"{link.name}_collision_{k}",
                      mesh=f"{link.name}_collision_{k}", **{"class": "collision"})


def write_mjcf(assembly: Assembly, files: dict[str, LinkFiles], path: Path) -> None:
    root = ET.Element("mujoco", model=assembly.name)
    root.append(ET.Comment(state_comment(assembly)))
    # Masses are given per body: MuJoCo must not recompute them from the (open) visual meshes.
    ET.SubElement(root, "compiler", angle="radian", inertiafromgeom="false")
    default = ET.SubElement(root, "default")
    ET.SubElement(ET.SubElement(default, "default", **{"class": "visual"}), "geom",
                  type="mesh", contype="0", conaffinity="0", group=VISUAL_GROUP)
    ET.SubElement(ET.SubElement(default, "default", **{"class": "collision"}), "geom",
                  type="mesh", group=COLLISION_GROUP, rgba="0.5 0.5 0.5 0.4")
    asset = ET.SubElement(root, "asset")
    for link in assembly.links:
        link_files = files[link.name]
        if link_files.visual is not None:
            ET.SubElement(asset, "mesh", name=f"{link.name}_visual", file=link_files.visual)
        for k, rel in enumerate(link_files.collision):
            ET.SubElement(asset, "mesh", name=f"{link.name}_collision_{k}", file=rel)
    world = ET.SubElement(root, "worldbody")
    base_link = assembly.links[0]
    base = _body(world, base_link, "0 0 0")
    _geoms(base, base_link, files[base_link.name])
    contact = ET.SubElement(root, "contact")
    for joint, link in zip(assembly.joints, assembly.links[1:], strict=True):
        unit = "rad" if joint.type == "revolute" else "scene units"
        base.append(ET.Comment(f" {joint.name}: observed end state at {num(joint.end)} {unit} "))
        body = _body(base, link, xyz(joint.origin))
        ET.SubElement(body, "joint", name=joint.name,
                      type="hinge" if joint.type == "revolute" else "slide", pos="0 0 0",
                      axis=xyz(joint.axis), limited="true",
                      range=f"{num(joint.lower)} {num(joint.upper)}",
                      damping=num(joint.damping), frictionloss=num(joint.friction))
        _geoms(body, link, files[link.name])
        ET.SubElement(contact, "exclude", body1=base_link.name, body2=link.name)
    tree = ET.ElementTree(root)
    ET.indent(tree)
    tree.write(path, encoding="utf-8", xml_declaration=True)
