"""URDF writer: one link per part, one joint per movable part (parent `base`), meshes as OBJ
relative to the file, one `<collision>` per convex piece (docs/export.md)."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from gear.export.assembly import BASE_LINK, Assembly
from gear.export.assets import LinkFiles
from gear.export.inertials import Inertial

# MuJoCo reads these compiler settings from a URDF's <mujoco> element: keep mesh paths as
# written (it strips them by default), and keep `base` a body of its own so the usual
# parent-child contact filter applies between it and the parts hinged on it.
MUJOCO_COMPILER = {"strippath": "false", "fusestatic": "false", "discardvisual": "true"}


def num(x: float) -> str:
    return f"{float(x) + 0.0:.10g}"  # + 0.0 turns -0.0 into 0


def xyz(v: np.ndarray) -> str:
    return " ".join(num(x) for x in v)


def state_comment(assembly: Assembly) -> str:
    return (f" gear export: every link is in the {assembly.state.upper()} state of the twin: "
            f"joint value 0 is the {assembly.state} state, each joint's observed end state is "
            "listed below (the limits may be widened past it). ")


def _inertial(parent: ET.Element, inertial: Inertial, frame: np.ndarray) -> None:
    node = ET.SubElement(parent, "inertial")
    ET.SubElement(node, "origin", xyz=xyz(inertial.com - frame), rpy="0 0 0")
    ET.SubElement(node, "mass", value=num(inertial.mass))
    i = inertial.inertia
    ET.SubElement(node, "inertia", ixx=num(i[0, 0]), ixy=num(i[0, 1]), ixz=num(i[0, 2]),
                  iyy=num(i[1, 1]), iyz=num(i[1, 2]), izz=num(i[2, 2]))


def write_urdf(assembly: Assembly, files: dict[str, LinkFiles], path: Path) -> None:
    robot = ET.Element("robot", name=assembly.name)
    robot.append(ET.Comment(state_comment(assembly)))
    ET.SubElement(ET.SubElement(robot, "mujoco"), "compiler", **MUJOCO_COMPILER)
    for link in assembly.links:
        node = ET.SubElement(robot, "link", name=link.name)
        link_files = files[link.name]
        if link_files.visual is not None:
            visual = ET.SubElement(node, "visual", name=f"{link.name}_visual")
            ET.SubElement(visual, "origin", xyz="0 0 0", rpy="0 0 0")
            ET.SubElement(ET.SubElement(visual, "geometry"), "mesh", filename=link_files.visual)
            material = ET.SubElement(visual, "material", name=f"{link.name}_color")
            ET.SubElement(material, "color", rgba=xyz(link.rgba))
        for k, rel in enumerate(link_files.collision):
            collision = ET.SubElement(node, "collision", name=f"{link.name}_collision_{k}")
            ET.SubElement(collision, "origin", xyz="0 0 0", rpy="0 0 0")
            ET.SubElement(ET.SubElement(collision, "geometry"), "mesh", filename=rel)
        _inertial(node, link.inertial, link.frame)
    for joint in assembly.joints:
        unit = "rad" if joint.type == "revolute" else "scene units"
        robot.append(ET.Comment(f" {joint.name}: observed end state at {num(joint.end)} {unit} "))
        node = ET.SubElement(robot, "joint", name=joint.name, type=joint.type)
        ET.SubElement(node, "parent", link=BASE_LINK)
        ET.SubElement(node, "child", link=joint.child)
        ET.SubElement(node, "origin", xyz=xyz(joint.origin), rpy="0 0 0")
        ET.SubElement(node, "axis", xyz=xyz(joint.axis))
        ET.SubElement(node, "limit", lower=num(joint.lower), upper=num(joint.upper),
                      effort=num(joint.effort), velocity=num(joint.velocity))
        ET.SubElement(node, "dynamics", damping=num(joint.damping), friction=num(joint.friction))
    tree = ET.ElementTree(robot)
    ET.indent(tree)
    tree.write(path, encoding="utf-8", xml_declaration=True)


def roundtrip_errors(path: Path, assembly: Assembly, tol: float = 1e-6) -> list[str]:
    """Reads the URDF back with gear's own importer and lists every joint that differs from
    what was written (type, axis, axis line, observed start -> end amount); [] when all agree."""
    from gear.synth.urdf import load_urdf

    parts = load_urdf(path).parts
    if len(parts) != len(assembly.joints):
        return [f"{path}: {len(parts)} moving joint(s) read back, "
                f"{len(assembly.joints)} written"]
    errors = []
    for part, joint in zip(parts, assembly.joints, strict=True):
        got = part.joint
        offset = np.asarray(got.origin) - joint.origin
        off_axis = offset - np.dot(offset, joint.axis) * joint.axis  # any point on the axis
        checks = {
            "type": got.type == joint.type,
            "axis": np.allclose(got.axis / np.linalg.norm(got.axis), joint.axis, atol=tol),
            "origin": np.linalg.norm(off_axis) <= tol,
            "limits": abs(got.lower - joint.lower) <= tol and abs(got.upper - joint.upper) <= tol,
        }
        errors += [f"{part.joint.name}: {what} differs after reading back"
                   for what, ok in checks.items() if not ok]
    return errors
