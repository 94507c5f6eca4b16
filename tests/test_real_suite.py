"""The real-asset suite (docs/evaluation.md, "Real-asset suite"): its scenes follow the stated
rules, and a few small PartNet-Mobility objects are recovered with the right part count and
joint types (a regression test at a tiny budget). Skipped when the assets are absent."""

from __future__ import annotations

import json

import numpy as np
import pytest

from gear.bench.accuracy import budget_config, record_structure
from gear.bench.accuracy.real import (
    MOTION_FRACTION,
    REAL_UP,
    WIDE_OPEN_DEG,
    assets_dir,
    real_scenes,
    render_real,
    select,
)
from gear.bench.accuracy.records import Run
from gear.cli import main
from gear.data import load_scene, validate_scene
from gear.synth.cameras import up_rotation
from gear.synth.generate import parse_up
from gear.synth.urdf import MOVABLE, _parse, load_urdf

ASSETS = assets_dir()
needs_assets = pytest.mark.skipif(not ASSETS.is_dir(),
                                  reason="PartNet-Mobility assets not available")


@needs_assets
def test_every_asset_gives_scenes_by_the_rules():
    scenes = real_scenes(ASSETS, seed=0)
    folders = sorted(p.name for p in ASSETS.iterdir() if (p / "mobility.urdf").is_file())
    assert sorted({s.folder for s in scenes}) == folders
    assert real_scenes(ASSETS, seed=0) == scenes  # seeded
    assert real_scenes(ASSETS, seed=1) != scenes
    for scene in scenes:
        robot = _parse(ASSETS / scene.folder / "mobility.urdf")
        joints = {j.name: j for j in robot.joints.values() if j.type in MOVABLE}
        # Continuous joints (knobs about their own axis) are not in the scene: they stay at 0.
        assert set(scene.joints) == {n for n, j in joints.items() if j.type != "continuous"}
        for name, (start, end) in scene.joints.items():
            lower, upper = joints[name].lower, joints[name].upper
            assert start == pytest.approx(np.clip(0.0, lower, upper))
            assert lower - 1e-12 <= end <= upper + 1e-12
            moved = abs(end - start) / (upper - lower)
            if start == end or (scene.name == "fridge-180" and name == "joint_0"):
                continue
            at_limit = min(abs(end - lower), abs(end - upper)) < 1e-12
            assert MOTION_FRACTION[0] - 1e-9 <= moved <= MOTION_FRACTION[1] + 1e-9 or at_limit
        # The importer accepts every scene: no moving joint rides on another one.
        obj = load_urdf(ASSETS / scene.folder / "mobility.urdf",
                        {n: v[0] for n, v in scene.joints.items()},
                        {n: v[1] for n, v in scene.joints.items()})
        assert len(obj.parts) + 1 == scene.parts
    by_name = {s.name: s for s in scenes}
    staplers = [s for s in scenes if s.folder.startswith("stapler")]
    assert len(staplers) == 2 and all(s.parts == 2 for s in staplers)
    wide = by_name["fridge-180"].joints["joint_0"]
    assert np.rad2deg(wide[1] - wide[0]) == pytest.approx(WIDE_OPEN_DEG)
    assert by_name["kitchen_counter"].parts == 9


@needs_assets
def test_select_by_name_in_order():
    scenes = real_scenes(ASSETS)
    assert [s.name for s in select(scenes, "scissors,fridge")] == [
        "scissors", "fridge", "fridge-180"]
    assert [s.name for s in select(scenes, "stapler")] == ["stapler-joint_0", "stapler-joint_1"]
    assert select(scenes, "") == scenes
    with pytest.raises(ValueError, match=r"unknown real-suite object.*teapot"):
        select(scenes, "scissors,teapot")


@needs_assets
def test_rendered_scene_is_a_rotated_textured_capture(tmp_path):
    scene = next(s for s in real_scenes(ASSETS) if s.name == "fridge")
    root = render_real(scene, ASSETS, tmp_path / "fridge", res=32, views=2, test_views=0)
    assert validate_scene(root) == []
    meta = json.loads((root / "synth.json").read_text())
    assert meta["effects"] == ["specular"] and meta["asset"] == scene.folder
    rotation = up_rotation(parse_up(REAL_UP))
    gt = load_scene(root).gt.joints
    # The fridge's door hinges are vertical in the asset (+z up), so along +y in the scene.
    for joint in gt:
        assert abs(joint.axis @ (rotation @ [0, 0, 1])) == pytest.approx(1.0, abs=1e-6)
    starts = [v.camera.center for v in load_scene(root).train("start")]
    ends = [v.camera.center for v in load_scene(root).train("end")]
    assert not np.allclose(starts, ends)  # other cameras in the other state


def test_suite_cli_errors(tmp_path, capsys):
    assert main(["bench", "accuracy", "--objects", "fridge", "--out", str(tmp_path)]) == 1
    assert "--objects selects objects of a --suite" in capsys.readouterr().err
    code = main(["bench", "accuracy", "--suite", "real", "--assets", str(tmp_path / "none"),
                 "--out", str(tmp_path / "out")])
    assert code == 1
    assert "PartNet-Mobility assets not found" in capsys.readouterr().err


# --- regression: K and joint types of small objects at a tiny budget -------------------------

# Small enough to run in the test suite, large enough for the pipeline to see the parts.
TINY = dict(res=64, views=16, test_views=0)
TINY_BUDGET = "quick:150"
# Training is deterministic on one machine, but float rounding differs between CPUs (vector
# widths in torch and the rasterizer), so an object on the edge of being recovered can pass on one
# machine and fail on another: its xfail is not strict.
SMALL_OBJECTS = [
    "scissors",
    "box",
    pytest.param("eyeglasses", marks=pytest.mark.xfail(strict=False, reason=(
        "thin temples: at this budget stage 1 may sample a temple in fragments in both "
        "states, and stage 2 then gives a fragment a motion of its own: K and types right on "
        "training seeds 0-3 with 3 of 4 since stage 3 merges parts read twice (2 of 4 "
        "before; seed 1 ends with K = 5); another CPU's rounding can do the same"))),
    "faucet",
]


@needs_assets
@pytest.mark.parametrize("name", SMALL_OBJECTS)
def test_small_object_part_count_and_types(name, tmp_path):
    from gear.train import train

    scene = next(s for s in real_scenes(ASSETS) if s.name == name)
    root = render_real(scene, ASSETS, tmp_path / "scene", **TINY)
    config, _ = budget_config(TINY_BUDGET)
    train(root, tmp_path / "out", config, quiet=True)
    record = Run(name, TINY_BUDGET)
    record_structure(record, tmp_path / "out", root)
    assert record.parts_true == scene.parts
    assert (record.parts_found, record.types_found) == (record.parts_true, record.types_true)
