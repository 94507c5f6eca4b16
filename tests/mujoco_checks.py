"""Physics checks of an exported model in MuJoCo, shared by the export tests: joint drift with
nothing driving the joints, and a position-actuator drive to each limit while measuring how
deep any moving collision piece sinks into the static body (MuJoCo's signed geom distance,
which is computed even between bodies whose contacts are excluded)."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

MOVING_JOINTS = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))
DRIVE_HZ = 2.0  # the position servo's natural frequency (critically damped)


def load(path: Path) -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(path))


def joint_ids(model: mujoco.MjModel) -> list[int]:
    return [j for j in range(model.njnt) if int(model.jnt_type[j]) in MOVING_JOINTS]


def joint_name(model: mujoco.MjModel, j: int) -> str:
    return mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j)


@dataclass
class Drift:
    largest: dict[str, float]  # joint name -> largest |value| reached (rad or m)
    inside_limits: bool


def drift(model: mujoco.MjModel, seconds: float = 1.0) -> Drift:
    """Gravity off, no actuation, every joint at 0: how far the joints move in `seconds`."""
    model.opt.gravity[:] = 0.0
    data = mujoco.MjData(model)
    largest = {joint_name(model, j): 0.0 for j in joint_ids(model)}
    inside = True
    for _ in range(round(seconds / model.opt.timestep)):
        mujoco.mj_step(model, data)
        for j in joint_ids(model):
            q = float(data.qpos[model.jnt_qposadr[j]])
            lo, hi = model.jnt_range[j]
            name = joint_name(model, j)
            largest[name] = max(largest[name], abs(q))
            inside &= lo - 1e-6 <= q <= hi + 1e-6
    return Drift(largest, inside)


def with_position_actuators(path: Path, scratch: Path) -> mujoco.MjModel:
    """The model at `path` (MJCF or URDF) plus a critically damped position servo per joint,
    saved as `scratch` (beside `path`, so relative mesh paths still resolve)."""
    model = load(path)
    if path.suffix == ".urdf":  # MuJoCo's own MJCF of the URDF, to add the actuators to
        mujoco.mj_saveLastXML(str(scratch), model)
        path = scratch
    tree = ET.parse(path)
    actuators = ET.SubElement(tree.getroot(), "actuator")
    w = 2 * np.pi * DRIVE_HZ
    for j in joint_ids(model):
        inertia = float(model.dof_M0[model.jnt_dofadr[j]])
        ET.SubElement(actuators, "position", joint=joint_name(model, j),
                      kp=f"{inertia * w * w:.9g}", kv=f"{2 * inertia * w:.9g}")
    tree.write(scratch)
    return load(scratch)


def _colliding_geoms(model: mujoco.MjModel) -> tuple[list[int], list[int]]:
    """(geoms on bodies with a joint, geoms welded to the world), collision geoms only."""
    moving, static = [], []
    for g in range(model.ngeom):
        if not (model.geom_contype[g] or model.geom_conaffinity[g]):
            continue
        body = model.geom_bodyid[g]
        (static if model.body_weldid[body] == 0 else moving).append(g)
    return moving, static


@dataclass
class Drive:
    upper: list[float]  # joint values after the servo held the upper limits (actuator order)
    lower: list[float]  # and after it came back and held the lower limits
    limits: list[tuple[float, float]]
    deepest: float  # deepest moving-vs-static penetration seen on the way (>= 0)


def drive_through_range(model: mujoco.MjModel, ramp: float = 2.0, hold: float = 1.0,
                        every: int = 10) -> Drive:
    """Position servos move every joint from 0 to its upper limit over `ramp` s, hold it
    `hold` s, then go to the lower limit and hold it, gravity off; the penetration is measured
    every `every` steps."""
    model.opt.gravity[:] = 0.0
    data = mujoco.MjData(model)
    moving, static = _colliding_geoms(model)
    joints = [model.actuator_trnid[a, 0] for a in range(model.nu)]
    limits = [(float(model.jnt_range[j, 0]), float(model.jnt_range[j, 1])) for j in joints]
    fromto = np.zeros(6)
    deepest = 0.0
    steps = round((ramp + hold) / model.opt.timestep)
    reached = []
    start = np.zeros(model.nu)
    for side in (1, 0):  # upper, then lower
        goal = np.array([lim[side] for lim in limits])
        for k in range(steps):
            s = min(1.0, k * model.opt.timestep / ramp)
            data.ctrl[:] = start + s * (goal - start)
            mujoco.mj_step(model, data)
            if k % every == 0 or k == steps - 1:
                for g1 in moving:
                    for g2 in static:
                        d = mujoco.mj_geomDistance(model, data, g1, g2, 0.05, fromto)
                        deepest = max(deepest, -d)
        reached.append([float(data.qpos[model.jnt_qposadr[j]]) for j in joints])
        start = goal
    return Drive(reached[0], reached[1], limits, deepest)


def link_pose(model: mujoco.MjModel, body: str, values: dict[str, float]) -> np.ndarray:
    """4x4 world pose of `body` with the named joints at `values` (forward kinematics)."""
    data = mujoco.MjData(model)
    for name, value in values.items():
        data.qpos[model.jnt_qposadr[model.joint(name).id]] = value
    mujoco.mj_kinematics(model, data)
    out = np.eye(4)
    out[:3, :3] = data.body(body).xmat.reshape(3, 3)
    out[:3, 3] = data.body(body).xpos
    return out
