"""Captures in nerfstudio and COLMAP layouts: the built-in fridge written in each layout by an
independent writer here (OpenGL / OpenCV camera axes, JPEG/PNG images with separate masks,
depth in millimetres) loads back to the original cameras (1e-6) and images."""

import importlib.util
import json
import shutil
import sys

import numpy as np
import pytest
from PIL import Image
from scipy.spatial.transform import Rotation

from gear.cli import main
from gear.data import SceneError, load_scene, validate_scene
from gear.data.coverage import input_warnings
from gear.synth import generate

CAMERA_TOL = 1e-6
STATES = ("start", "end")


@pytest.fixture(scope="module")
def fridge(tmp_path_factory):
    root = generate("fridge", tmp_path_factory.mktemp("fridge") / "s", res=32, views=4,
                    test_views=2)
    return load_scene(root)


def _u8(x):
    return (np.clip(x, 0, 1) * 255 + 0.5).astype(np.uint8)


def _gl_cam_to_world(camera):
    """OpenCV world-to-camera -> OpenGL camera-to-world, written out rather than taken from
    gear.camera: flip the camera's y and z axes."""
    c2w = np.linalg.inv(camera.world_to_cam)
    c2w[:3, 1:3] *= -1.0
    return c2w


def _write_images(folder, stem, view, image_ext=".png"):
    """RGB image (no alpha), binary mask, depth (uint16 mm), regions, parts; paths relative to
    `folder`."""
    paths = {"file_path": f"images/{stem}{image_ext}", "mask_path": f"masks/{stem}.png",
             "depth_file_path": f"depth/{stem}.png", "region_mask_path": f"regions/{stem}.npy",
             "part_ids_path": f"parts/{stem}.png"}
    for rel in paths.values():
        (folder / rel).parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(_u8(view.rgb), "RGB").save(folder / paths["file_path"], quality=95)
    Image.fromarray(_u8(view.alpha), "L").save(folder / paths["mask_path"])
    Image.fromarray(np.round(view.depth * 1000).astype(np.uint16)).save(
        folder / paths["depth_file_path"])
    np.save(folder / paths["region_mask_path"], view.regions.astype(np.uint16))
    Image.fromarray(view.parts, "L").save(folder / paths["part_ids_path"])
    return paths


def write_nerfstudio(scene, root, image_ext=".png"):
    """start/ gets global intrinsics and per-frame "split"; end/ per-frame intrinsics and
    nerfstudio's test_filenames."""
    for state in STATES:
        folder = root / state
        folder.mkdir(parents=True)
        frames, test_files = [], []
        for split in ("train", "test"):
            for view in scene.views[state][split]:
                stem = f"{split}_{view.name.rsplit('/', 1)[1]}"
                frame = _write_images(folder, stem, view, image_ext)
                frame["transform_matrix"] = _gl_cam_to_world(view.camera).tolist()
                c = view.camera
                if state == "start":
                    frame["split"] = split
                else:
                    frame.update(fl_x=c.fx, fl_y=c.fy, cx=c.cx, cy=c.cy, w=c.width, h=c.height)
                    if split == "test":
                        test_files.append(frame["file_path"])
                frames.append(frame)
        c = scene.views[state]["train"][0].camera
        meta = {"camera_model": "OPENCV", "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
                "frames": frames}
        if state == "start":
            meta.update(fl_x=c.fx, fl_y=c.fy, cx=c.cx, cy=c.cy, w=c.width, h=c.height)
        else:
            meta["test_filenames"] = test_files
        (folder / "transforms.json").write_text(json.dumps(meta))
    return root


def _check_same(original, loaded, exact_rgb=True):
    for state in STATES:
        for split in ("train", "test"):
            a_views, b_views = original.views[state][split], loaded.views[state][split]
            assert [v.name.rsplit("/", 1)[1] for v in b_views] == \
                [f"{split}_{v.name.rsplit('/', 1)[1]}" for v in a_views]
            for a, b in zip(a_views, b_views, strict=True):
                np.testing.assert_allclose(b.camera.world_to_cam, a.camera.world_to_cam,
                                           atol=CAMERA_TOL)
                for key in ("fx", "fy", "cx", "cy", "width", "height"):
                    assert getattr(b.camera, key) == pytest.approx(getattr(a.camera, key),
                                                                   abs=CAMERA_TOL)
                np.testing.assert_array_equal(b.alpha, a.alpha)
                if exact_rgb:
                    np.testing.assert_array_equal(b.rgb, a.rgb)
                else:  # JPEG quality 95
                    assert np.abs(b.rgb - a.rgb)[a.alpha > 0].mean() < 0.02


def test_nerfstudio_round_trip(fridge, tmp_path):
    loaded = load_scene(write_nerfstudio(fridge, tmp_path / "ns"))
    assert loaded.layout.startswith("nerfstudio")
    _check_same(fridge, loaded)
    for a, b in zip(fridge.all_views(), loaded.all_views(), strict=True):
        np.testing.assert_array_equal(b.depth, a.depth)  # mm pngs both ways
        np.testing.assert_array_equal(b.regions, a.regions)
        np.testing.assert_array_equal(b.parts, a.parts)
    assert input_warnings(loaded) == []


def test_nerfstudio_jpeg_and_depth_scale(fridge, tmp_path):
    root = write_nerfstudio(fridge, tmp_path / "ns", image_ext=".jpg")
    meta = json.loads((root / "end/transforms.json").read_text())
    meta["depth_unit_scale_factor"] = 0.002  # as if the pngs held half-millimetres
    (root / "end/transforms.json").write_text(json.dumps(meta))
    loaded = load_scene(root)
    _check_same(fridge, loaded, exact_rgb=False)
    a, b = fridge.train("end")[0], loaded.train("end")[0]
    np.testing.assert_allclose(b.depth, 2 * a.depth, rtol=1e-6)


def test_nerfstudio_problems_are_clear(fridge, tmp_path):
    root = write_nerfstudio(fridge, tmp_path / "ns", image_ext=".jpg")
    meta = json.loads((root / "start/transforms.json").read_text())
    meta["k1"] = 0.05
    (root / "start/transforms.json").write_text(json.dumps(meta))
    meta = json.loads((root / "end/transforms.json").read_text())
    del meta["frames"][0]["mask_path"]
    meta["frames"][1]["camera_model"] = "OPENCV_FISHEYE"
    meta["frames"][2]["w"] = 64
    (root / "end/transforms.json").write_text(json.dumps(meta))
    problems = validate_scene(root)
    expected = [
        "start/transforms.json: frame 0 (images/train_0000.jpg): non-zero lens distortion "
        "(k1=0.05): undistort the images first",
        "end/images/train_0000.jpg: no object mask: give a mask_path",
        "camera_model 'OPENCV_FISHEYE' is not supported",
        "end/images/train_0002.jpg: size 32x32 differs from the transforms file's w x h 64x32",
    ]
    for fragment in expected:
        assert any(fragment in p for p in problems), (fragment, problems)
    with pytest.raises(SceneError):
        load_scene(root)


def test_artgs_file_with_nerfstudio_intrinsics_points_to_the_layout(tmp_path):
    (tmp_path / "transforms_train_start.json").write_text(
        json.dumps({"fl_x": 30.0, "frames": []}))
    problems = validate_scene(tmp_path)
    assert any("nerfstudio's layout" in p for p in problems), problems


def test_unknown_folder_names_the_layouts(tmp_path):
    (tmp_path / "photos").mkdir()
    (problem,) = validate_scene(tmp_path)
    assert "no scene found" in problem and "nerfstudio" in problem and "COLMAP" in problem


def _colmap_text(model_dir, cameras, images):
    """COLMAP's text model: cameras.txt, images.txt (quaternion w x y z of world-to-camera,
    then its translation) and an empty points3D.txt."""
    model_dir.mkdir(parents=True)
    (model_dir / "cameras.txt").write_text(
        "".join(f"{cid} {model} {w} {h} {' '.join(repr(float(p)) for p in params)}\n"
                for cid, (model, w, h, params) in cameras.items()))
    lines = []
    for iid, (w2c, cid, name) in enumerate(images, start=1):
        x, y, z, w = Rotation.from_matrix(w2c[:3, :3]).as_quat()
        numbers = " ".join(repr(float(v)) for v in (w, x, y, z, *w2c[:3, 3]))
        lines.append(f"{iid} {numbers} {cid} {name}\n\n")
    (model_dir / "images.txt").write_text("".join(lines))
    (model_dir / "points3D.txt").write_text("")


def _colmap_images(scene, state, images_dir, masks_dir, prefix=""):
    """RGB images and COLMAP-named masks (IMAGE_NAME.png); (name, view) per image."""
    out = []
    for split in ("train", "test"):
        for view in scene.views[state][split]:
            name = f"{prefix}{split}_{view.name.rsplit('/', 1)[1]}.png"
            (images_dir / name).parent.mkdir(parents=True, exist_ok=True)
            (masks_dir / name).parent.mkdir(parents=True, exist_ok=True)
            Image.fromarray(_u8(view.rgb), "RGB").save(images_dir / name)
            Image.fromarray(_u8(view.alpha), "L").save(masks_dir / f"{name}.png")
            out.append((name, view))
    return out


def _pinhole(camera):
    return ("PINHOLE", camera.width, camera.height, [camera.fx, camera.fy, camera.cx, camera.cy])


def _test_list(root, names):
    (root / "test_images.txt").write_text("\n".join(names) + "\n")


def write_colmap_joint(scene, root):
    """One model of both states' images (images/start/..., images/end/...)."""
    cameras, images, tests = {}, [], []
    for state in STATES:
        for name, view in _colmap_images(scene, state, root / "images", root / "masks",
                                         f"{state}/"):
            cid = len(cameras) + 1
            cameras[cid] = _pinhole(view.camera)
            images.append((view.camera.world_to_cam, cid, name))
            tests += [name] if "/test_" in name else []
    _colmap_text(root / "sparse" / "0", cameras, images)
    _test_list(root, tests)
    return root


def _similarity(scale, rotvec, t):
    m = np.eye(4)
    m[:3, :3] = scale * Rotation.from_rotvec(rotvec).as_matrix()
    m[:3, 3] = t
    return m


def write_colmap_separate(scene, root, end_to_start):
    """One model per state; the end model in its own frame: x_start = end_to_start x_end."""
    tests = []
    scale = np.cbrt(np.linalg.det(end_to_start[:3, :3]))
    for state in STATES:
        images, cameras = [], {}
        for name, view in _colmap_images(scene, state, root / state / "images",
                                         root / state / "masks"):
            w2c = view.camera.world_to_cam
            if state == "end":  # the end model's pose of the same camera (rigid again)
                w2c = np.diag([1 / scale] * 3 + [1.0]) @ w2c @ end_to_start
            cameras[len(cameras) + 1] = _pinhole(view.camera)
            images.append((w2c, len(cameras), name))
            tests += [name] if name.startswith("test_") else []
        _colmap_text(root / state / "sparse" / "0", cameras, images)
    _test_list(root, tests)
    (root / "end_to_start.json").write_text(json.dumps({"matrix": end_to_start.tolist()}))
    return root


needs_pycolmap = pytest.mark.skipif(
    importlib.util.find_spec("pycolmap") is None, reason="COLMAP input needs pycolmap"
)


@needs_pycolmap
def test_colmap_one_model_round_trip(fridge, tmp_path):
    loaded = load_scene(write_colmap_joint(fridge, tmp_path / "cm"))
    assert loaded.layout == "COLMAP sparse model"
    _check_same(fridge, loaded)
    assert loaded.warnings == []


@needs_pycolmap
def test_colmap_two_models_with_a_similarity(fridge, tmp_path):
    sim = _similarity(2.5, [0.3, -1.1, 0.4], [0.2, -3.0, 1.5])
    loaded = load_scene(write_colmap_separate(fridge, tmp_path / "cm", sim))
    _check_same(fridge, loaded)


@needs_pycolmap
def test_colmap_problems_and_warnings(fridge, tmp_path, capsys):
    root = write_colmap_separate(fridge, tmp_path / "cm", np.eye(4))
    (root / "end_to_start.json").unlink()
    assert any("end_to_start.json: missing: separate start and end COLMAP models" in p
               for p in validate_scene(root))
    root = write_colmap_joint(fridge, tmp_path / "joint")
    cameras = (root / "sparse/0/cameras.txt").read_text().splitlines()
    cid, _, w, h, f, _, cx, cy = cameras[0].split()
    cameras[0] = f"{cid} OPENCV {w} {h} {f} {f} {cx} {cy} -0.1 0.0 0.0 0.0"
    (root / "sparse/0/cameras.txt").write_text("\n".join(cameras) + "\n")
    Image.new("RGB", (32, 32)).save(root / "images/start/unregistered.png")
    problems = validate_scene(root)
    assert any("OPENCV has non-zero lens distortion" in p and "image_undistorter" in p
               for p in problems), problems
    cameras[0] = f"{cid} OPENCV {w} {h} {f} {f} {cx} {cy} 0.0 0.0 0.0 0.0"  # zero: a pinhole
    (root / "sparse/0/cameras.txt").write_text("\n".join(cameras) + "\n")
    assert validate_scene(root) == []
    assert main(["check", str(root)]) == 0
    out = capsys.readouterr().out
    assert "warning:" in out and "1 image(s) not in the COLMAP model" in out
    assert "start/unregistered.png" in out


def test_colmap_without_pycolmap_says_how_to_install(fridge, tmp_path, monkeypatch):
    root = write_colmap_joint(fridge, tmp_path / "cm")
    monkeypatch.setitem(sys.modules, "pycolmap", None)  # import raises
    (problem,) = validate_scene(root)
    assert "pip install pycolmap" in problem


def test_check_explains_and_warns_on_partial_inputs(fridge, tmp_path, capsys):
    """A scene missing one depth image and every end-state region mask: check reports ok but
    warns, naming the views and what training does instead."""
    root = write_nerfstudio(fridge, tmp_path / "ns")
    for state, edit in (("start", "depth"), ("end", "regions")):
        meta = json.loads((root / state / "transforms.json").read_text())
        for k, frame in enumerate(meta["frames"]):
            if edit == "regions":
                del frame["region_mask_path"]
            elif k == 1:
                del frame["depth_file_path"]
        (root / state / "transforms.json").write_text(json.dumps(meta))
    assert main(["check", str(root)]) == 0
    out = capsys.readouterr().out
    assert "layout:        nerfstudio" in out
    assert "intrinsics:    32x32 fx" in out
    assert "depth:         start train 3/4, start test 2/2, end train 4/4, end test 2/2" in out
    warnings = [line for line in out.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 2, out
    assert "depth on 3 of 4 start training views (none on start/train/train_0001)" in warnings[0]
    assert "visual hull" in warnings[0]
    assert "region masks on start views only, none on end" in warnings[1]


def test_check_on_a_complete_artgs_scene_warns_nothing(fridge, capsys):
    assert main(["check", str(fridge.root)]) == 0
    out = capsys.readouterr().out
    assert "layout:        ArtGS/GEAR" in out and "warning" not in out
    assert "depth:         every view" in out


def test_copy_of_layout_keeps_gt(fridge, tmp_path):
    """gt/trans.json is read beside any layout."""
    root = write_nerfstudio(fridge, tmp_path / "ns")
    shutil.copytree(fridge.root / "gt", root / "gt")
    loaded = load_scene(root)
    assert len(loaded.gt.joints) == len(fridge.gt.joints) == 1
    np.testing.assert_allclose(loaded.gt.joints[0].axis, fridge.gt.joints[0].axis)


def test_training_on_a_nerfstudio_capture_says_what_it_uses_in_part(fridge, tmp_path):
    """`gear train` reads the nerfstudio layout and logs (never silently drops) a depth image
    missing from one view, and `gear eval` scores its test views without ground truth. The
    start state serves as both states, so the run is short: one static part, no stage 3 (as in
    test_train's motionless scene)."""
    import dataclasses

    from gear.commands.eval import evaluate
    from gear.config import make_config
    from gear.train import train

    same = {state: {split: [dataclasses.replace(v, name=v.name.replace("start", state, 1))
                            for v in views] for split, views in fridge.views["start"].items()}
            for state in STATES}
    twin = dataclasses.replace(fridge, views=same)
    root = write_nerfstudio(twin, tmp_path / "ns")
    meta = json.loads((root / "end/transforms.json").read_text())
    del meta["frames"][2]["depth_file_path"]
    (root / "end/transforms.json").write_text(json.dumps(meta))
    config = make_config("quick", dict(stage1_iterations=2, lr_means=1e-7, lr_means_final=1e-8,
                                       mesh_voxel=0.04, mesh_trunc=0.16))
    train(root, tmp_path / "out", config, quiet=True)
    log = [json.loads(line) for line in (tmp_path / "out/log.jsonl").read_text().splitlines()]
    said = [r["message"] for r in log if r.get("message", "").startswith("warning:")]
    assert len(said) == 1 and "depth on 3 of 4 end training views" in said[0], said
    assert "none on end/train/train_0002" in said[0]
    inputs = [r["message"] for r in log if r.get("message", "").startswith("inputs:")]
    assert len(inputs) == 1 and "end: 4 training views with object masks, depth on 3 (" in \
        inputs[0], inputs
    metrics = evaluate(tmp_path / "out", root)
    assert metrics["psnr_views"] == 4 and metrics["psnr"] > 10.0  # rendered vs test photos
    assert metrics["axis_ang"] is None  # no gt/: joint errors are skipped, not faked


@needs_pycolmap
def test_colmap_background_images_are_said_and_duplicate_names_refused(fridge, tmp_path):
    root = tmp_path / "cm"
    view = fridge.train("start")[0]
    names = ["start/0000.png", "start/again/0000.png", "background/wall.png", "end/0000.png"]
    for name in names:
        (root / "images" / name).parent.mkdir(parents=True, exist_ok=True)
        (root / "masks" / name).parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(_u8(view.rgb), "RGB").save(root / "images" / name)
        Image.fromarray(_u8(view.alpha), "L").save(root / "masks" / f"{name}.png")
    _colmap_text(root / "sparse" / "0", {1: _pinhole(view.camera)},
                 [(view.camera.world_to_cam, 1, name) for name in names])
    (problem,) = validate_scene(root)
    assert "2 images are named start/train/0000" in problem
    (root / "images/start/again/0000.png").unlink()
    names.remove("start/again/0000.png")
    _colmap_text(root / "sparse" / "1", {1: _pinhole(view.camera)},
                 [(view.camera.world_to_cam, 1, name) for name in names])
    shutil.rmtree(root / "sparse" / "0")
    (root / "sparse" / "1").rename(root / "sparse" / "0")
    scene = load_scene(root)
    assert [len(scene.train(s)) for s in STATES] == [1, 1]
    assert scene.warnings == ["sparse/0: image background/wall.png is in neither start/ nor end/: "
                              "not used"]


@pytest.mark.parametrize("encoding", ["0/255", "0/1", "1-bit", "16-bit"])
def test_mask_encodings(fridge, tmp_path, encoding):
    """Object masks as tools write them all read as the same mask."""
    root = write_nerfstudio(fridge, tmp_path / "ns")
    view = fridge.train("start")[0]
    binary = view.alpha > 0.5
    image = {"0/255": Image.fromarray(binary.astype(np.uint8) * 255, "L"),
             "0/1": Image.fromarray(binary.astype(np.uint8), "L"),
             "1-bit": Image.fromarray(binary).convert("1"),
             "16-bit": Image.fromarray(binary.astype(np.uint16) * 65535)}[encoding]
    image.save(root / "start/masks/train_0000.png")
    np.testing.assert_array_equal(load_scene(root).train("start")[0].alpha, binary)
