"""`gear check` (and so training's loader) validates the formats of depth and mask files: depth
must be 16-bit, masks must be black and white within their type's range, and depth that covers
little of the object is warned about; training says which inputs it uses."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from PIL import Image

from gear.cli import main
from gear.data import load_scene
from gear.data.coverage import depth_on_object, input_warnings, inputs_used
from gear.synth import generate
from test_data_layouts import write_nerfstudio

DEPTH = "start/train/depth/0000.png"  # a depth file of the generated (ArtGS/GEAR) layout
MASK = "start/masks/train_0000.png"  # an object mask of the nerfstudio layout


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    return generate("fridge", tmp_path_factory.mktemp("scene") / "s", res=32, views=4,
                    test_views=1)


@pytest.fixture
def copy(scene_dir, tmp_path):
    return shutil.copytree(scene_dir, tmp_path / "copy")


@pytest.fixture
def nerfstudio(scene_dir, tmp_path):
    return write_nerfstudio(load_scene(scene_dir), tmp_path / "ns")


def _check(root, capsys) -> tuple[int, str]:
    code = main(["check", str(root)])
    return code, capsys.readouterr().out


def test_an_8bit_depth_png_is_an_error_naming_the_file(copy, tmp_path, capsys):
    depth = np.asarray(Image.open(copy / DEPTH))
    Image.fromarray(np.clip(depth // 8, 0, 255).astype(np.uint8), "L").save(copy / DEPTH)
    code, out = _check(copy, capsys)
    assert code == 1
    assert (f"{DEPTH}: depth must be a single-channel 16-bit png (millimetres), got 8-bit "
            "grayscale") in out
    # Training refuses the same scene before it creates anything.
    assert main(["train", str(copy), "--out", str(tmp_path / "out"), "--quiet"]) == 1
    assert DEPTH in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_a_16bit_depth_png_passes_and_check_says_how_much_of_the_object_has_depth(
        scene_dir, capsys):
    code, out = _check(scene_dir, capsys)
    assert code == 0
    scene = load_scene(scene_dir)
    fraction = depth_on_object(scene.all_views())
    assert fraction is not None and fraction > 0.5
    assert f"depth:         every view ({100 * fraction:.0f}% of object pixels)" in out


def test_depth_on_object_counts_object_pixels_with_depth(scene_dir):
    view = load_scene(scene_dir).train("start")[0]
    view.depth = np.where(np.arange(view.depth.shape[1]) < view.depth.shape[1] // 2,
                          0.0, 1.0).astype(np.float32)[None, :].repeat(view.depth.shape[0], 0)
    obj = view.alpha > 0.5
    expected = (obj & (view.depth > 0)).sum() / obj.sum()
    assert depth_on_object([view]) == pytest.approx(expected)
    view.depth = None
    assert depth_on_object([view]) is None


def test_depth_covering_little_of_the_object_is_warned(copy, capsys):
    for path in sorted((copy / "start/train/depth").glob("*.png")):
        depth = np.asarray(Image.open(path)).copy()
        depth[:, : depth.shape[1] * 4 // 5] = 0  # most of every map lost
        Image.fromarray(depth.astype(np.uint16)).save(path)
    code, out = _check(copy, capsys)
    assert code == 0
    warnings = [line for line in out.splitlines() if line.startswith("warning:")]
    assert any("of the object pixels of the start training views" in w for w in warnings), out
    assert not any("end training views" in w for w in warnings)


def test_a_label_image_as_object_mask_is_an_error(nerfstudio, capsys):
    mask = np.asarray(Image.open(nerfstudio / MASK)) > 127
    labels = np.where(mask, 3, 0).astype(np.uint8)  # part ids 0..3, not a black/white mask
    Image.fromarray(labels, "L").save(nerfstudio / MASK)
    code, out = _check(nerfstudio, capsys)
    assert code == 1
    assert f"{MASK}: object mask values span 0..3" in out and "label image" in out


def test_a_grey_object_mask_is_warned_and_thresholded_at_half(nerfstudio, capsys):
    mask = np.asarray(Image.open(nerfstudio / MASK)) > 127
    grey = np.where(mask, 200, 60).astype(np.uint8)  # a photo-like "mask": every pixel grey
    Image.fromarray(grey, "L").save(nerfstudio / MASK)
    code, out = _check(nerfstudio, capsys)
    assert code == 0
    assert f"warning: {MASK}: object mask is not black and white (100% grey pixels)" in out
    np.testing.assert_array_equal(load_scene(nerfstudio).train("start")[0].alpha, mask)


def test_a_black_and_white_mask_with_soft_edges_is_not_warned(nerfstudio, capsys):
    mask = np.asarray(Image.open(nerfstudio / MASK)).astype(np.uint8)
    mask[0, :3] = 128  # a few anti-aliased pixels, as lossy tools write them
    Image.fromarray(mask, "L").save(nerfstudio / MASK)
    assert not [w for w in input_warnings(load_scene(nerfstudio)) if "black and white" in w]


def test_training_inputs_are_said_per_state(scene_dir):
    line = inputs_used(load_scene(scene_dir))
    assert line.startswith("inputs: start: 4 training views with object masks, depth on 4 (")
    assert "end: 4 training views" in line and "region masks on 4" in line
