"""Exported twins in a physics engine and a URDF library: yourdfpy loads and validates the URDF,
MuJoCo loads the MJCF and the URDF; left alone with gravity off the joints stay put; position
servos drive each joint to its limits without the moving link sinking into the static body; and
the forward kinematics at the upper limit lands the part on the run's end-state mesh.

On twins built from the ground truth of built-in objects (exact geometry) and on a twin trained
by the quick profile on a built-in scene."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

from gear import _core
from gear.export.assembly import ExportOptions
from gear.export.bundle import ExportResult, export_twin
from gear.metrics import chamfer_points, sample_surface
from twin_outdir import make_gt_out_dir

mujoco = pytest.importorskip("mujoco")
yourdfpy = pytest.importorskip("yourdfpy")
import mujoco_checks as mc  # noqa: E402 (needs mujoco, skipped above without it)

DRIFT_RAD, DRIFT_M = 0.01, 1e-3
MAX_PENETRATION = 5e-3  # m
SAMPLES = 4000


def _export(run: Path, folder: Path, name: str, **options: float) -> ExportResult:
    return export_twin(run, folder, folder, name=name, options=ExportOptions(**options),
                       quiet=True)


@pytest.fixture(scope="module", params=["fridge", "drawer_cabinet"])
def gt_export(request, tmp_path_factory) -> tuple[Path, ExportResult]:
    root = tmp_path_factory.mktemp(request.param)
    run = make_gt_out_dir(root / "run", request.param)
    # Widened limits: the servo then also drives each part past its observed start.
    return run, _export(run, root / "export", request.param, widen=0.1)


def _check_urdf_library(result: ExportResult) -> None:
    robot = yourdfpy.URDF.load(str(result.urdf), mesh_dir=str(result.urdf.parent))
    assert robot.validate()
    assert sorted(robot.actuated_joint_names) == [j.name for j in result.assembly.joints]
    for link in robot.robot.links:
        for element in link.visuals + link.collisions:
            path = result.urdf.parent / element.geometry.mesh.filename
            assert path.is_file(), path
            mesh = trimesh.load(path, force="mesh")
            assert len(mesh.faces) > 0 and np.all(np.isfinite(mesh.vertices))
    for joint in result.assembly.joints:
        limit = robot.joint_map[joint.name].limit
        assert (limit.lower, limit.upper) == pytest.approx((joint.lower, joint.upper))


def _check_physics(result: ExportResult, scratch: Path) -> None:
    """Drift and drive checks on the MJCF and on the URDF."""
    for path in (result.mjcf, result.urdf):
        model = mc.load(path)
        assert model.nu == 0 and len(mc.joint_ids(model)) == len(result.assembly.joints)
        drift = mc.drift(model)
        assert drift.inside_limits, (path.name, drift)
        for joint in result.assembly.joints:
            bound = DRIFT_RAD if joint.type == "revolute" else DRIFT_M
            assert drift.largest[joint.name] <= bound, (path.name, drift)
        drive = mc.drive_through_range(mc.with_position_actuators(path, scratch))
        for k, joint in enumerate(result.assembly.joints):
            tol = 0.02 * (joint.upper - joint.lower)
            # MuJoCo's saved XML of a URDF keeps 6 significant digits.
            assert drive.limits[k] == pytest.approx((joint.lower, joint.upper), abs=1e-5)
            assert abs(drive.upper[k] - joint.upper) <= tol, (path.name, joint.name, drive)
            assert abs(drive.lower[k] - joint.lower) <= tol, (path.name, joint.name, drive)
        assert drive.deepest <= MAX_PENETRATION, (path.name, drive.deepest)


def _sampling_floor(mesh: trimesh.Trimesh) -> float:
    """Chamfer between two independent samplings of the same mesh: what any match can reach."""
    return chamfer_points(sample_surface(mesh, SAMPLES, 0), sample_surface(mesh, SAMPLES, 1))


def _fk_chamfers(run: Path, result: ExportResult) -> list[tuple[float, float]]:
    """(chamfer, sampling floor) per moving link: its exported visual mesh posed by MuJoCo's
    forward kinematics at the observed end value (the upper limit unless widened), against the
    run's meshes/end/part_i.ply."""
    model = mc.load(result.mjcf)
    folder = result.mjcf.parent
    out = []
    for joint in result.assembly.joints:
        pose = mc.link_pose(model, joint.child, {joint.name: joint.end})
        mesh = trimesh.load(folder / "meshes" / "visual" / f"{joint.child}.obj", force="mesh")
        mesh.apply_transform(pose)
        end = trimesh.load(run / "meshes" / "end" / f"{joint.child}.ply", force="mesh")
        got = chamfer_points(sample_surface(mesh, SAMPLES, 2), sample_surface(end, SAMPLES, 3))
        out.append((got, _sampling_floor(end)))
    return out


def test_gt_twin_loads_in_yourdfpy_with_every_mesh(gt_export):
    _check_urdf_library(gt_export[1])


def test_gt_twin_holds_still_and_drives_to_its_limits_without_sinking(gt_export):
    _check_physics(gt_export[1], gt_export[1].mjcf.parent / "_servo.xml")


def test_gt_twin_forward_kinematics_lands_on_the_end_meshes(gt_export):
    run, result = gt_export
    for got, floor in _fk_chamfers(run, result):
        assert got <= 1.5 * floor, (got, floor)


def test_gt_twin_masses_are_those_of_everyday_furniture(gt_export):
    total = sum(link.inertial.mass for link in gt_export[1].assembly.links)
    assert 10.0 <= total <= 150.0, total  # kg: a fridge or a drawer cabinet, not a tonne
    assert all(link.inertial.mass > 0 for link in gt_export[1].assembly.links)


GPU_RASTERIZER = hasattr(_core, "rasterize_forward")


@pytest.mark.skipif(not GPU_RASTERIZER, reason="needs the GPU rasterizer in gear._core")
def test_trained_twin_is_simulation_ready(tmp_path):
    from gear.config import make_config
    from gear.synth import generate
    from gear.train import train

    scene = generate("fridge", tmp_path / "scene", res=64, views=16, test_views=2, seed=0)
    run = tmp_path / "run"
    train(scene, run, make_config("quick"), quiet=True)
    # A coarser decomposition than the default keeps the test short; the checks are the same.
    result = _export(run, tmp_path / "export", "fridge", concavity=0.1, max_pieces=12)
    _check_urdf_library(result)
    _check_physics(result, result.mjcf.parent / "_servo.xml")
    for got, floor in _fk_chamfers(run, result):
        # Trained meshes are fused separately per state, so the start-state mesh carried to
        # the end differs from the end-state one by the reconstruction's own noise.
        assert got <= 3.0 * floor, (got, floor)
    # Coarser pieces fill more of the hollow body, so this export weighs more than a default
    # one (about 110 kg); a tonne, as hulls gave, would fail.
    masses = [link.inertial.mass for link in result.assembly.links]
    assert math.isfinite(sum(masses)) and 10.0 <= sum(masses) <= 250.0
