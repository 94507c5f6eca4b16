"""`gear export` on the hand-made toy run (tests/twin_outdir.py: box parts, so every number is
known): URDF and MJCF structure, link frames, convex pieces, inertials, limits, colours, GLBs,
part PLYs, the named state, and the bad-input cases."""

from __future__ import annotations

import json
import shutil
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import trimesh

from gear.cli import main
from gear.export import bundle
from gear.export.assembly import ExportOptions
from gear.export.bundle import MANIFEST, export_twin
from gear.export.urdf import roundtrip_errors
from gear.synth.urdf import load_urdf
from gear.twin import TwinError, read_ply_vertices
from twin_outdir import BOXES, COLORS, HINGE, SLIDE, joint_matrix, make_out_dir, start_points


@pytest.fixture(scope="module")
def out_dir(tmp_path_factory):
    return make_out_dir(tmp_path_factory.mktemp("run"))


@pytest.fixture(scope="module")
def exported(out_dir, tmp_path_factory):
    folder = tmp_path_factory.mktemp("export") / "toy"
    return export_twin(out_dir, folder, folder, name="toy", quiet=True)


def _floats(text: str) -> np.ndarray:
    return np.array([float(x) for x in text.split()])


def _box(k: int) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(BOXES[k][0]), np.asarray(BOXES[k][1])


FRAMES = {"base": np.zeros(3), "part_0": np.array(HINGE["origin"]),
          "part_1": np.array(SLIDE["origin"])}


def test_urdf_joints_limits_and_dynamics(exported):
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
        axis = np.asarray(want["axis"]) / np.linalg.norm(want["axis"])
        np.testing.assert_allclose(_floats(node.find("axis").get("xyz")), axis, atol=1e-9)
        upper = np.deg2rad(want["angle_deg"]) if want["type"] == "revolute" else want["distance"]
        limit = node.find("limit")
        assert float(limit.get("lower")) == 0.0
        assert float(limit.get("upper")) == pytest.approx(upper, abs=1e-8)
        dynamics = node.find("dynamics")
        assert float(dynamics.get("damping")) > 0 and float(dynamics.get("friction")) > 0
    assert roundtrip_errors(exported.urdf, exported.assembly) == []


def test_every_file_names_the_start_state(exported, out_dir):
    folder = exported.urdf.parent
    manifest = json.loads((folder / MANIFEST).read_text())
    assert manifest["state"] == "start"
    for model in (exported.urdf, exported.mjcf):
        assert "every link is in the START state" in model.read_text()
    assert sorted(manifest["files"]["glb"]) == ["end", "start"]
    assert all(p.startswith("splats/start/") for p in manifest["files"]["splats"])


def test_link_meshes_are_in_the_link_frame_with_one_file_per_convex_piece(exported, out_dir):
    root = ET.parse(exported.urdf).getroot()
    for k, link in enumerate(root.findall("link")):
        name = link.get("name")
        lo, hi = _box(k)
        collisions = link.findall("collision")
        assert len(collisions) == 1  # a box is convex: one piece, itself
        piece = trimesh.load(exported.urdf.parent / collisions[0].find("geometry/mesh")
                             .get("filename"), force="mesh")
        assert piece.is_convex
        if name == "base":  # cut back by the clearance where the door and drawer slide on it
            assert 0.97 * np.prod(hi - lo) <= piece.volume < np.prod(hi - lo)
            assert np.all(piece.bounds[0] >= lo - 1e-9) and np.all(piece.bounds[1] <= hi + 1e-9)
        else:  # moving parts keep their exact pieces
            assert piece.volume == pytest.approx(np.prod(hi - lo), rel=1e-6)
            np.testing.assert_allclose(piece.bounds + FRAMES[name], [lo, hi], atol=1e-9)
        visual = link.find("visual/geometry/mesh").get("filename")
        text = (exported.urdf.parent / visual).read_text()
        assert "\nvn " in text  # normals
        mesh = trimesh.load(exported.urdf.parent / visual, force="mesh")
        np.testing.assert_allclose(mesh.bounds + FRAMES[name], [lo, hi], atol=1e-9)


def test_visual_colours_come_from_the_gaussians(exported):
    for k, link in enumerate(exported.assembly.links):
        colors = link.visual.visual.vertex_colors[:, :3] / 255.0
        # The toy's Gaussians are their part's colour +- 0.05.
        assert np.abs(colors - COLORS[k]).max() < 0.06
        np.testing.assert_allclose(link.rgba[:3], COLORS[k], atol=0.06)


def test_inertia_of_a_box_link_at_the_default_density(exported):
    from gear.export import defaults

    drawer = ET.parse(exported.urdf).getroot().find("link[@name='part_1']/inertial")
    lo, hi = _box(2)
    a, b, c = hi - lo
    mass = defaults.DENSITY * a * b * c
    assert float(drawer.find("mass").get("value")) == pytest.approx(mass, rel=1e-6)
    np.testing.assert_allclose(_floats(drawer.find("origin").get("xyz")),
                               (lo + hi) / 2 - FRAMES["part_1"], atol=1e-9)
    inertia = drawer.find("inertia")
    want = {"ixx": mass * (b * b + c * c) / 12, "iyy": mass * (a * a + c * c) / 12,
            "izz": mass * (a * a + b * b) / 12, "ixy": 0.0, "ixz": 0.0, "iyz": 0.0}
    for key, value in want.items():
        assert float(inertia.get(key)) == pytest.approx(value, rel=1e-6, abs=1e-9)


def test_static_pieces_are_cut_back_where_the_parts_move(exported):
    """The toy's door stands on the top face of the static box and its drawer slides along the
    bottom face: the static piece loses a clearance-thin slice there, nothing else."""
    from gear.export.assembly import CLEARANCE

    base = exported.assembly.links[0].pieces[0]
    lo, hi = _box(0)
    size = np.linalg.norm(np.ptp(np.concatenate([_box(k) for k in range(3)]), axis=0))
    gap = CLEARANCE * size
    shift = np.array([0.0, 0.0, gap])
    np.testing.assert_allclose(base.bounds, [lo + shift, hi - shift], atol=1e-9)
    assert any("plane cut(s)" in note for note in exported.notes)


def test_total_mass_is_spread_by_volume_and_limits_widen(out_dir, tmp_path):
    result = export_twin(out_dir, tmp_path / "u", options=ExportOptions(mass=30.0, widen=0.1),
                         quiet=True)
    volumes = np.array([link.inertial.volume for link in result.assembly.links])
    masses = np.array([link.inertial.mass for link in result.assembly.links])
    np.testing.assert_allclose(masses, 30.0 * volumes / volumes.sum(), rtol=1e-9)
    assert masses.sum() == pytest.approx(30.0)
    np.testing.assert_allclose(volumes[1:], [np.prod(np.subtract(hi, lo)) for lo, hi in BOXES[1:]],
                               rtol=1e-6)
    hinge = result.assembly.joints[0]
    full = np.deg2rad(HINGE["angle_deg"])
    assert (hinge.lower, hinge.upper, hinge.end) == pytest.approx((-0.1 * full, 1.1 * full, full))


def test_mjcf_bodies_joints_and_excluded_parent_contacts(exported):
    root = ET.parse(exported.mjcf).getroot()
    base = root.find("worldbody/body")
    assert base.get("name") == "base" and base.find("joint") is None  # welded to the world
    children = base.findall("body")
    assert [c.get("name") for c in children] == ["part_0", "part_1"]
    for child, want in zip(children, (HINGE, SLIDE), strict=True):
        np.testing.assert_allclose(_floats(child.get("pos")), want["origin"], atol=1e-9)
        joint = child.find("joint")
        assert joint.get("type") == ("hinge" if want["type"] == "revolute" else "slide")
        assert joint.get("limited") == "true"
        collisions = [g for g in child.findall("geom") if g.get("class") == "collision"]
        assert len(collisions) == 1
    excluded = {(e.get("body1"), e.get("body2")) for e in root.findall("contact/exclude")}
    assert excluded == {("base", "part_0"), ("base", "part_1")}


def test_glb_per_state_with_colours(exported, out_dir):
    folder = exported.urdf.parent
    for state, fraction in (("start", 0.0), ("end", 1.0)):
        scene = trimesh.load(folder / f"toy_{state}.glb")
        assert set(scene.geometry) == {"base", "part_0", "part_1"}
        door = scene.dump(concatenate=False)
        door = next(g for g in door if g.metadata.get("name") == "part_0")
        lo, hi = _box(1)
        corners = trimesh.creation.box(extents=hi - lo)
        corners.apply_translation((lo + hi) / 2)
        corners.apply_transform(joint_matrix(HINGE, fraction))
        np.testing.assert_allclose(door.bounds, corners.bounds, atol=1e-6)
        colors = door.visual.vertex_colors[:, :3] / 255.0
        assert np.abs(colors - COLORS[1]).max() < 0.06


def test_one_gaussian_ply_per_part_in_the_start_state(exported):
    points, parts = start_points()
    for k, name in enumerate(["base", "part_0", "part_1"]):
        props = read_ply_vertices(exported.urdf.parent / "splats" / "start" / f"{name}.ply")
        xyz = np.stack([props["x"], props["y"], props["z"]], axis=1)
        np.testing.assert_allclose(np.sort(xyz, 0), np.sort(points[parts == k], 0), atol=1e-5)
        assert {"f_dc_0", "opacity", "scale_0", "rot_0"} <= set(props)


def test_canonical_end_run_exports_the_same_start_state(out_dir, tmp_path):
    run = make_out_dir(tmp_path / "run", canonical="end")
    result = export_twin(run, tmp_path / "u", quiet=True)
    props = read_ply_vertices(tmp_path / "u" / "splats" / "start" / "part_0.ply")
    points, parts = start_points()
    xyz = np.stack([props["x"], props["y"], props["z"]], axis=1)
    np.testing.assert_allclose(np.sort(xyz, 0), np.sort(points[parts == 1], 0), atol=1e-5)
    assert "end state" in json.loads((tmp_path / "u" / MANIFEST).read_text())["state_note"]
    assert result.assembly.state == "start"


def test_visual_face_budget(out_dir, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(out_dir, run)
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.1)  # 5120 faces
    sphere.apply_translation([0.0, 0.0, -0.05])
    sphere.export(run / "meshes" / "start" / "static.ply")
    result = export_twin(run, tmp_path / "u", options=ExportOptions(faces=500), quiet=True)
    visual = result.assembly.links[0].visual
    assert 250 <= len(visual.faces) <= 500
    # Simplified, still the same sphere: every vertex within 5 mm of the radius.
    radii = np.linalg.norm(visual.vertices - [0.0, 0.0, -0.05], axis=1)
    assert np.abs(radii - 0.1).max() < 5e-3


def test_negative_angle_flips_the_axis_and_keeps_the_motion(out_dir, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(out_dir, run)
    flipped = {**HINGE, "axis": [0.0, 0.0, -1.0], "angle_deg": -70.0}
    (run / "joints.json").write_text(json.dumps({"canonical": "start",
                                                 "joints": [flipped, SLIDE]}))
    result = export_twin(run, tmp_path / "u", quiet=True)
    joint = result.assembly.joints[0]
    assert joint.upper == pytest.approx(np.deg2rad(70.0))
    np.testing.assert_allclose(joint.axis, [0.0, 0.0, 1.0])
    part = load_urdf(result.urdf, end={"joint_0": joint.upper}).parts[0]
    np.testing.assert_allclose(part.joint.pose(joint.upper), joint_matrix(flipped, 1.0),
                               atol=1e-9)


def test_end_state_meshes_are_moved_back_to_start(out_dir, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(out_dir, run)
    shutil.rmtree(run / "meshes" / "start")
    result = export_twin(run, tmp_path / "u", quiet=True)
    assert sum("moved back to the start state" in n for n in result.notes) == 3
    lo, hi = _box(1)
    np.testing.assert_allclose(result.assembly.links[1].visual.bounds, [lo, hi], atol=1e-6)


def test_missing_run_files_are_named(out_dir, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(out_dir, run)
    for state in ("start", "end"):
        (run / "meshes" / state / "part_1.ply").unlink()
    with pytest.raises(TwinError, match=r"meshes/start/part_1\.ply: missing"):
        export_twin(run, tmp_path / "u", quiet=True)
    (run / "gaussians_canonical.ply").unlink()
    with pytest.raises(TwinError, match=r"gaussians_canonical\.ply: missing"):
        export_twin(run, tmp_path / "u", quiet=True)
    (run / "joints.json").unlink()
    with pytest.raises(TwinError, match=r"joints\.json: missing"):
        export_twin(run, tmp_path / "u", quiet=True)
    assert not (tmp_path / "u").exists()


def test_output_folder_problems_are_one_line_errors(out_dir, tmp_path, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    assert main(["export", str(out_dir), "--urdf", str(blocker / "u")]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("gear: error: ") and "cannot write the output folder" in err
    assert len(err.splitlines()) == 1
    assert main(["export", str(out_dir), "--mjcf", str(blocker)]) == 1
    assert "exists and is not a folder" in capsys.readouterr().err
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    assert main(["export", str(out_dir), "--urdf", str(other)]) == 1
    assert "not empty (and is not a gear export)" in capsys.readouterr().err
    assert main(["export", str(out_dir)]) == 1
    assert "give --urdf DIR and/or --mjcf DIR" in capsys.readouterr().err
    assert main(["export", str(out_dir), "--urdf", str(tmp_path / "v"), "--density", "-1"]) == 1
    assert "--density must be a positive number" in capsys.readouterr().err


def test_a_failed_export_leaves_the_previous_one_untouched(exported, out_dir, tmp_path,
                                                           monkeypatch):
    folder = tmp_path / "u"
    shutil.copytree(exported.urdf.parent, folder)
    before = sorted(p.relative_to(folder) for p in folder.rglob("*"))

    def broken(*_args: object) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(bundle, "write_glb", broken)
    with pytest.raises(OSError, match="disk full"):
        export_twin(out_dir, folder, name="toy", quiet=True)
    assert sorted(p.relative_to(folder) for p in folder.rglob("*")) == before
    assert [p.name for p in tmp_path.iterdir()] == ["u"]  # no temporary folder left behind


def test_export_command_reports_masses_state_and_round_trip(out_dir, tmp_path, capsys):
    assert main(["export", str(out_dir), "--urdf", str(tmp_path / "u"), "--mjcf",
                 str(tmp_path / "m"), "--name", "toy", "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "every file holds the twin in its start state" in printed
    assert "round-trip check: gear's URDF reader gives the same joints" in printed
    assert (tmp_path / "u" / "toy.urdf").is_file() and (tmp_path / "m" / "toy.xml").is_file()
    assert not (tmp_path / "u" / "toy.xml").exists()


def test_a_part_with_an_empty_mesh_gets_a_light_link_without_geometry(out_dir, tmp_path):
    mujoco = pytest.importorskip("mujoco")
    run = tmp_path / "run"
    shutil.copytree(out_dir, run)
    trimesh.Trimesh().export(run / "meshes" / "start" / "part_1.ply")
    folder = tmp_path / "u"
    result = export_twin(run, folder, folder, name="toy", quiet=True)
    drawer = result.assembly.links[2]
    assert drawer.visual is None and drawer.pieces == [] and drawer.inertial.mass == 1e-3
    assert any("part_1: its mesh is empty" in note for note in result.notes)
    assert ET.parse(result.urdf).getroot().find("link[@name='part_1']/collision") is None
    model = mujoco.MjModel.from_xml_path(str(result.mjcf))  # a massless body would be refused
    assert model.body("part_1").mass[0] == pytest.approx(1e-3)
