"""The accuracy benchmark's budgets and its table/plot writers, on fabricated records."""

from __future__ import annotations

import argparse
import csv
import json

import numpy as np
import pytest
from PIL import Image

from gear.bench.accuracy import (
    EM_INTERVALS,
    METRICS,
    Run,
    budget_config,
    markdown_table,
    read_csv,
    scaled_em_interval,
    type_counts,
    variants,
    write_results,
)
from gear.cli import main
from gear.config import make_config
from gear.data import load_scene


def fake_runs() -> list[Run]:
    runs = []
    for scene, scale in (("fridge", 1.0), ("storage7", 3.0)):
        for budget, iters, seconds in (("quick", 500, 40.0), ("2000", 2000, 150.0),
                                       ("fast", 10000, 700.0)):
            err = scale * 500 / iters
            runs.append(Run(
                scene, budget, iterations=iters,
                timings={"stage1": seconds * 0.5, "stage2": 1.0, "stage3": seconds * 0.5 - 1},
                metrics={"axis_ang": err, "axis_pos": err / 2, "geo_dist_deg": err,
                         "geo_dist_m": None, "cd_s": err, "cd_m": 0.0, "cd_w": err,
                         "part_iou": 1 - err / 10, "psnr": 20 + iters / 1000},
            ))
    runs.append(Run("safe180", "quick", iterations=500, timings={"stage1": 3.0},
                    status="failed: non-finite loss | stage 3"))
    return runs


def test_writers_on_fabricated_records(tmp_path):
    runs = fake_runs()
    paths = write_results(runs, tmp_path / "bench", "test machine, 2 cores")
    with open(paths["csv"]) as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == len(runs)
    first = rows[0]
    assert first["scene"] == "fridge" and first["budget"] == "quick"
    assert float(first["total_s"]) == pytest.approx(40.0)
    assert float(first["time_stage1_s"]) == pytest.approx(20.0)
    assert float(first["axis_ang"]) == pytest.approx(1.0)
    assert first["geo_dist_m"] == ""  # not computable: empty cell, not "None" or 0
    assert rows[-1]["status"].startswith("failed")

    md = paths["md"].read_text()
    lines = md.splitlines()
    assert lines[0] == "Machine: test machine, 2 cores"
    table = [ln for ln in lines if ln.startswith("|")]
    assert len(table) == 2 + len(runs)  # header, separator, one row per run
    widths = {ln.count("|") for ln in table}
    assert len(widths) == 1  # every row has the header's column count (the '|' was escaped)
    assert "failed: non-finite loss / stage 3" in md
    storage_fast = next(ln for ln in table if "storage7" in ln and "| fast |" in ln)
    assert "| 0.150 |" in storage_fast  # axis_ang = 3·500/10000

    image = np.asarray(Image.open(paths["png"]))
    assert image.shape[0] > 300 and image.shape[1] > 600
    assert image[..., :3].std() > 10  # something was drawn


def test_ablation_records_get_a_bar_chart(tmp_path):
    """Ablation rows share one budget: the plot puts the variants along x (bars per scene), so
    it differs from the time plot of the same rows relabelled as budgets."""
    runs = []
    for scene, scale in (("fridge", 1.0), ("drawer_cabinet", 2.0)):
        for i, variant in enumerate(("em", "joint", "em_interval=50")):
            runs.append(Run(scene, "quick", variant, 300, timings={"stage3": 10.0 + i},
                            metrics={"axis_ang": scale * (i + 1), "part_iou": 0.8}))
    bars = write_results(runs, tmp_path / "ablation", "m")["png"]
    for r in runs:
        r.budget, r.variant = f"quick:{r.iterations}{r.variant}", "default"
    lines = write_results(runs, tmp_path / "budgets", "m")["png"]
    a, b = (np.asarray(Image.open(p).convert("L"), dtype=float) for p in (bars, lines))
    assert a.std() > 10
    assert a.shape != b.shape or np.abs(a - b).mean() > 1.0


def test_csv_round_trip(tmp_path):
    from gear.bench.accuracy import write_csv

    runs = fake_runs()
    runs[0].cpu_seconds = 12.345
    write_csv(runs, tmp_path / "a.csv")
    back = read_csv(tmp_path / "a.csv")
    assert [(r.scene, r.budget, r.variant, r.iterations, r.status) for r in back] == [
        (r.scene, r.budget, r.variant, r.iterations, r.status) for r in runs]
    assert back[0].cpu_seconds == pytest.approx(12.35) and back[1].cpu_seconds is None
    for got, want in zip(back, runs, strict=True):
        assert got.timings == pytest.approx(want.timings, abs=0.01)  # the CSV keeps 2 decimals
        assert {k: v for k, v in got.metrics.items() if v is not None} == pytest.approx(
            {k: v for k, v in want.metrics.items() if v is not None})


def test_table_lists_stage_times_in_pipeline_order():
    # Training reports its steps by key; the table shows them in the order they run, whatever
    # order a run's dict (or the CSV) has them in, and keeps unknown steps after them.
    timings = {"outputs": 1.0, "stage3": 5.0, "stage2": 0.5, "stage1-end": 2.0,
               "stage1-start": 3.0, "extra": 0.25}
    md = markdown_table([Run("fridge", "quick", iterations=300, timings=timings,
                             cpu_seconds=9.5)], "m")
    header, _, row = [ln for ln in md.splitlines() if ln.startswith("|")]
    cells = [c.strip() for c in header.strip("|").split("|")]
    assert cells[4:12] == ["stage 1 A (s)", "stage 1 B (s)", "stage 2 (s)", "stage 3 (s)",
                           "outputs (s)", "extra (s)", "total (s)", "CPU (s)"]
    values = [c.strip() for c in row.strip("|").split("|")][4:12]
    assert values == ["3.000", "2.000", "0.500", "5.000", "1.000", "0.250", "11.750", "9.500"]


def test_default_budget_ladder_spans_quick_to_fast():
    from gear.bench.accuracy import _resolve_defaults, add_arguments

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args([])
    _resolve_defaults(args)
    iterations = [budget_config(b)[1] for b in args.profiles.split(",")]
    assert iterations == [300, 1000, 3000, 10_000]


def test_config_file_applies_to_every_budget_and_labels_the_runs(tmp_path):
    # A real (tiny) benchmark: the built-in fridge at 32², two 20-iteration budgets, with a
    # Gaussian cap from --config. The cap must reach training (each run's saved config) and
    # name the runs' variant, so capped and uncapped runs can share one table.
    cap = tmp_path / "cap.json"
    cap.write_text(json.dumps({"max_gaussians_per_pixel": 1.5}))
    out = tmp_path / "bench"
    code = main(["bench", "accuracy", "--scenes", "fridge", "--profiles", "quick:20,quick:40",
                 "--res", "32", "--views", "3", "--test-views", "1", "--config", str(cap),
                 "--out", str(out)])
    assert code == 0
    back = read_csv(out / "accuracy.csv")
    assert [(r.budget, r.variant, r.status) for r in back] == [
        ("quick:20", "max_gaussians_per_pixel=1.5", "ok"),
        ("quick:40", "max_gaussians_per_pixel=1.5", "ok")]
    for r in back:
        assert set(r.timings) >= {"stage1", "stage2", "stage3"}
        assert r.metrics["part_iou"] is not None
        assert r.cpu_seconds is not None and r.cpu_seconds > 0
        saved = json.loads((out / "accuracy_runs" / "outputs" /
                            f"fridge-{r.budget}-{r.variant}" / "config.json").read_text())
        assert saved["max_gaussians_per_pixel"] == 1.5
        assert saved["stage3_iterations"] == r.iterations
    assert "| stage 1 (s) | stage 2 (s) | stage 3 (s) |" in (
        out / "accuracy.md").read_text()


def test_bad_config_file_fails_before_training(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"max_gaussians_per_pixel": -1}))
    code = main(["bench", "accuracy", "--scenes", "fridge", "--profiles", "quick",
                 "--config", str(bad), "--out", str(tmp_path / "bench")])
    assert code != 0
    assert "max_gaussians_per_pixel" in capsys.readouterr().err
    assert not (tmp_path / "bench").exists()


def test_run_labels_name_config_fields():
    from gear.bench.accuracy import run_label

    assert run_label("default", {}) == "default"
    assert run_label("em", {}) == "em"
    assert run_label("default", {"sh_degree": 1, "max_gaussians_per_pixel": 3.0}) == (
        "max_gaussians_per_pixel=3.0,sh_degree=1")
    assert run_label("joint", {"sh_degree": 1}) == "joint;sh_degree=1"


def test_markdown_table_without_runs_has_header_only():
    md = markdown_table([], "m")
    assert md.count("\n|") == 2
    assert all(label in md for _, label, _ in METRICS)


def test_budget_rescales_like_fast():
    fast, n = budget_config("fast")
    assert n == 10_000
    scaled, n = budget_config("10000")
    for name in ("stage1_iterations", "stage3_iterations", "densify_from", "densify_until",
                 "stage3_densify_until", "joint_classify_iteration",
                 "em_refine_joint_iterations"):
        assert getattr(scaled, name) == getattr(fast, name), name
    small, n = budget_config("3000", seed=4)
    assert (n, small.stage3_iterations, small.joint_classify_iteration) == (3000, 3000, 1000)
    assert small.seed == 4
    for budget in ("1000", "3000"):  # every budget of the ladder densifies, several times
        config, _ = budget_config(budget)
        window = config.densify_until - config.densify_from
        assert config.densify_from >= 1 and window >= 2 * config.densify_interval, budget
    assert budget_config("quick")[0] == make_config("quick")
    quick = make_config("quick")
    double, n = budget_config("quick:600")  # the quick schedule stretched to 600 + 600
    assert (n, double.stage3_iterations) == (600, 600)
    assert double.joint_classify_iteration == 2 * quick.joint_classify_iteration
    assert double.max_gaussians == quick.max_gaussians  # the rest of the profile is kept
    for bad in ("medium", "turbo:600", "quick:x"):
        with pytest.raises(ValueError, match=f"budget '{bad}'"):
            budget_config(bad)


def test_ablation_variants_cover_the_studies():
    labels = [label for label, _, _ in variants(True)]
    assert {"em", "joint", "em-refine"} <= set(labels)
    assert [f"em_interval={n}" for n in EM_INTERVALS] == [lb for lb in labels if "interval" in lb]
    effects = [fx for _, _, fx in variants(True) if fx]
    assert ("mask-over",) in effects and ("mask-under",) in effects
    assert variants(False) == [("default", {}, ())]


def test_em_interval_keeps_the_papers_share_of_stage_3():
    full = make_config("full")
    assert scaled_em_interval(500, full) == 500  # the paper's own schedule is unchanged
    quick = make_config("quick")  # 300 stage-3 iterations = 1/100 of the paper's 30k
    assert [scaled_em_interval(n, quick) for n in EM_INTERVALS] == [1, 2, 5, 20, 30]
    fast, _ = budget_config("fast")  # 10k: a third
    assert scaled_em_interval(3000, fast) == 1000
    assert scaled_em_interval(50, budget_config("quick:150")[0]) == 1  # never 0


def test_bad_budget_fails_before_training(tmp_path, capsys):
    code = main(["bench", "accuracy", "--scenes", "fridge", "--profiles", "quick,lots",
                 "--out", str(tmp_path)])
    assert code == 1
    assert "budget 'lots'" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


def test_run_loop_records_every_run_and_failure(tmp_path, monkeypatch, capsys):
    # Training and evaluation replaced by stand-ins: this checks the loop, the configs it passes
    # and the files it writes, not the method.
    import gear.bench.accuracy as accuracy
    import gear.evaluate as eval_cmd
    import gear.train as train_mod

    scene = tmp_path / "my_scene"
    scene.mkdir()
    seen = []

    def fake_train(scene_dir, out_dir, config, overwrite=False, quiet=False):
        assert overwrite  # a re-run replaces the earlier run of that configuration
        seen.append((scene_dir, config.stage3_iterations, config.schedule, config.em_interval))
        if config.schedule == "joint":
            raise RuntimeError("stage 3 iteration 7: non-finite loss")
        out_dir.mkdir(parents=True, exist_ok=True)  # as the real trainer does
        return train_mod.TrainResult([], "start", {"stage1": 2.0, "stage3": 1.0})

    def fake_evaluate(out_dir, scene_dir):
        return {"axis_ang": 1.5, "cd_w": 2.0, "part_iou": 0.9, "type_mismatches": 1}

    monkeypatch.setattr(train_mod, "train", fake_train)
    monkeypatch.setattr(eval_cmd, "evaluate", fake_evaluate)
    monkeypatch.setattr(accuracy, "machine_description", lambda: "test machine")
    out = tmp_path / "bench"
    code = main(["bench", "accuracy", "--scenes", str(scene), "--profiles", "quick,100",
                 "--out", str(out)])
    assert code == 0
    quick_iterations = make_config("quick").stage3_iterations
    assert [(s[1], s[2]) for s in seen] == [(quick_iterations, "em"), (100, "em")]
    rows = list(csv.DictReader(open(out / "accuracy.csv")))
    assert [r["budget"] for r in rows] == ["quick", "100"]
    assert rows[1]["scene"] == "my_scene" and float(rows[1]["total_s"]) == 3.0
    assert rows[0]["axis_ang"] == "1.5" and rows[0]["type_mismatches"] == "1"
    kept = json.loads((out / "accuracy_runs" / "outputs" / "my_scene-100-default" /
                       "metrics.json").read_text())
    assert kept["cd_w"] == 2.0  # each run keeps its full metrics next to its outputs

    # --append keeps the table and trains only what is not in it yet.
    seen.clear()
    code = main(["bench", "accuracy", "--scenes", str(scene), "--profiles", "quick,100,200",
                 "--out", str(out), "--append"])
    assert code == 0 and [s[1] for s in seen] == [200]
    rows = list(csv.DictReader(open(out / "accuracy.csv")))
    assert [r["budget"] for r in rows] == ["quick", "100", "200"]
    assert rows[0]["axis_ang"] == "1.5"

    seen.clear()
    code = main(["bench", "accuracy", "--scenes", str(scene), "--profiles", "100",
                 "--ablation", "--out", str(out)])
    assert code == 1  # the failed joint-optimisation run makes the exit code non-zero ...
    rows = list(csv.DictReader(open(out / "accuracy.csv")))
    status = {r["variant"]: r["status"] for r in rows}
    assert status["joint"].startswith("failed: stage 3 iteration 7")  # ... but is recorded
    assert status["em_interval=50"] == "ok"
    # Intervals 50..3000 of a 30k stage 3 at the same share of this budget's 100 iterations;
    # the plain "em" variant keeps the budget's own interval (the full profile's 500).
    assert sorted(s[3] for s in seen if s[2] == "em") == [1, 1, 2, 7, 10, 500]
    # A scene folder cannot be regenerated with flawed masks: recorded as skipped, with why.
    assert status["masks:mask-over"].startswith("skipped: ")
    assert "built-in object name" in status["masks:mask-over"]


def test_suite_table_and_plot_show_structure_per_object(tmp_path):
    runs = [
        Run("scissors", "quick", iterations=300, timings={"stage1": 60.0, "stage3": 80.0},
            metrics={"axis_ang": 87.6, "axis_pos": 0.25, "geo_dist_deg": 178.6, "cd_m": 7.4,
                     "part_iou": 0.34}, parts_true=2, parts_found=3,
            types_true=type_counts(["rotate"]), types_found=type_counts(["revolute"] * 2)),
        Run("cabinet_tall", "quick", iterations=300, timings={"stage1": 90.0},
            metrics={"axis_ang": 0.5, "geo_dist_m": 0.01, "part_iou": 0.8}, parts_true=3,
            parts_found=3, types_true="1R+1P", types_found="1R+1P",
            part_motion_px=[8.64, 0.14], types_visible="1R"),
        Run("fridge", "quick", iterations=300, status="failed: stage 2 | no motion"),
    ]
    paths = write_results(runs, tmp_path / "real", "m", suite=True)
    md = paths["md"].read_text()
    table = [ln for ln in md.splitlines() if ln.startswith("|")]
    assert len(table) == 2 + len(runs) and len({ln.count("|") for ln in table}) == 1
    assert "| scissors | quick | 3 / 2 | 2R / 1R | - | 87.600 | 0.250 | 178.6 | - | 7.400 " \
           "| 0.340 | 140.0 | ok |" in md
    # A part that moves less than a pixel in the images is named as such.
    assert "| cabinet_tall | quick | 3 / 3 (2 move >= 1 px) | 1R+1P / 1R+1P | 0.140 |" in md
    assert "| fridge | quick | - / - | - / - |" in table[-1]
    assert "failed: stage 2 / no motion" in table[-1]
    back = read_csv(paths["csv"])
    assert [(r.parts_true, r.parts_found, r.types_true, r.types_found) for r in back] == [
        (2, 3, "1R", "2R"), (3, 3, "1R+1P", "1R+1P"), (None, None, "", "")]
    assert [r.part_motion_px for r in back] == [[], [8.64, 0.14], []]
    assert back[1].types_visible == "1R"
    # The summary counts the scenes found right, on every true part and on the visible ones:
    # cabinet_tall is right on all three, not on its two visible ones (it found a third part).
    assert ("- quick: K and types right on 1 of 3 scenes (1 of 2 with at most 3 parts); on the "
            "parts that move >= 1 px: 0 of 3 (0 of 2)") in md
    image = np.asarray(Image.open(paths["png"]).convert("L"), dtype=float)
    assert image.std() > 10


def test_type_counts_ignore_order():
    assert type_counts(["revolute", "prismatic", "revolute"]) == "2R+1P"
    assert type_counts(["translate", "rotate", "rotate"]) == "2R+1P"
    assert type_counts([]) == "-"


SUITE_URDF = """<?xml version="1.0"?>
<robot name="two_lids">
  <link name="base"><visual><geometry><box size="0.4 0.4 0.2"/></geometry></visual></link>
  <link name="lid"><visual><origin xyz="0.1 0 0"/>
    <geometry><box size="0.2 0.4 0.02"/></geometry></visual></link>
  <link name="flap"><visual><origin xyz="0 0.1 0"/>
    <geometry><box size="0.1 0.2 0.02"/></geometry></visual></link>
  <joint name="hinge" type="revolute"><origin xyz="-0.2 0 0.11"/><axis xyz="0 1 0"/>
    <parent link="base"/><child link="lid"/><limit lower="-1.5" upper="0.5"/></joint>
  <joint name="flap_hinge" type="revolute"><origin xyz="0.1 0.2 0"/><axis xyz="1 0 0"/>
    <parent link="lid"/><child link="flap"/><limit lower="0" upper="1"/></joint>
</robot>
"""


def test_suite_run_loop_renders_and_records_structure(tmp_path, monkeypatch):
    # A made-up asset folder (a lid with a flap riding on it) and a stand-in trainer that
    # finds one hinge: checks the loop, the nested-joint scenes and the structure columns.
    import gear.bench.accuracy as accuracy
    import gear.evaluate as eval_cmd
    import gear.train as train_mod

    asset = tmp_path / "assets" / "lidbox_1"
    asset.mkdir(parents=True)
    (asset / "mobility.urdf").write_text(SUITE_URDF)

    def fake_train(scene_dir, out_dir, config, overwrite=False, quiet=False):
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "joints.json").write_text(json.dumps({"joints": [{"type": "revolute"}]}))
        return train_mod.TrainResult([], "start", {"stage1": 2.0})

    monkeypatch.setattr(train_mod, "train", fake_train)
    monkeypatch.setattr(eval_cmd, "evaluate", lambda out_dir, scene_dir: {"axis_ang": 1.0})
    monkeypatch.setattr(accuracy, "machine_description", lambda: "test machine")
    out = tmp_path / "real"
    code = main(["bench", "accuracy", "--suite", "real", "--assets", str(tmp_path / "assets"),
                 "--profile", "quick", "--res", "24", "--views", "2", "--test-views", "0",
                 "--out", str(out)])
    assert code == 0
    back = read_csv(out / "accuracy.csv")
    # One scene per nested joint, the other joint held at rest; each has one moving part.
    assert [r.scene for r in back] == ["lidbox-hinge", "lidbox-flap_hinge"]
    assert all((r.parts_true, r.parts_found, r.types_true, r.types_found) ==
               (2, 2, "1R", "1R") for r in back)
    assert all(len(r.part_motion_px) == 1 and r.part_motion_px[0] > 0 for r in back)
    assert all(r.types_visible == ("1R" if r.part_motion_px[0] >= 1 else "-") for r in back)
    scene = load_scene(out / "accuracy_runs" / "scenes" / "lidbox-hinge-r24-v2")
    assert len(scene.gt.joints) == 1 and scene.gt.joints[0].amount < 0  # towards -1.5
    assert "| lidbox-hinge | quick | 2 / 2 | 1R / 1R |" in (out / "accuracy.md").read_text()


def test_append_resumes_an_interrupted_run_and_replaces_a_foreign_one(tmp_path, monkeypatch):
    # Stand-in trainer: which folders were resumed and which started over. An interrupted run
    # (a checkpoint, no completion marker) continues under --append, never loses its
    # checkpoint; a checkpoint of another configuration is replaced; without --append every
    # run starts over.
    import gear.bench.accuracy as accuracy
    import gear.evaluate as eval_cmd
    import gear.train as train_mod
    from gear.run_folder import RunFolderError

    scene = tmp_path / "my_scene"
    scene.mkdir()
    out = tmp_path / "bench"
    outputs = out / "accuracy_runs" / "outputs"
    calls = []

    def fake_train(scene_dir, out_dir, config, resume=False, overwrite=False, quiet=False):
        calls.append((out_dir.name, "resume" if resume else "overwrite"))
        assert resume != overwrite
        if resume and out_dir.name.endswith("-200-default"):
            raise RunFolderError("--resume: the options differ from the saved run's (seed)")
        out_dir.mkdir(parents=True, exist_ok=True)
        return train_mod.TrainResult([], "start", {"stage1": 1.0})

    monkeypatch.setattr(train_mod, "train", fake_train)
    monkeypatch.setattr(eval_cmd, "evaluate", lambda out_dir, scene_dir: {"axis_ang": 1.0})
    monkeypatch.setattr(accuracy, "machine_description", lambda: "test machine")
    for budget in ("100", "200"):  # two interrupted runs
        (outputs / f"my_scene-{budget}-default" / "checkpoints").mkdir(parents=True)
        (outputs / f"my_scene-{budget}-default" / "checkpoints" / "last.pt").write_bytes(b"x")
    finished = outputs / "my_scene-300-default"  # a finished run is never resumed
    (finished / "checkpoints").mkdir(parents=True)
    (finished / "checkpoints" / "last.pt").write_bytes(b"x")
    (finished / "complete.json").write_text("{}")

    args = ["bench", "accuracy", "--scenes", str(scene), "--profiles", "100,200,300,400",
            "--out", str(out)]
    assert main([*args, "--append"]) == 0
    assert calls == [
        ("my_scene-100-default", "resume"),
        ("my_scene-200-default", "resume"),  # another configuration's checkpoint ...
        ("my_scene-200-default", "overwrite"),  # ... is replaced
        ("my_scene-300-default", "overwrite"),
        ("my_scene-400-default", "overwrite"),
    ]
    rows = list(csv.DictReader(open(out / "accuracy.csv")))
    assert [(r["budget"], r["status"]) for r in rows] == [
        ("100", "ok"), ("200", "ok"), ("300", "ok"), ("400", "ok")]

    calls.clear()
    assert main(args) == 0  # without --append: every run starts over
    assert [mode for _, mode in calls] == ["overwrite"] * 4


def test_append_scores_a_finished_run_of_the_same_scene_and_configuration(tmp_path,
                                                                          monkeypatch):
    # A run that finished before the benchmark scored it (trained by hand, or its scoring
    # interrupted: no row in accuracy.csv) is scored as it is under --append, once its last
    # checkpoint shows the same scene and configuration; a run of another configuration is
    # trained again. Real (tiny) training, so that the checkpoint's fingerprint is real.
    import gear.bench.accuracy as accuracy
    import gear.train as train_mod
    from gear.synth import generate

    monkeypatch.setattr(accuracy, "machine_description", lambda: "test machine")
    scene = generate("fridge", tmp_path / "fridge", res=24, views=4, test_views=1)
    other = generate("drawer_cabinet", tmp_path / "other", res=24, views=4, test_views=1)
    tiny = dict(init_max_points=400, max_gaussians=800, num_parts=2, classify_tune_steps=2,
                mesh_voxel=0.08, mesh_trunc=0.24)
    config_file = tmp_path / "tiny.json"
    config_file.write_text(json.dumps(tiny))
    out = tmp_path / "bench"
    args = ["bench", "accuracy", "--scenes", str(scene), "--profiles", "quick:20",
            "--config", str(config_file), "--out", str(out)]
    assert main(args) == 0
    first = list(csv.DictReader(open(out / "accuracy.csv")))
    run_dir = out / "accuracy_runs" / "outputs" / f"fridge-quick:20-{accuracy.config_label(tiny)}"
    config = budget_config("quick:20")[0].replace(**tiny)
    found = train_mod.finished_run(scene, run_dir, config)
    assert found is not None and found.timings == json.loads(
        (run_dir / "complete.json").read_text())["timings"]
    assert train_mod.finished_run(other, run_dir, config) is None  # another scene
    assert train_mod.finished_run(scene, run_dir, config.replace(seed=1)) is None

    trained = []
    real_train = train_mod.train

    def counting_train(*a, **k):
        trained.append(k)
        return real_train(*a, **k)

    monkeypatch.setattr(train_mod, "train", counting_train)
    (out / "accuracy.csv").unlink()  # the run is in its folder, not in the table
    assert main([*args, "--append"]) == 0
    assert trained == []
    again = list(csv.DictReader(open(out / "accuracy.csv")))
    assert [r["axis_ang"] for r in again] == [r["axis_ang"] for r in first]
    assert [r["total_s"] for r in again] == [r["total_s"] for r in first]
    assert first[0]["cpu_s"] and not again[0]["cpu_s"]  # not trained here: CPU time unknown

    (out / "accuracy.csv").unlink()
    assert main([*args, "--append", "--seed", "1"]) == 0  # another configuration: trained
    assert [k.get("overwrite") for k in trained] == [True]
