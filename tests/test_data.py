"""Scene loader, writer and validation (every problem class triggered by a broken scene)."""

import json
import shutil

import numpy as np
import pytest
from PIL import Image

from gear.cli import main
from gear.data import GtJoint, SceneError, load_scene, validate_scene, write_scene
from gear.synth import generate


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    return generate(
        "double_door", tmp_path_factory.mktemp("scene") / "s", res=40, views=4, test_views=2
    )


@pytest.fixture
def broken(scene_dir, tmp_path):
    """A fresh copy of the valid scene to break."""
    return shutil.copytree(scene_dir, tmp_path / "broken")


def test_load_generated_scene(scene_dir):
    scene = load_scene(scene_dir)
    assert [len(scene.train(s)) for s in ("start", "end")] == [4, 4]
    assert [len(scene.test(s)) for s in ("start", "end")] == [2, 2]
    assert scene.has_depth and scene.has_regions and scene.has_parts
    v = scene.train("end")[1]
    assert v.name == "end/train/0001" and v.state == "end"
    assert v.rgb.shape == (40, 40, 3) and v.rgb.dtype == np.float32
    assert v.alpha.shape == (40, 40) and set(np.unique(v.alpha)) <= {0.0, 1.0}
    assert v.depth.dtype == np.float32 and v.regions.dtype == np.int32 and v.parts.dtype == np.uint8
    assert len(scene.gt.joints) == 2 and all(j.type == "revolute" for j in scene.gt.joints)
    assert set(scene.gt.meshes["start"]) == {"whole", "static", "part_0", "part_1"}
    # Training-only loading skips the test split.
    assert load_scene(scene_dir, splits=("train",)).test("start") == []


def test_round_trip(scene_dir, tmp_path):
    scene = load_scene(scene_dir)
    write_scene(tmp_path / "copy", scene.views, joints=scene.gt.joints)
    again = load_scene(tmp_path / "copy")
    for a, b in zip(scene.all_views(), again.all_views(), strict=True):
        assert a.name == b.name
        np.testing.assert_array_equal(a.rgb, b.rgb)
        np.testing.assert_array_equal(a.alpha, b.alpha)
        np.testing.assert_array_equal(a.depth, b.depth)
        np.testing.assert_array_equal(a.regions, b.regions)
        np.testing.assert_array_equal(a.parts, b.parts)
        np.testing.assert_allclose(a.camera.world_to_cam, b.camera.world_to_cam, atol=1e-12)
        assert a.camera.fx == pytest.approx(b.camera.fx, rel=1e-12)
    for ja, jb in zip(scene.gt.joints, again.gt.joints, strict=True):
        np.testing.assert_allclose(ja.origin, jb.origin)
        np.testing.assert_allclose(ja.axis, jb.axis)
        assert (ja.type, ja.amount, ja.start) == (jb.type, jb.amount, jb.start)


def test_trans_json_semantics(tmp_path):
    """l/r and a non-unit translate direction: amount = (r - l) * |d|, axis normalised."""
    (tmp_path / "gt").mkdir()
    info = {
        "trans_info": [
            {
                "axis": {"o": [0, 0, 0], "d": [0, 2, 0]},
                "type": "translate",
                "translate": {"l": 0.1, "r": 0.4},
            },
            {
                "axis": {"o": [1, 0, 0], "d": [0, 0, 1]},
                "type": "rotate",
                "rotate": {"l": -10, "r": 80},
            },
        ]
    }
    (tmp_path / "gt" / "trans.json").write_text(json.dumps(info))
    from gear.data.files import Reader
    from gear.data.gt import load_gt

    reader = Reader(tmp_path)
    gt = load_gt(reader)
    assert reader.problems == []
    assert gt.joints[0].amount == pytest.approx(0.6)
    np.testing.assert_allclose(gt.joints[0].axis, [0, 1, 0])
    assert gt.joints[1].amount == pytest.approx(90.0)
    # A 90 degree right-hand turn about +z through (1,0,0) takes (2,0,0) to (1,1,0).
    moved = gt.joints[1].motion() @ np.array([2.0, 0, 0, 1])
    np.testing.assert_allclose(moved[:3], [1, 1, 0], atol=1e-12)


def _frame_edit(root, name, edit):
    path = root / name
    meta = json.loads(path.read_text())
    edit(meta)
    path.write_text(json.dumps(meta))


def _expect(root, *fragments):
    problems = validate_scene(root)
    for fragment in fragments:
        assert any(fragment in p for p in problems), (fragment, problems)
    with pytest.raises(SceneError) as err:
        load_scene(root)
    assert err.value.problems == problems
    return problems


def test_valid_scene_has_no_problems(scene_dir, capsys):
    assert validate_scene(scene_dir) == []
    assert main(["check", str(scene_dir)]) == 0
    out = capsys.readouterr().out.strip()
    assert "ok, 12 views" in out and "start 4 train + 2 test, end 4 train + 2 test" in out
    assert "intrinsics:    40x40 fx" in out and "warning" not in out


def test_missing_image(broken, capsys):
    (broken / "start/train/rgba/0001.png").unlink()
    _expect(broken, "start/train/rgba/0001.png: missing")
    assert main(["check", str(broken)]) == 1
    assert "0001.png: missing" in capsys.readouterr().out


def test_unreadable_image(broken):
    (broken / "end/test/rgba/0000.png").write_bytes(b"not a png")
    (broken / "end/test/depth/0001.png").write_bytes(b"\x89PNG broken")
    _expect(
        broken, "end/test/rgba/0000.png: unreadable image", "end/test/depth/0001.png: unreadable"
    )


def test_size_mismatch(broken):
    img = Image.open(broken / "start/train/rgba/0002.png")
    img.resize((32, 40)).save(broken / "start/train/rgba/0002.png")
    depth = Image.open(broken / "end/train/depth/0000.png")
    depth.crop((0, 0, 40, 30)).save(broken / "end/train/depth/0000.png")
    _expect(
        broken,
        "start/train/rgba/0002.png: size 32x40 differs",
        "end/train/depth/0000.png: shape 30x40 differs from its image 40x40",
    )


def test_non_finite_and_non_rigid_camera(broken):
    def nan_pose(meta):
        meta["frames"][0]["transform_matrix"][0][3] = float("nan")

    def scaled_pose(meta):
        m = np.array(meta["frames"][1]["transform_matrix"])
        m[:3, :3] *= 1.5
        meta["frames"][1]["transform_matrix"] = m.tolist()

    _frame_edit(broken, "transforms_train_start.json", nan_pose)
    _frame_edit(broken, "transforms_train_end.json", scaled_pose)
    _expect(
        broken,
        "transforms_train_start.json: frame 0 (start/train/rgba/0000.png): camera",
        "non-finite",
        "transforms_train_end.json: frame 1",
        "not a rotation",
    )


def test_empty_alpha_and_missing_alpha(broken):
    path = broken / "start/test/rgba/0001.png"
    rgba = np.asarray(Image.open(path)).copy()
    rgba[..., 3] = 0
    Image.fromarray(rgba, "RGBA").save(path)
    Image.fromarray(rgba[..., :3], "RGB").save(broken / "end/test/rgba/0001.png")
    _expect(
        broken, "start/test/rgba/0001.png: alpha is empty", "end/test/rgba/0001.png: has no alpha"
    )


def test_mask_shape_mismatch(broken):
    np.save(broken / "start/train/mask/0003.npy", np.zeros((40, 41), dtype=np.uint16))
    np.save(broken / "end/train/mask/0003.npy", np.zeros((40, 40), dtype=np.float32))
    _expect(
        broken,
        "start/train/mask/0003.npy: shape 40x41 differs from its image 40x40",
        "end/train/mask/0003.npy: region mask must be a 2D integer array",
    )


def test_trans_json_missing_fields(broken):
    path = broken / "gt/trans.json"
    info = json.loads(path.read_text())
    del info["trans_info"][0]["axis"]
    del info["trans_info"][1]["rotate"]
    path.write_text(json.dumps(info))
    _expect(
        broken, "gt/trans.json: trans_info[0]: missing 'axis'", "trans_info[1]: missing 'rotate'"
    )
    path.write_text(json.dumps({"joints": []}))
    _expect(broken, "gt/trans.json: needs a 'trans_info' list")


def test_missing_transforms_and_bad_json(broken, tmp_path):
    (broken / "transforms_train_end.json").unlink()
    (broken / "transforms_test_start.json").write_text("{ not json")
    _expect(
        broken, "transforms_train_end.json: missing", "transforms_test_start.json: unreadable json"
    )
    assert validate_scene(tmp_path / "nowhere") == [f"{tmp_path / 'nowhere'}: not a directory"]


def test_gt_joint_rejects_bad_axis():
    with pytest.raises(ValueError, match="axis"):
        GtJoint("revolute", [0, 0, 0], [0, 0, 0], 10.0)
    with pytest.raises(ValueError, match="type"):
        GtJoint("screw", [0, 0, 0], [0, 0, 1], 10.0)


def test_scene_without_depth_or_masks_loads(scene_dir, tmp_path, capsys):
    scene = load_scene(scene_dir, splits=("train",))
    for views in scene.views.values():
        for v in views["train"]:
            v.depth = v.regions = v.parts = None
    write_scene(tmp_path / "bare", scene.views)
    bare = load_scene(tmp_path / "bare")
    assert bare.gt is None and not bare.has_depth and not bare.has_regions
    assert bare.test("start") == [] and len(bare.train("end")) == 4
    assert main(["check", str(tmp_path / "bare")]) == 0
    out = capsys.readouterr().out
    assert "depth:         none" in out and "region masks:  none" in out
    assert "warning" not in out  # nothing partial: the training uses what there is


def test_camera_problems_reported_even_without_image(broken):
    (broken / "start/train/rgba/0000.png").unlink()

    def three_by_three(meta):
        meta["frames"][0]["transform_matrix"] = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]

    def bad_angle(meta):
        meta["camera_angle_y"] = "wide"

    _frame_edit(broken, "transforms_train_start.json", three_by_three)
    _frame_edit(broken, "transforms_test_end.json", bad_angle)
    _expect(
        broken,
        "start/train/rgba/0000.png: missing",
        "transforms_train_start.json: frame 0 (start/train/rgba/0000.png): camera",
        "expected a 4x4 matrix",
        "transforms_test_end.json: camera_angle_y must be a number",
    )


def test_blender_style_file_paths(broken):
    """"./start/train/rgba/0000" (dot prefix, no extension) points at the same png."""

    def blender_paths(meta):
        for frame in meta["frames"]:
            frame["file_path"] = "./" + frame["file_path"].removesuffix(".png")

    _frame_edit(broken, "transforms_train_start.json", blender_paths)
    scene = load_scene(broken)
    assert scene.train("start")[2].name == "start/train/0002"
    assert scene.train("start")[2].depth is not None
