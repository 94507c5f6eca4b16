"""Import a URDF articulated object (PartNet-Mobility `mobility.urdf` + OBJ meshes first).

Handles: revolute, prismatic, continuous (a revolute joint without limits) and fixed joints;
several visuals per link; links without geometry; mesh/box/cylinder/sphere geometry; OBJ
materials (`Kd` colours, `map_Kd` textures resolved relative to the .mtl file).
Joints whose value is the same in both states are frozen at that value: their child links
belong to their parent's part. A moving joint below another moving joint is refused (its
motion would not be one rigid joint of trans.json).
"""

from __future__ import annotations

import hashlib
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh
from PIL import Image

from gear.synth.model import Articulated, Joint, Part, Surface

UNTEXTURED_PATTERN = 0.12  # faint solid texture on flat-coloured assets (photometric grip)
MOVABLE = ("revolute", "continuous", "prismatic")


@dataclass
class _Visual:
    origin: np.ndarray  # 4x4 in the link frame
    kind: str  # "mesh" | "box" | "cylinder" | "sphere"
    params: dict
    color: np.ndarray | None  # rgb from a URDF <material>


@dataclass
class _Joint:
    name: str
    type: str
    parent: str
    child: str
    origin: np.ndarray  # 4x4 in the parent link frame
    axis: np.ndarray
    lower: float
    upper: float


@dataclass
class _Robot:
    links: dict[str, list[_Visual]] = field(default_factory=dict)
    joints: dict[str, _Joint] = field(default_factory=dict)  # by child link


def _floats(text: str | None, n: int, default: list[float], what: str) -> np.ndarray:
    if text is None:
        return np.array(default, dtype=np.float64)
    try:
        values = np.array([float(x) for x in text.split()], dtype=np.float64)
    except ValueError:
        raise ValueError(f"{what}: expected {n} numbers, got {text!r}") from None
    if values.shape != (n,) or not np.all(np.isfinite(values)):
        raise ValueError(f"{what}: expected {n} finite numbers, got {text!r}")
    return values


def _origin(elem: ET.Element | None, what: str) -> np.ndarray:
    if elem is None:
        return np.eye(4)
    xyz = _floats(elem.get("xyz"), 3, [0, 0, 0], f"{what} origin xyz")
    roll, pitch, yaw = _floats(elem.get("rpy"), 3, [0, 0, 0], f"{what} origin rpy")
    out = trimesh.transformations.euler_matrix(roll, pitch, yaw, "sxyz")
    out[:3, 3] = xyz
    return out


def _parse(path: Path) -> _Robot:
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as err:
        raise ValueError(f"{path}: not a readable URDF ({err})") from None
    if root.tag != "robot":
        raise ValueError(f"{path}: the root element is <{root.tag}>, not <robot>")
    materials = {}
    for m in root.findall("material"):
        color = m.find("color")
        if m.get("name") and color is not None:
            materials[m.get("name")] = _floats(color.get("rgba"), 4, [1, 1, 1, 1], "color")[:3]
    robot = _Robot()
    for link in root.findall("link"):
        name = link.get("name")
        visuals = []
        for k, vis in enumerate(link.findall("visual")):
            what = f"{path.name}: link {name} visual {k}"
            geom = vis.find("geometry")
            shape = geom[0] if geom is not None and len(geom) else None
            if shape is None:
                continue
            params = dict(shape.attrib)
            color = None
            mat = vis.find("material")
            if mat is not None:
                c = mat.find("color")
                color = (
                    _floats(c.get("rgba"), 4, [1, 1, 1, 1], f"{what} color")[:3]
                    if c is not None
                    else materials.get(mat.get("name"))
                )
            if shape.tag not in ("mesh", "box", "cylinder", "sphere"):
                raise ValueError(f"{what}: unsupported geometry <{shape.tag}>")
            visuals.append(_Visual(_origin(vis.find("origin"), what), shape.tag, params, color))
        robot.links[name] = visuals
    for j in root.findall("joint"):
        name, kind = j.get("name"), j.get("type")
        parent, child = j.find("parent"), j.find("child")
        if parent is None or child is None:
            raise ValueError(f"{path.name}: joint {name} needs <parent> and <child>")
        limit = j.find("limit")
        lower, upper = -np.inf, np.inf
        if kind in ("revolute", "prismatic"):
            if limit is None:
                raise ValueError(f"{path.name}: {kind} joint {name} needs <limit>")
            lower, upper = float(limit.get("lower", 0)), float(limit.get("upper", 0))
        axis = _floats(
            j.find("axis").get("xyz") if j.find("axis") is not None else None,
            3,
            [1, 0, 0],
            f"joint {name} axis",
        )
        if kind in MOVABLE and np.linalg.norm(axis) < 1e-12:
            raise ValueError(f"{path.name}: joint {name} has a zero axis")
        robot.joints[child.get("link")] = _Joint(
            name,
            kind,
            parent.get("link"),
            child.get("link"),
            _origin(j.find("origin"), f"joint {name}"),
            axis,
            lower,
            upper,
        )
    missing = {j.parent for j in robot.joints.values()} - set(robot.links)
    if missing:
        raise ValueError(f"{path.name}: joints refer to unknown link(s) {sorted(missing)}")
    return robot


def _joint_values(
    robot: _Robot, start: dict[str, float], end: dict[str, float]
) -> dict[str, tuple[float, float]]:
    """(start, end) per joint: given values, else the limits (lower -> upper) for limited
    joints and 0 for continuous ones (which then do not move)."""
    joints = {j.name: j for j in robot.joints.values()}
    for given, flag in ((start, "--start"), (end, "--end")):
        unknown = sorted(set(given) - {n for n, j in joints.items() if j.type in MOVABLE})
        if unknown:
            movable = sorted(n for n, j in joints.items() if j.type in MOVABLE)
            raise ValueError(f"{flag}: no movable joint named {unknown}; movable: {movable}")
    out = {}
    for name, j in joints.items():
        default = (j.lower, j.upper) if j.type in ("revolute", "prismatic") else (0.0, 0.0)
        out[name] = (start.get(name, default[0]), end.get(name, default[1]))
    return out


def _texture(path: Path, cache: dict[str, np.ndarray]) -> np.ndarray:
    """Texture image as float32 RGB, shared between meshes that use the same image (PartNet
    assets reference one image from dozens of .mtl files)."""
    key = hashlib.md5(path.read_bytes()).hexdigest()
    if key not in cache:
        try:
            cache[key] = np.asarray(Image.open(path).convert("RGB"), dtype=np.float32) / 255.0
        except OSError as err:
            raise ValueError(f"texture {path} is unreadable ({err})") from None
    return cache[key]


def _mtl_maps(obj_path: Path) -> dict[str, Path]:
    """material name -> diffuse texture file, from the .mtl libraries an OBJ names."""
    maps: dict[str, Path] = {}
    for line in obj_path.read_text(errors="replace").splitlines():
        if not line.startswith("mtllib"):
            continue
        mtl = obj_path.parent / line.split(maxsplit=1)[1].strip()
        if not mtl.is_file():
            continue
        current = None
        for m in mtl.read_text(errors="replace").splitlines():
            words = m.split()
            if words[:1] == ["newmtl"] and len(words) > 1:
                current = words[1]
            elif words[:1] == ["map_Kd"] and current and len(words) > 1:
                maps[current] = mtl.parent / words[-1]
    return maps


def _mesh_surfaces(
    file: Path, scale: np.ndarray, color: np.ndarray | None, textures: dict[str, np.ndarray]
) -> list[Surface]:
    if not file.is_file():
        raise ValueError(f"mesh file {file} is missing")
    try:
        scene = trimesh.load(file, force="scene", process=False)
    except Exception as err:  # trimesh raises many kinds for broken files
        raise ValueError(f"mesh file {file} is unreadable ({err})") from None
    maps = _mtl_maps(file) if file.suffix.lower() == ".obj" else {}
    out = []
    for mesh in scene.dump():
        if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
            continue
        verts = mesh.vertices * scale
        faces = np.asarray(mesh.faces)
        visual = mesh.visual
        material = getattr(visual, "material", None)
        uv, texture = None, None
        rgb = color if color is not None else np.array([0.7, 0.7, 0.7])
        if visual.kind == "texture" and material is not None:
            if getattr(material, "diffuse", None) is not None:
                rgb = np.asarray(material.diffuse[:3], dtype=np.float64) / 255.0
            tex_file = maps.get(getattr(material, "name", None))
            if tex_file is not None and visual.uv is not None and tex_file.is_file():
                uv, texture = np.asarray(visual.uv)[faces], _texture(tex_file, textures)
        elif visual.kind in ("face", "vertex"):
            face_rgb = np.asarray(visual.face_colors[:, :3], dtype=np.float64) / 255.0
            rgb = face_rgb
        pattern = 0.0 if texture is not None else UNTEXTURED_PATTERN
        out.append(Surface(verts, faces, np.asarray(rgb, np.float32), pattern, uv, texture))
    return out


def _visual_surfaces(vis: _Visual, base: Path, textures: dict[str, np.ndarray]) -> list[Surface]:
    color = vis.color
    if vis.kind == "mesh":
        filename = vis.params.get("filename", "")
        if filename.startswith("package://"):
            filename = filename.split("/", 3)[-1]
        scale = _floats(vis.params.get("scale"), 3, [1, 1, 1], f"mesh {filename} scale")
        surfaces = _mesh_surfaces(base / filename, scale, color, textures)
    else:
        if vis.kind == "box":
            mesh = trimesh.creation.box(
                extents=_floats(vis.params.get("size"), 3, [1, 1, 1], "box size")
            )
        elif vis.kind == "cylinder":
            mesh = trimesh.creation.cylinder(
                radius=float(vis.params.get("radius", 0.5)),
                height=float(vis.params.get("length", 1)),
            )
        else:
            mesh = trimesh.creation.icosphere(2, radius=float(vis.params.get("radius", 0.5)))
        rgb = color if color is not None else np.array([0.7, 0.7, 0.7])
        surfaces = [Surface(mesh.vertices, mesh.faces, rgb, UNTEXTURED_PATTERN)]
    return [s.transformed(vis.origin) for s in surfaces]


def load_urdf(
    path: str | Path,
    start: dict[str, float] | None = None,
    end: dict[str, float] | None = None,
) -> Articulated:
    """The URDF at `path` as an `Articulated` object; joint values in radians or metres."""
    path = Path(path)
    robot = _parse(path)
    values = _joint_values(robot, start or {}, end or {})
    roots = [name for name in robot.links if name not in robot.joints]
    if len(roots) != 1:
        raise ValueError(f"{path.name}: expected one root link, found {roots}")

    def moving(j: _Joint) -> bool:
        return j.type in MOVABLE and values[j.name][0] != values[j.name][1]

    # Walk the tree from the root: each link's transform with moving joints at 0 (the parts'
    # rest geometry) and the part (index into `parts`, -1 static) it belongs to.
    children: dict[str, list[_Joint]] = {}
    for j in robot.joints.values():
        children.setdefault(j.parent, []).append(j)
    static: list[Surface] = []
    parts: list[Part] = []
    textures: dict[str, np.ndarray] = {}
    stack = [(roots[0], np.eye(4), -1)]
    seen = set()
    while stack:
        link, pose, part = stack.pop()
        if link in seen:
            raise ValueError(f"{path.name}: link {link} is reached twice (the joints form a loop)")
        seen.add(link)
        surfaces = [
            s.transformed(pose)
            for v in robot.links.get(link, [])
            for s in _visual_surfaces(v, path.parent, textures)
        ]
        (static if part < 0 else parts[part].surfaces).extend(surfaces)
        for j in children.get(link, []):
            frame = pose @ j.origin
            axis = j.axis / max(np.linalg.norm(j.axis), 1e-12)
            if moving(j):
                if part >= 0:
                    raise ValueError(
                        f"{path.name}: joint {j.name} moves and so does its ancestor joint "
                        f"{parts[part].joint.name}; keep one of them fixed with --start/--end"
                    )
                kind = "prismatic" if j.type == "prismatic" else "revolute"
                joint = Joint(
                    j.name,
                    kind,
                    frame[:3, 3],
                    frame[:3, :3] @ axis,
                    j.lower,
                    j.upper,
                    *values[j.name],
                )
                parts.append(Part(joint, []))
                stack.append((j.child, frame, len(parts) - 1))
            else:
                value = values[j.name][0] if j.type in MOVABLE else 0.0
                frozen = Joint(
                    j.name,
                    "prismatic" if j.type == "prismatic" else "revolute",
                    np.zeros(3),
                    axis,
                    -np.inf,
                    np.inf,
                    value,
                    value,
                ).pose(value)
                stack.append((j.child, frame @ frozen, part))
    empty = [p.joint.name for p in parts if not p.surfaces]
    if empty:
        raise ValueError(
            f"{path.name}: moving joint(s) {empty} carry no geometry; freeze them with "
            "--start/--end"
        )
    order = {j.name: i for i, j in enumerate(robot.joints.values())}  # file order
    parts.sort(key=lambda p: order[p.joint.name])
    if not static and not parts:
        raise ValueError(f"{path.name}: no visual geometry")
    return Articulated(path.parent.name if path.stem == "mobility" else path.stem, static, parts)
