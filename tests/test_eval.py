"""`gear eval` on a fabricated scene and output folder whose metrics are known by construction."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import trimesh
from PIL import Image

from gear.camera import Camera
from gear.cli import main
from gear.data import GtJoint, View, write_scene
from gear.evaluate import evaluate
from gear.metrics import chamfer
from gear.run_folder import COMPLETE

RES = 16
OBJ = 102  # object colour in 8-bit steps: exact through PNG round trips
ERR = 26  # render error on object pixels, in 8-bit steps


def label_image() -> np.ndarray:
    """Static rows 0-7 (128 px), part 1 rows 8-11 left (32 px), part 2 rows 8-11 right."""
    img = np.full((RES, RES), 255, np.uint8)
    img[:8] = 0
    img[8:12, :8] = 1
    img[8:12, 8:] = 2
    return img


def square(z: float) -> trimesh.Trimesh:
    v = np.array([[0, 0, z], [1, 0, z], [1, 1, z], [0, 1, z]], float)
    return trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], process=False)


def gt_meshes() -> dict[str, trimesh.Trimesh]:
    return {
        "whole": square(0.0),
        "static": trimesh.creation.box(extents=[1.0, 1.0, 0.2]),
        "part_0": trimesh.creation.box(extents=[0.3, 0.1, 0.5]),
        "part_1": trimesh.creation.box(extents=[0.1, 0.6, 0.2]),
    }


GT_JOINTS = [
    GtJoint("revolute", origin=[0.5, 0, 0], axis=[0, 0, 1], amount=60.0),
    GtJoint("prismatic", origin=[0, 0, 0], axis=[1, 0, 0], amount=0.2),
]


def make_scene(root, with_gt: bool = True):
    parts = label_image()
    alpha = (parts != 255).astype(np.float32)
    rgb = np.zeros((RES, RES, 3), np.float32)
    rgb[parts != 255] = OBJ / 255
    views = {}
    for state in ("start", "end"):
        views[state] = {}
        for split, n in (("train", 2), ("test", 1)):
            vs = []
            for i in range(n):
                eye = [3 * math.cos(i + 0.3), 3 * math.sin(i + 0.3), 1.0]
                cam = Camera.look_at(eye, [0, 0, 0], [0, 0, 1], 0.8, RES, RES)
                vs.append(View(f"{state}/{split}/{i:04d}", cam, rgb, alpha, parts=parts.copy()))
            views[state][split] = vs
    joints = GT_JOINTS if with_gt else None
    meshes = {s: gt_meshes() for s in ("start", "end")} if with_gt else None
    return write_scene(root, views, joints=joints, meshes=meshes)


def make_output(out, d: float = 0.1):
    """Predictions in swapped order: pred 0 is the prismatic joint (GT 1), pred 1 the hinge."""
    joints = [
        {"part": 1, "type": "prismatic", "axis": [1, 0, 0], "origin": [0, 0, 0], "distance": 0.23},
        # Pivot 0.01 off the GT axis (perpendicular), angle 3 degrees short.
        {"part": 2, "type": "revolute", "axis": [0, 0, 1], "origin": [0.5, 0.01, 0.4],
         "angle_deg": 57.0},
    ]
    (out / "joints.json").parent.mkdir(parents=True, exist_ok=True)
    (out / "joints.json").write_text(json.dumps({"canonical": "start", "joints": joints}))
    (out / COMPLETE).write_text("{}\n")  # a finished run: eval reads only those
    (out / "log.jsonl").write_text(
        json.dumps({"event": "timings", "stage1": 12.5, "stage2": 0.5}) + "\n"
        + json.dumps({"event": "timings", "stage1": 12.5, "stage2": 0.5, "stage3": 30.0}) + "\n"
        + '{"iteration": 5, "loss"'  # a last line cut short by an interrupted write
    )
    gt = gt_meshes()
    for state in ("start", "end"):
        folder = out / "meshes" / state
        folder.mkdir(parents=True)
        square(d).export(folder / "whole.ply")  # offset d along the normal
        gt["static"].export(folder / "static.ply")
        gt["part_1"].export(folder / "part_0.ply")  # pred part 0 is GT part 1 ...
        gt["part_0"].export(folder / "part_1.ply")  # ... and pred part 1 is GT part 0
    # Part images with predicted ids: GT part 1 (hinge) is predicted part 2 and vice versa.
    swap = np.arange(256, dtype=np.uint8)
    swap[1], swap[2] = 2, 1
    gt_labels = label_image()
    for state in ("start", "end"):
        for split, n in (("train", 2), ("test", 1)):
            for i in range(n):
                pred = swap[gt_labels]
                if (state, split, i) == ("start", "test", 0):
                    pred[gt_labels == 1] = 0  # the hinge part missed in one view: taken as static
                path = out / "parts" / state / split / f"{i:04d}.png"
                path.parent.mkdir(parents=True, exist_ok=True)
                Image.fromarray(pred).save(path)
        # Test render over black: object pixels ERR steps too bright, background exact.
        render = np.zeros((RES, RES, 3), np.uint8)
        render[gt_labels != 255] = OBJ + ERR
        path = out / "renders" / state / "test" / "0000.png"
        path.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(render).save(path)


def test_eval_known_metrics(tmp_path, capsys):
    scene = make_scene(tmp_path / "scene")
    out = tmp_path / "out"
    make_output(out, d=0.1)
    assert main(["eval", str(out), str(scene), "--samples", "4000"]) == 0
    printed = capsys.readouterr().out
    assert "Axis Ang" in printed and "CD-w" in printed
    m = json.loads((out / "metrics.json").read_text())

    # Joints: matched across the swapped order, errors known by construction.
    pairs = {(r["gt"], r["pred"]) for r in m["joints"]}
    assert pairs == {(0, 1), (1, 0)}
    assert m["type_mismatches"] == 0 and not m["count_mismatch"]
    assert m["axis_ang"] == pytest.approx(0.0, abs=1e-6)
    assert m["axis_pos"] == pytest.approx(0.1)  # 0.01 x 10
    assert m["geo_dist_deg"] == pytest.approx(3.0)
    assert m["geo_dist_m"] == pytest.approx(0.03)

    # Chamfer: whole = squares offset by 0.1 -> 2000·d² = 20 plus the 4000-sample floor
    # (~2/(π·4000)·1000 ≈ 0.16, up to ~0.2 with border effects); matched parts are exact copies,
    # so CD-m sits at the sampling floor, far below what a wrong pairing would give.
    assert 20.1 < m["cd_w"] < 20.25
    for state in ("start", "end"):
        assert m["chamfer"][state]["whole"] == pytest.approx(m["cd_w"])
    gt = gt_meshes()
    floor_m = np.mean([chamfer(gt[k], gt[k], n=4000) for k in ("part_0", "part_1")])
    assert m["cd_m"] == pytest.approx(floor_m, rel=1e-5)  # PLY stores float32 vertices
    wrong = chamfer(gt["part_0"], gt["part_1"], n=4000)
    assert wrong > 10 * m["cd_m"]
    assert m["cd_s"] == pytest.approx(chamfer(gt["static"], gt["static"], n=4000), rel=1e-5)

    # Part IoU pooled over 6 views: static I=768, U=800; hinge part I=160, U=192; slider exact.
    assert m["part_iou"] == pytest.approx((768 / 800 + 160 / 192 + 1.0) / 3)
    assert m["part_iou_splits"]["train"]["mean"] == pytest.approx(1.0)

    # PSNR: object pixels (192 of 256) off by ERR/255, background exact.
    masked = 20 * math.log10(255 / ERR)
    assert m["psnr_masked"] == pytest.approx(masked, abs=1e-4)
    assert m["psnr"] == pytest.approx(masked - 10 * math.log10(192 / 256), abs=1e-4)
    assert m["timings"] == {"stage1": 12.5, "stage2": 0.5, "stage3": 30.0}  # the last record
    assert "stage3 30.0" in printed
    assert m["skipped"] == []


def test_eval_reports_type_mismatch(tmp_path):
    scene = make_scene(tmp_path / "scene")
    out = tmp_path / "out"
    make_output(out)
    joints = json.loads((out / "joints.json").read_text())
    # The hinge predicted as a slider: only a type-inconsistent pairing remains for it.
    joints["joints"][1] = {"part": 2, "type": "prismatic", "axis": [0, 0, 1],
                           "origin": [0, 0, 0], "distance": 0.1}
    (out / "joints.json").write_text(json.dumps(joints))
    m = evaluate(out, scene, samples=500)
    assert m["type_mismatches"] == 1
    row = next(r for r in m["joints"] if r["gt"] == 0)
    assert not row["type_match"] and row["pred_type"] == "prismatic"
    assert row["geo_dist"] == pytest.approx(60.0)  # the whole GT rotation counts as error


def test_eval_without_ground_truth_says_what_is_missing(tmp_path, capsys):
    scene = make_scene(tmp_path / "scene", with_gt=False)
    out = tmp_path / "out"
    out.mkdir()
    (out / COMPLETE).write_text("{}\n")  # a finished run whose outputs are all gone
    assert main(["eval", str(out), str(scene)]) == 0
    printed = capsys.readouterr().out
    m = json.loads((out / "metrics.json").read_text())
    # Every summary key is present, None when it cannot be computed.
    assert m["axis_ang"] is None and m["cd_w"] is None and m["part_iou"] is None
    assert m["psnr"] is None
    reasons = " ".join(m["skipped"])
    assert "joints.json missing" in reasons
    assert "no gt/trans.json" in reasons
    assert "part IoU not computed" in reasons and "PSNR not computed" in reasons
    assert "log.jsonl missing" in reasons and m["timings"] is None
    assert "not computed:" in printed


def test_eval_missing_output_folder_is_one_line_error(tmp_path, capsys):
    scene = make_scene(tmp_path / "scene")
    assert main(["eval", str(tmp_path / "nope"), str(scene)]) == 1
    assert "no such output folder" in capsys.readouterr().err


def test_eval_bad_joint_names_the_file(tmp_path):
    scene = make_scene(tmp_path / "scene")
    out = tmp_path / "out"
    make_output(out)
    (out / "joints.json").write_text(json.dumps({"joints": [{"type": "revolute",
                                                            "axis": [0, 0, 0]}]}))
    with pytest.raises(ValueError, match=r"joints\.json: joints\[0\]\.axis: zero-length"):
        evaluate(out, scene, samples=100)


def test_eval_empty_or_missing_predicted_mesh_is_reported(tmp_path):
    scene = make_scene(tmp_path / "scene")
    out = tmp_path / "out"
    make_output(out)
    trimesh.Trimesh().export(out / "meshes" / "end" / "part_0.ply")  # a part that vanished
    (out / "meshes" / "start" / "static.ply").unlink()
    m = evaluate(out, scene, samples=500)
    reasons = " ".join(m["skipped"])
    assert "end/part_0.ply empty: CD of end/part_1 not computed" in reasons
    assert "start/static.ply missing" in reasons
    assert set(m["chamfer"]["end"]) == {"whole", "static", "part_0"}
    assert set(m["chamfer"]["start"]) == {"whole", "part_0", "part_1"}
    assert m["cd_s"] == pytest.approx(m["chamfer"]["end"]["static"])  # the one state left
