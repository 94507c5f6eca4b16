"""Export a trained twin as a URDF articulated model for robotics tools (docs/export.md).

One link per part: `base` (the static part) and `part_<i>` (moved by joints[i]), one joint per
movable part (`joint_<i>`, parent `base`). Everything is expressed in the START state: joint
value 0 is the start state, the end state is value `angle` (radians) or `distance`, and the
limits are that interval. Each joint frame sits on the joint's axis point (`origin` in
joints.json) with the world's orientation, so the axis is written in world coordinates; each
part's mesh is shifted into that frame by its visual/collision origin. Meshes are the trained
TSDF meshes converted to Wavefront OBJ, the mesh format URDF loaders most widely accept.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from gear.twin import TwinError, TwinJoint, load_joints

BASE_LINK = "base"
MESH_FOLDER = "meshes"


@dataclass
class UrdfExport:
    """What `export_urdf` wrote, and anything the user should know about it."""

    urdf: Path
    joints: list[TwinJoint]  # as written: amount >= 0 (a negative one has its axis flipped)
    notes: list[str] = field(default_factory=list)


def _load_mesh(path: Path) -> trimesh.Trimesh | None:
    """The triangles in `path` (None when the file holds none); a broken file is an error."""
    try:
        loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as err:  # trimesh raises many exception kinds for broken files
        raise TwinError(f"{path}: unreadable mesh ({err})") from None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        return None
    if not np.all(np.isfinite(loaded.vertices)):
        raise TwinError(f"{path}: mesh has non-finite vertices")
    return loaded


def start_meshes(out_dir: Path, joints: list[TwinJoint],
                 notes: list[str]) -> dict[str, trimesh.Trimesh | None]:
    """"static" and "part_<i>" meshes in the start state: meshes/start/<name>.ply, else the
    end-state file moved back along its joint. None for a part whose mesh is empty."""
    movers: dict[str, TwinJoint | None] = {"static": None}
    movers.update({f"part_{j.part - 1}": j for j in joints})
    out: dict[str, trimesh.Trimesh | None] = {}
    for name, joint in movers.items():
        start, end = (out_dir / "meshes" / s / f"{name}.ply" for s in ("start", "end"))
        if start.is_file():
            out[name] = _load_mesh(start)
        elif end.is_file():
            mesh = _load_mesh(end)
            if mesh is not None and joint is not None:
                rot, t = joint.motion(-1.0)
                matrix = np.eye(4)
                matrix[:3, :3], matrix[:3, 3] = rot, t
                mesh.apply_transform(matrix)
            notes.append(f"{name}: no start-state mesh, used {end} moved back to the start state")
            out[name] = mesh
        else:
            raise TwinError(f"{start}: missing (and no {end} either): the part meshes of a "
                            "trained run")
        if out[name] is None:
            notes.append(f"{name}: its mesh is empty, the link has no visual/collision/inertia")
    return out


def _num(x: float) -> str:
    return f"{float(x) + 0.0:.15g}"  # + 0.0 turns -0.0 into 0


def _xyz(v: np.ndarray) -> str:
    return " ".join(_num(x) for x in v)


def _inertial(link: ET.Element, mesh: trimesh.Trimesh, frame: np.ndarray, density: float,
              notes: list[str], name: str) -> None:
    """Mass, centre of mass and inertia of the mesh's convex hull at `density` (TSDF meshes
    are rarely watertight; their hull always is)."""
    try:
        body = mesh.convex_hull
        ok = body.volume > 1e-12
    except Exception:  # qhull refuses flat or degenerate point sets
        ok = False
    if not ok:  # flat part: a box of its bounds, thickened so the inertia is positive
        extents = np.maximum(mesh.extents, 1e-3 * max(float(mesh.extents.max()), 1e-3))
        body = trimesh.creation.box(extents=extents)
        body.apply_translation(mesh.bounds.mean(axis=0))
        notes.append(f"{name}: flat mesh, inertia from a thickened bounding box")
    body.density = density
    inertia = body.moment_inertia  # about the centre of mass, world axes
    node = ET.SubElement(link, "inertial")
    ET.SubElement(node, "origin", xyz=_xyz(body.center_mass - frame), rpy="0 0 0")
    ET.SubElement(node, "mass", value=_num(body.mass))
    ET.SubElement(node, "inertia", **{
        f"i{a}{b}": _num(inertia[i, j])
        for i, j, a, b in ((0, 0, "x", "x"), (0, 1, "x", "y"), (0, 2, "x", "z"),
                           (1, 1, "y", "y"), (1, 2, "y", "z"), (2, 2, "z", "z"))
    })


def _link(robot: ET.Element, name: str, mesh: trimesh.Trimesh | None, frame: np.ndarray,
          urdf_dir: Path, density: float, notes: list[str]) -> None:
    """A link whose frame is at `frame` (world, no rotation), its mesh written as OBJ."""
    link = ET.SubElement(robot, "link", name=name)
    if mesh is None:
        return
    rel = f"{MESH_FOLDER}/{name}.obj"
    mesh.export(urdf_dir / rel, file_type="obj")
    for tag in ("visual", "collision"):
        node = ET.SubElement(link, tag)
        ET.SubElement(node, "origin", xyz=_xyz(-frame), rpy="0 0 0")
        ET.SubElement(ET.SubElement(node, "geometry"), "mesh", filename=rel)
    _inertial(link, mesh, frame, density, notes, name)


def _signed(joint: TwinJoint) -> TwinJoint:
    """The same motion with a non-negative amount (a negative one flips the axis)."""
    if joint.amount >= 0:
        return joint
    return TwinJoint(joint.part, joint.type, -joint.axis, joint.origin, -joint.amount)


def export_urdf(out_dir: str | Path, urdf_dir: str | Path, name: str | None = None,
                density: float = 1000.0, effort: float = 100.0,
                velocity: float = 1.0) -> UrdfExport:
    """Writes URDF_DIR/<name>.urdf and URDF_DIR/meshes/*.obj from a trained OUT_DIR."""
    out_dir, urdf_dir = Path(out_dir), Path(urdf_dir)
    for what, value in (("density", density), ("effort", effort), ("velocity", velocity)):
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"{what} must be a positive number, got {value}")
    _, joints = load_joints(out_dir)
    joints = [_signed(j) for j in joints]
    notes: list[str] = []
    meshes = start_meshes(out_dir, joints, notes)
    name = name or out_dir.resolve().name
    (urdf_dir / MESH_FOLDER).mkdir(parents=True, exist_ok=True)

    robot = ET.Element("robot", name=name)
    _link(robot, BASE_LINK, meshes["static"], np.zeros(3), urdf_dir, density, notes)
    for j in joints:
        i = j.part - 1
        _link(robot, f"part_{i}", meshes[f"part_{i}"], j.origin, urdf_dir, density, notes)
        node = ET.SubElement(robot, "joint", name=f"joint_{i}", type=j.type)
        ET.SubElement(node, "parent", link=BASE_LINK)
        ET.SubElement(node, "child", link=f"part_{i}")
        ET.SubElement(node, "origin", xyz=_xyz(j.origin), rpy="0 0 0")
        ET.SubElement(node, "axis", xyz=_xyz(j.axis))
        upper = math.radians(j.amount) if j.type == "revolute" else j.amount
        ET.SubElement(node, "limit", lower="0", upper=_num(upper), effort=_num(effort),
                      velocity=_num(velocity))
    tree = ET.ElementTree(robot)
    ET.indent(tree)
    path = urdf_dir / f"{name}.urdf"
    tree.write(path, encoding="utf-8", xml_declaration=True)
    return UrdfExport(path, joints, notes)


def roundtrip_errors(export: UrdfExport, tol: float = 1e-6) -> list[str]:
    """Reads the URDF back with gear's own importer and lists every joint that differs from
    what was exported (type, axis, axis point, start -> end amount); [] when all agree."""
    from gear.synth.urdf import load_urdf

    parts = load_urdf(export.urdf).parts
    if len(parts) != len(export.joints):
        return [f"{export.urdf}: {len(parts)} moving joint(s) read back, "
                f"{len(export.joints)} written"]
    errors = []
    for part, joint in zip(parts, export.joints, strict=True):
        got = part.joint.gt()
        want_amount = joint.amount
        offset = np.asarray(got.origin) - joint.origin
        off_axis = offset - np.dot(offset, joint.axis) * joint.axis  # any point on the axis
        checks = {
            "type": got.type == joint.type,
            "axis": np.allclose(got.axis, joint.axis, atol=tol),
            "origin": np.linalg.norm(off_axis) <= tol,
            "amount": abs(got.amount - want_amount) <= tol * max(1.0, abs(want_amount)),
        }
        errors += [f"{part.joint.name}: {what} differs after reading back"
                   for what, ok in checks.items() if not ok]
    return errors
