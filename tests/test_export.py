"""URDF export of a trained twin: the file's joints, links and meshes, and the round trip
through gear's own URDF reader."""

from __future__ import annotations

import json
import shutil
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import trimesh

from gear.cli import main
from gear.export import export_urdf, roundtrip_errors
from gear.synth.urdf import load_urdf
from gear.twin import TwinError
from twin_outdir import BOXES, HINGE, SLIDE, joint_matrix, make_out_dir


@pytest.fixture(scope="module")
def out_dir(tmp_path_factory):
    return make_out_dir(tmp_path_factory.mktemp("run"))


@pytest.fixture(scope="module")
def exported(out_dir, tmp_path_factory):
    return export_urdf(out_dir, tmp_path_factory.mktemp("urdf"), name="toy")


def _floats(text: str) -> np.ndarray:
    return np.array([float(x) for x in text.split()])


def _start_vertices(out_dir, name):
    return trimesh.load(out_dir / "meshes" / "start" / f"{name}.ply", process=False).vertices


def test_urdf_joints_links_and_limits(exported, out_dir):
    root = ET.parse(exported.urdf).getroot()
    assert root.tag == "robot" and root.get("name") == "toy"
    assert [link.get("name") for link in root.findall("link")] == ["base", "part_0", "part_1"]
    joints = root.findall("joint")
    assert [(j.get("name"), j.get("type")) for j in joints] == [
        ("joint_0", "revolute"), ("joint_1", "prismatic")]
    for node, want in zip(joints, (HINGE, SLIDE), strict=True):
        assert node.find("parent").get("link") == "base"
        np.testing.assert_allclose(_floats(node.find("origin").get("xyz")), want["origin"],
                                   atol=1e-9)
        np.testing.assert_allclose(_floats(node.find("origin").get("rpy")), 0.0)
        axis = np.asarray(want["axis"]) / np.linalg.norm(want["axis"])
        np.testing.assert_allclose(_floats(node.find("axis").get("xyz")), axis, atol=1e-9)
        limit = node.find("limit")
        upper = np.deg2rad(want["angle_deg"]) if want["type"] == "revolute" else want["distance"]
        assert float(limit.get("lower")) == 0.0
        assert float(limit.get("upper")) == pytest.approx(upper, abs=1e-8)
        assert float(limit.get("effort")) > 0 and float(limit.get("velocity")) > 0


def test_link_meshes_are_obj_in_the_joint_frame(exported, out_dir):
    root = ET.parse(exported.urdf).getroot()
    frames = {"base": np.zeros(3), "part_0": np.array(HINGE["origin"]),
              "part_1": np.array(SLIDE["origin"])}
    for link in root.findall("link"):
        name = link.get("name")
        for tag in ("visual", "collision"):
            node = link.find(tag)
            filename = node.find("geometry/mesh").get("filename")
            assert filename.endswith(".obj")
            mesh = trimesh.load(exported.urdf.parent / filename, force="mesh", process=False)
            shift = _floats(node.find("origin").get("xyz"))
            np.testing.assert_allclose(shift, -frames[name], atol=1e-9)
            # Link frame + visual origin puts the mesh back where the start-state mesh is.
            want = _start_vertices(out_dir, "static" if name == "base" else name)
            got = mesh.vertices + shift + frames[name]
            np.testing.assert_allclose(np.sort(got, axis=0), np.sort(want, axis=0), atol=1e-6)


def test_inertia_of_a_box_link(exported):
    base = ET.parse(exported.urdf).getroot().find("link[@name='base']/inertial")
    lo, hi = np.asarray(BOXES[0][0]), np.asarray(BOXES[0][1])
    a, b, c = hi - lo
    mass = 1000.0 * a * b * c  # default density
    assert float(base.find("mass").get("value")) == pytest.approx(mass, rel=1e-6)
    np.testing.assert_allclose(_floats(base.find("origin").get("xyz")), (lo + hi) / 2, atol=1e-9)
    inertia = base.find("inertia")
    want = {"ixx": mass * (b * b + c * c) / 12, "iyy": mass * (a * a + c * c) / 12,
            "izz": mass * (a * a + b * b) / 12, "ixy": 0.0, "ixz": 0.0, "iyz": 0.0}
    for key, value in want.items():
        assert float(inertia.get(key)) == pytest.approx(value, rel=1e-6, abs=1e-9)


def test_gear_urdf_reader_gives_the_same_joints_and_geometry(exported, out_dir):
    obj = load_urdf(exported.urdf)
    assert len(obj.parts) == 2
    for part, want in zip(obj.parts, (HINGE, SLIDE), strict=True):
        gt = part.joint.gt()
        assert gt.type == want["type"]
        np.testing.assert_allclose(gt.axis, np.asarray(want["axis"]) / np.linalg.norm(
            want["axis"]), atol=1e-9)
        np.testing.assert_allclose(gt.origin, want["origin"], atol=1e-9)
        amount = want["angle_deg"] if want["type"] == "revolute" else want["distance"]
        assert gt.amount == pytest.approx(amount, abs=1e-6)
        assert gt.start == 0.0
    # Read-back geometry: the start state as exported, and the reader's end pose of each part
    # lands on the trained end-state mesh.
    for k, (part, joint) in enumerate(zip(obj.parts, (HINGE, SLIDE), strict=True)):
        verts = np.concatenate([s.vertices for s in part.surfaces])
        np.testing.assert_allclose(np.sort(verts, 0),
                                   np.sort(_start_vertices(out_dir, f"part_{k}"), 0), atol=1e-6)
        end = part.joint.pose(part.joint.end)
        moved = verts @ end[:3, :3].T + end[:3, 3]
        want_end = trimesh.load(out_dir / "meshes" / "end" / f"part_{k}.ply").vertices
        ref = joint_matrix(joint, 1.0)
        np.testing.assert_allclose(moved, verts @ ref[:3, :3].T + ref[:3, 3], atol=1e-6)
        np.testing.assert_allclose(np.sort(moved, 0), np.sort(want_end, 0), atol=1e-6)
    assert roundtrip_errors(exported) == []


def test_negative_angle_flips_the_axis_and_keeps_the_motion(out_dir, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(out_dir, run)
    flipped = {**HINGE, "axis": [0.0, 0.0, -1.0], "angle_deg": -70.0}
    (run / "joints.json").write_text(json.dumps({"canonical": "start",
                                                 "joints": [flipped, SLIDE]}))
    result = export_urdf(run, tmp_path / "urdf")
    assert result.joints[0].amount == pytest.approx(70.0)
    np.testing.assert_allclose(result.joints[0].axis, [0.0, 0.0, 1.0])
    gt = load_urdf(result.urdf).parts[0].joint.gt()
    np.testing.assert_allclose(gt.motion(1.0), joint_matrix(flipped, 1.0), atol=1e-9)
    assert roundtrip_errors(result) == []


def test_end_state_meshes_are_moved_back_to_start(out_dir, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(out_dir, run)
    shutil.rmtree(run / "meshes" / "start")
    result = export_urdf(run, tmp_path / "urdf")
    assert sum("moved back to the start state" in n for n in result.notes) == 3
    part = load_urdf(result.urdf).parts[0]
    verts = np.concatenate([s.vertices for s in part.surfaces])
    np.testing.assert_allclose(np.sort(verts, 0), np.sort(_start_vertices(out_dir, "part_0"), 0),
                               atol=1e-6)


def test_missing_meshes_and_joints_are_named(out_dir, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(out_dir, run)
    for state in ("start", "end"):
        (run / "meshes" / state / "part_1.ply").unlink()
    with pytest.raises(TwinError, match=r"meshes/start/part_1\.ply: missing"):
        export_urdf(run, tmp_path / "urdf")
    (run / "joints.json").unlink()
    with pytest.raises(TwinError, match=r"joints\.json: missing"):
        export_urdf(run, tmp_path / "urdf")


def test_export_command_reports_the_round_trip(out_dir, tmp_path, capsys):
    assert main(["export", str(out_dir), "--urdf", str(tmp_path / "u"), "--name", "toy"]) == 0
    printed = capsys.readouterr().out
    assert "round-trip check: gear's URDF reader gives the same joints" in printed
    assert (tmp_path / "u" / "toy.urdf").is_file()
    assert main(["export", str(out_dir), "--urdf", str(tmp_path / "v"), "--density", "-1"]) == 1
    assert "density must be a positive number" in capsys.readouterr().err
