"""URDF import: a small URDF written here, and the real PartNet-Mobility assets (skipped when
they are absent; see gear.bench.accuracy.real.assets_dir for where they are looked for)."""

import numpy as np
import pytest
from PIL import Image

from gear.bench.accuracy.real import assets_dir
from gear.cli import main
from gear.data import load_scene, validate_scene
from gear.synth import render_scene
from gear.synth.urdf import load_urdf

ASSETS = assets_dir()
REAL = {  # folder -> moving parts with the default states (limits lower -> upper)
    "cabinet_upper_46108": 4,
    "kitchen_counter_26608": 8,
    "microwave_7128": 2,  # door + push button; the continuous knobs stay put
    "scissors_10495": 1,
}

URDF = """<?xml version="1.0"?>
<robot name="test_cabinet">
  <material name="blue"><color rgba="0.1 0.2 0.8 1"/></material>
  <link name="base">
    <visual><origin xyz="0 0 0.5"/><geometry><box size="1 0.6 1"/></geometry>
      <material name="blue"/></visual>
  </link>
  <link name="nothing"/>
  <link name="door">
    <visual><origin xyz="0.25 0 0" rpy="1.5707963 0 0"/>
      <geometry><mesh filename="meshes/panel.obj"/></geometry></visual>
    <visual><origin xyz="0.45 -0.03 0"/>
      <geometry><cylinder radius="0.02" length="0.1"/></geometry></visual>
  </link>
  <link name="knob"><visual><geometry><sphere radius="0.03"/></geometry></visual></link>
  <link name="drawer">
    <visual><geometry><box size="0.4 0.5 0.2"/></geometry></visual>
  </link>
  <link name="pull"><visual><geometry><box size="0.2 0.02 0.02"/></geometry></visual></link>
  <joint name="j_nothing" type="fixed"><parent link="base"/><child link="nothing"/></joint>
  <joint name="j_door" type="revolute">
    <origin xyz="-0.5 -0.31 0.5"/><axis xyz="0 0 -1"/>
    <parent link="base"/><child link="door"/><limit lower="0" upper="1.6"/>
  </joint>
  <joint name="j_knob" type="continuous">
    <origin xyz="0.3 -0.05 0.2"/><axis xyz="0 1 0"/><parent link="door"/><child link="knob"/>
  </joint>
  <joint name="j_drawer" type="prismatic">
    <origin xyz="0 -0.05 1.1"/><axis xyz="0 -2 0"/>
    <parent link="base"/><child link="drawer"/><limit lower="0" upper="0.3"/>
  </joint>
  <joint name="j_pull" type="fixed">
    <origin xyz="0 -0.26 0"/><parent link="drawer"/><child link="pull"/>
  </joint>
</robot>
"""

OBJ = """mtllib panel.mtl
v -0.25 -0.5 0
v 0.25 -0.5 0
v 0.25 0.5 0
v -0.25 0.5 0
vt 0 0
vt 1 0
vt 1 1
vt 0 1
usemtl checker
f 1/1 2/2 3/3
f 1/1 3/3 4/4
"""

MTL = """newmtl checker
Kd 1 1 1
map_Kd ../textures/checker.png
"""


@pytest.fixture
def urdf(tmp_path):
    (tmp_path / "meshes").mkdir()
    (tmp_path / "textures").mkdir()
    (tmp_path / "meshes" / "panel.obj").write_text(OBJ)
    (tmp_path / "meshes" / "panel.mtl").write_text(MTL)
    checker = np.zeros((8, 8, 3), np.uint8)
    checker[:4, :4] = checker[4:, 4:] = [230, 20, 20]
    checker[:4, 4:] = checker[4:, :4] = [20, 230, 20]
    Image.fromarray(checker).resize((64, 64), Image.NEAREST).save(
        tmp_path / "textures" / "checker.png"
    )
    path = tmp_path / "test.urdf"
    path.write_text(URDF)
    return path


def test_small_urdf_parts_and_joints(urdf):
    obj = load_urdf(urdf)
    # Two moving joints by default (limits lower -> upper); the continuous knob stays at 0
    # and merges into the door; the fixed pull merges into the drawer.
    names = [p.joint.name for p in obj.parts]
    assert names == ["j_door", "j_drawer"]  # trans_info follows the URDF's joint order
    door = next(p for p in obj.parts if p.joint.name == "j_door")
    drawer = next(p for p in obj.parts if p.joint.name == "j_drawer")
    assert len(door.surfaces) == 3 and len(drawer.surfaces) == 2 and len(obj.static) == 1
    np.testing.assert_allclose(door.joint.origin, [-0.5, -0.31, 0.5])
    np.testing.assert_allclose(door.joint.axis, [0, 0, -1])
    assert (door.joint.start, door.joint.end) == (0.0, 1.6)
    np.testing.assert_allclose(drawer.joint.axis, [0, -1, 0])  # normalised
    gt = drawer.joint.gt()
    assert gt.type == "prismatic" and gt.amount == pytest.approx(0.3)
    # The rpy-rotated door panel stands upright in the plane y = -0.31.
    panel = door.surfaces[0]
    np.testing.assert_allclose(panel.vertices[:, 1], -0.31, atol=1e-6)
    assert np.ptp(panel.vertices[:, 2]) == pytest.approx(1.0, abs=1e-6)
    assert panel.texture is not None and panel.uv.shape == (2, 3, 2)


def test_small_urdf_scene(urdf, tmp_path):
    root = render_scene(
        load_urdf(urdf, start={"j_door": 0.2}, end={"j_door": 1.2}),
        tmp_path / "scene",
        res=48,
        views=6,
        test_views=0,
    )
    assert validate_scene(root) == []
    scene = load_scene(root)
    assert [j.type for j in scene.gt.joints] == ["revolute", "prismatic"]
    assert scene.gt.joints[0].amount == pytest.approx(np.rad2deg(1.0))
    rgb = np.concatenate([v.rgb[v.parts == 1] for v in scene.all_views()])
    # The door's checker texture shows both of its colours.
    assert ((rgb[:, 0] > 2 * rgb[:, 1]) & (rgb[:, 0] > 0.2)).any()
    assert ((rgb[:, 1] > 2 * rgb[:, 0]) & (rgb[:, 1] > 0.2)).any()


def test_urdf_errors(urdf, tmp_path):
    with pytest.raises(ValueError, match="j_knob moves and so does its ancestor joint j_door"):
        load_urdf(urdf, end={"j_knob": 0.5})
    with pytest.raises(ValueError, match="no movable joint named"):
        load_urdf(urdf, start={"j_pull": 0.1})
    with pytest.raises(ValueError, match="outside its limits"):
        load_urdf(urdf, end={"j_door": 3.0})
    bad = tmp_path / "bad.urdf"
    bad.write_text(URDF.replace("meshes/panel.obj", "meshes/missing.obj"))
    with pytest.raises(ValueError, match=r"missing\.obj is missing"):
        load_urdf(bad)
    bad.write_text("<robot><link name='a'>")
    with pytest.raises(ValueError, match="not a readable URDF"):
        load_urdf(bad)


def test_urdf_cli(urdf, tmp_path):
    out = tmp_path / "cli"
    args = ["synth", "--urdf", str(urdf), "--out", str(out), "--res", "32", "--views", "2",
            "--test-views", "0", "--start", "j_drawer=0.1", "--end", "j_drawer=0.1"]
    assert main(args) == 0
    assert len(load_scene(out).gt.joints) == 1  # the drawer no longer moves
    assert main([*args[:-2], "--end", "j_drawer=oops"]) == 1
    assert main(["synth", "fridge", "--out", str(out), "--start", "a=1"]) == 1


@pytest.mark.skipif(not ASSETS.is_dir(), reason="PartNet-Mobility assets not available")
@pytest.mark.parametrize("folder", sorted(REAL))
def test_real_assets_render_valid_scenes(folder, tmp_path):
    obj = load_urdf(ASSETS / folder / "mobility.urdf")
    assert len(obj.parts) == REAL[folder]
    root = render_scene(obj, tmp_path / folder, res=40, views=3, test_views=0)
    assert validate_scene(root) == []
    scene = load_scene(root)
    for v in scene.all_views():
        obj_px = v.alpha > 0
        np.testing.assert_array_equal(v.depth > 0, obj_px)
        np.testing.assert_array_equal(v.parts != 255, obj_px)
    assert len(scene.gt.joints) == REAL[folder]
