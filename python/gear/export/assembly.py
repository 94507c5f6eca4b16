"""The articulated model every writer shares: links (visual mesh, convex collision pieces,
inertial) and joints (axis, limits, dynamics), built once from a trained run.

Links: `base` is the static part, `part_<i>` the part moved by joints[i] (its id is i+1 in the
run). Each joint frame sits on the joint's axis point with the world's orientation, so axes are
world directions; every geometry is in the START state, where every joint value is 0.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import trimesh

from gear.data.scene import GtJoint
from gear.export import defaults
from gear.export.clearance import clear_joint_paths
from gear.export.collision import convex_pieces
from gear.export.inertials import (
    Inertial,
    check_positive,
    link_density,
    point_inertial,
    solid_inertial,
)
from gear.export.meshes import visual_mesh
from gear.export.source import EXPORT_STATE, RunSource
from gear.twin import TwinJoint

BASE_LINK = "base"
CLEARANCE = 1e-3  # gap left between moving and static collision pieces, x the object's size


@dataclass
class ExportOptions:
    faces: int = defaults.FACES  # visual faces per link
    density: float | None = None  # kg per cubic scene unit (None: defaults.DENSITY)
    mass: float | None = None  # total kg, spread over the links by volume (overrides density)
    widen: float = 0.0  # joint limits grow by this fraction of the observed range at both ends
    damping: float = defaults.DAMPING
    friction: float = defaults.FRICTION
    effort: float = defaults.EFFORT
    velocity: float = defaults.VELOCITY
    concavity: float = defaults.CONCAVITY
    max_pieces: int = defaults.MAX_PIECES

    def check(self) -> None:
        if self.faces < 4:
            raise ValueError(f"--faces must be at least 4, got {self.faces}")
        if self.max_pieces < 1:
            raise ValueError(f"--max-pieces must be at least 1, got {self.max_pieces}")
        for what, value in (("--density", self.density), ("--mass", self.mass),
                            ("--effort", self.effort), ("--velocity", self.velocity),
                            ("--concavity", self.concavity)):
            check_positive(what, value)
        for what, value in (("--widen", self.widen), ("--damping", self.damping),
                            ("--friction", self.friction)):
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{what} must be a number >= 0, got {value}")


@dataclass
class Link:
    name: str  # "base" | "part_<i>"
    part: str  # the run's part name: "static" | "part_<i>"
    frame: np.ndarray  # [3] world position of the link frame in the start state
    visual: trimesh.Trimesh | None  # world coordinates, start state, vertex colours
    pieces: list[trimesh.Trimesh]  # convex collision pieces, world coordinates
    inertial: Inertial
    rgba: np.ndarray  # [4] the link's mean colour, for formats without vertex colours

    def local(self, mesh: trimesh.Trimesh) -> trimesh.Trimesh:
        """A copy of `mesh` in this link's frame."""
        out = mesh.copy()
        out.apply_translation(-self.frame)
        return out


@dataclass
class Joint:
    name: str  # "joint_<i>"
    child: str  # "part_<i>"
    type: str  # "revolute" | "prismatic"
    origin: np.ndarray  # [3] world, on the axis: the child link's frame
    axis: np.ndarray  # [3] unit, world
    lower: float  # radians or scene units
    upper: float
    end: float  # the observed end state's joint value (the start state is 0)
    damping: float
    friction: float
    effort: float
    velocity: float

    def motion(self, value: float) -> np.ndarray:
        """4x4 world transform of the child's start-state geometry at joint `value`."""
        amount = math.degrees(value) if self.type == "revolute" else value
        return GtJoint(self.type, self.origin, self.axis, amount).motion()


@dataclass
class Assembly:
    name: str
    links: list[Link]  # links[0] is the base
    joints: list[Joint]  # joints[i] moves links[i + 1]
    state: str = EXPORT_STATE
    density: float = 0.0  # the density the masses were computed with
    notes: list[str] = field(default_factory=list)


def _joint(j: TwinJoint, options: ExportOptions) -> Joint:
    i = j.part - 1
    end = math.radians(j.amount) if j.type == "revolute" else j.amount
    margin = options.widen * end
    lower = 0.0 - margin  # not -margin: -0.0 would print as "-0"
    return Joint(f"joint_{i}", f"part_{i}", j.type, j.origin, j.axis, lower, end + margin, end,
                 options.damping, options.friction, options.effort, options.velocity)


def build_assembly(run: RunSource, name: str, options: ExportOptions,
                   progress: Callable[[str], None] = lambda _: None) -> Assembly:
    """Visual meshes, convex decompositions and inertials of every part of `run`;
    `progress` is called with each part's name when it is done."""
    options.check()
    frames = [np.zeros(3)] + [j.origin for j in run.joints]
    visuals, pieces = [], []
    for part in run.parts:
        if part.mesh is None:
            visuals.append(None)
            pieces.append([])
        else:
            visuals.append(visual_mesh(part.mesh, options.faces, part.means, part.rgb,
                                       part.opacity))
            pieces.append(convex_pieces(part.mesh, options.concavity, options.max_pieces))
        progress(part.name)
    joints = [_joint(j, options) for j in run.joints]
    notes = list(run.notes)
    if pieces[0] and joints:
        everything = [m for m in (p.mesh for p in run.parts) if m is not None]
        size = float(np.linalg.norm(np.ptp(np.concatenate([m.vertices for m in everything]), 0)))
        pieces[0], cuts = clear_joint_paths(pieces[0], list(zip(joints, pieces[1:], strict=True)),
                                            CLEARANCE * size)
        if cuts:
            notes.append(f"base: {cuts} plane cut(s) of its collision pieces clear the moving "
                         "parts' paths")
    volumes = [sum(p.volume for p in ps) for ps in pieces]
    density = link_density(volumes, options.density, options.mass)
    links = []
    for k, part in enumerate(run.parts):
        visual = visuals[k]
        inertial = (solid_inertial(pieces[k], density) if pieces[k]
                    else point_inertial(frames[k]))
        rgba = (np.append(visual.visual.vertex_colors[:, :3].mean(axis=0) / 255, 1.0)
                if visual is not None else np.array([0.6, 0.6, 0.6, 1.0]))
        links.append(Link(BASE_LINK if k == 0 else part.name, part.name, frames[k], visual,
                          pieces[k], inertial, rgba))
    return Assembly(name, links, joints, EXPORT_STATE, density, notes)
