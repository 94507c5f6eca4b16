"""Runs never lose or mix results: one run per output folder (lock, --resume / --overwrite,
staged outputs and a completion marker), resume checks what it resumes, SIGTERM / SIGHUP save
a checkpoint, typed config errors before anything is written, empty parts are dropped."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from gear import outputs as outputs_mod
from gear.articulation import PartMotion
from gear.cli import main
from gear.config import RANGES, make_config
from gear.outputs import drop_empty_parts
from gear.pipeline.runner import stops_interrupt
from gear.run_folder import COMPLETE, LOCK, RunFolder, RunFolderError
from gear.splats import Gaussians
from gear.synth import generate
from gear.train import train
from test_pipeline_resume import CONFIG, interrupted_at


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return generate("fridge", tmp_path_factory.mktemp("scene"), res=16, views=4, test_views=1)


@pytest.fixture(scope="module")
def other_scene(tmp_path_factory):
    return generate("fridge", tmp_path_factory.mktemp("other"), res=16, views=5, test_views=1)


def run_cli(argv: list[str], capsys) -> tuple[int, str]:
    code = main([str(a) for a in argv])
    return code, capsys.readouterr().err.strip()


# --- one run per output folder ---------------------------------------------------------------

def test_a_second_run_on_a_locked_folder_stops_naming_the_holder(tmp_path):
    with RunFolder.open(tmp_path / "out"):
        with pytest.raises(RunFolderError, match=rf"in use by another gear run \(PID "
                                                 rf"{os.getpid()}, started \d{{4}}-"):
            RunFolder.open(tmp_path / "out")
    assert not (tmp_path / "out" / LOCK).exists()  # released and removed on close


def test_a_lock_held_by_another_process_is_refused_and_a_dead_ones_taken_over(tmp_path):
    out = tmp_path / "out"
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys; from gear.run_folder import RunFolder; "
         f"f = RunFolder.open({str(out)!r}); print('held', flush=True); sys.stdin.read()"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(RunFolderError, match=f"PID {holder.pid}, started"):
            RunFolder.open(out)
    finally:
        holder.kill()  # SIGKILL: no clean-up, the lock file stays behind
        holder.wait()
    assert (out / LOCK).exists()
    with RunFolder.open(out) as folder:
        assert len(folder.notes) == 1
        assert "stale lock" in folder.notes[0] and f"PID {holder.pid}" in folder.notes[0]


def test_a_folder_holding_a_run_is_refused_without_resume_or_overwrite(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "log.jsonl").write_text("{}\n")
    with pytest.raises(RunFolderError, match="holds an unfinished run; continue it with --resume"):
        RunFolder.open(out)
    (out / COMPLETE).write_text("{}")
    with pytest.raises(RunFolderError, match="holds a finished run"):
        RunFolder.open(out)
    with pytest.raises(RunFolderError, match="is finished; nothing to resume"):
        RunFolder.open(out, resume=True)
    with pytest.raises(RunFolderError, match="exclude each other"):
        RunFolder.open(out, resume=True, overwrite=True)
    (out / "notes.txt").write_text("mine")
    with RunFolder.open(out, overwrite=True) as folder:
        assert "removed the previous run" in folder.notes[0]
    # The old run's files are gone, the user's own file stays.
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]


def test_overwrite_also_removes_the_old_runs_export_metrics_and_renders(tmp_path):
    out = tmp_path / "out"
    for name in ("joints.json", COMPLETE, "metrics.json", "twin_renders/s0.000/0000.png",
                 "urdf/export.json", "urdf/out.urdf", "mine/photo.jpg", "notes.txt"):
        (out / name).parent.mkdir(parents=True, exist_ok=True)
        (out / name).write_text("x")
    with pytest.raises(RunFolderError, match="holds a finished run"):
        RunFolder.open(out)
    with RunFolder.open(out, overwrite=True):
        pass
    # The export folder (recognised by its manifest) goes with the run: a new run's files never
    # sit beside the old run's URDF; folders and files gear did not write stay.
    assert sorted(p.name for p in out.iterdir()) == ["mine", "notes.txt"]


def test_a_folder_holding_only_an_export_counts_as_a_run_not_as_foreign_files(tmp_path):
    (tmp_path / "urdf").mkdir()
    (tmp_path / "urdf" / "export.json").write_text("{}")
    with pytest.raises(RunFolderError, match="holds an unfinished run"):
        RunFolder.open(tmp_path)


def test_a_folder_of_other_files_is_refused(tmp_path):
    (tmp_path / "holiday.jpg").write_bytes(b"x")
    with pytest.raises(RunFolderError, match=r"not a gear run's \(holiday\.jpg\)"):
        RunFolder.open(tmp_path, overwrite=True)


def test_outputs_are_staged_and_published_with_the_marker_last(tmp_path):
    with RunFolder.open(tmp_path / "out") as folder:
        staged = folder.staging()
        (staged / "joints.json").write_text("new")
        (staged / "meshes").mkdir()
        (folder.path / "meshes").mkdir()  # left by an earlier attempt of this run
        (folder.path / "meshes" / "old.ply").write_text("old")
        assert not (folder.path / "joints.json").exists()
        folder.publish({"joints": 0})
    names = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert names == [COMPLETE, "joints.json", "meshes"]
    assert list((tmp_path / "out" / "meshes").iterdir()) == []


def test_out_naming_a_file_or_an_uncreatable_folder_is_one_clean_line(scene, tmp_path, capsys):
    afile = tmp_path / "afile"
    afile.write_text("x")
    code, err = run_cli(["train", scene, "--out", afile, "--profile", "quick"], capsys)
    assert code == 1 and err == f"gear: error: --out {afile}: is a file, not a folder"
    code, err = run_cli(["train", scene, "--out", afile / "sub", "--profile", "quick"], capsys)
    assert code == 1 and err.startswith(f"gear: error: --out {afile / 'sub'}: cannot create")
    assert "\n" not in err


def test_a_failure_while_writing_outputs_leaves_an_unfinished_run_that_resumes(
        scene, tmp_path, monkeypatch):
    def broken(*_args, **_kw):
        raise OSError("disk full")

    monkeypatch.setattr(outputs_mod, "write_meshes", broken)
    with pytest.raises(OSError, match="disk full"):
        train(scene, tmp_path / "out", make_config("quick", CONFIG), quiet=True)
    names = {p.name for p in (tmp_path / "out").iterdir()}
    assert COMPLETE not in names and "joints.json" not in names and LOCK not in names
    monkeypatch.undo()
    train(scene, tmp_path / "out", make_config("quick", CONFIG), resume=True, quiet=True)
    assert (tmp_path / "out" / COMPLETE).exists() and (tmp_path / "out" / "meshes").is_dir()


def test_a_run_from_before_the_completion_marker_says_how_to_finish_it(scene, tmp_path,
                                                                     capsys):
    out = tmp_path / "old"
    train(scene, out, make_config("quick", CONFIG), quiet=True)
    joints = (out / "joints.json").read_bytes()
    (out / COMPLETE).unlink()  # what a gear older than the marker left
    hint = (f"has outputs but no {COMPLETE} (written by an older gear, or stopped while "
            f"publishing them); `gear train SCENE --out {out} --resume` rewrites them")
    code, err = run_cli(["eval", out, scene], capsys)
    assert code == 1 and err.startswith(f"gear: error: {out}: {hint}") and "\n" not in err
    code, err = run_cli(["train", scene, "--out", out, "--profile", "quick"], capsys)
    assert code == 1 and err.startswith(f"gear: error: --out {out}: {hint}")
    # The advice works: --resume rewrites the outputs from the final checkpoint, marks the run.
    train(scene, out, make_config("quick", CONFIG), resume=True, quiet=True)
    assert (out / COMPLETE).is_file() and (out / "joints.json").read_bytes() == joints


# --- resume checks what it resumes -----------------------------------------------------------

@pytest.fixture(scope="module")
def interrupted(scene, tmp_path_factory):
    """A run stopped inside stage 3, as Ctrl-C leaves it."""
    out = tmp_path_factory.mktemp("interrupted") / "out"
    with interrupted_at("stage3", 5), pytest.raises(KeyboardInterrupt):
        train(scene, out, make_config("quick", CONFIG), quiet=True)
    return out


def test_resume_with_another_scene_names_what_differs(interrupted, other_scene):
    with pytest.raises(ValueError, match=r"another scene \(.*new files: "):
        train(other_scene, interrupted, make_config("quick", CONFIG), resume=True, quiet=True)


def test_resume_with_changed_options_names_them(scene, interrupted, capsys):
    code, err = run_cli(["train", scene, "--out", interrupted, "--resume", "--seed", "3"], capsys)
    assert code == 1
    assert err == ("gear: error: --resume: the options differ from the saved run's (seed 0 -> 3);"
                   " resume without them or start over with --overwrite")
    code, err = run_cli(["train", scene, "--out", interrupted, "--resume", "--profile", "fast"],
                        capsys)
    assert code == 1 and "profile 'quick' -> 'fast'" in err
    code, err = run_cli(["train", scene, "--out", interrupted, "--resume", "--parts", "4"], capsys)
    assert code == 1 and "num_parts 2 -> 4" in err


def test_a_new_run_over_an_unfinished_one_is_refused(scene, interrupted, capsys):
    code, err = run_cli(["train", scene, "--out", interrupted, "--profile", "quick"], capsys)
    assert code == 1 and "holds an unfinished run" in err


# --- SIGTERM and SIGHUP save a checkpoint like Ctrl-C ---------------------------------------

@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP])
def test_sigterm_and_sighup_save_a_checkpoint(scene, tmp_path, sig):
    config = tmp_path / "long.json"
    config.write_text(json.dumps({**CONFIG, "stage1_iterations": 100_000,
                                  "checkpoint_every": 100_000, "log_every": 1}))
    out = tmp_path / "out"
    proc = subprocess.Popen(
        [sys.executable, "-m", "gear", "train", str(scene), "--out", str(out), "--profile",
         "quick", "--config", str(config), "--quiet"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        # Wait for training iterations to be logged (the signal handlers are in place then).
        while proc.poll() is None and '"iteration": 2' not in _read(out / "log.jsonl"):
            time.sleep(0.2)
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    assert "interrupted: checkpoint saved at stage1 iteration" in err
    saved = torch.load(out / "checkpoints" / "last.pt", weights_only=False)
    assert saved["stage"] == "stage1" and saved["iteration"] >= 3
    assert not (out / LOCK).exists() and not (out / COMPLETE).exists()


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP])
def test_stop_signals_outside_the_iterations_unwind_like_ctrl_c(sig):
    before = signal.getsignal(sig)
    with stops_interrupt(), pytest.raises(KeyboardInterrupt):
        os.kill(os.getpid(), sig)
        time.sleep(5)  # the handler runs at the next bytecode; never reached
    assert signal.getsignal(sig) == before  # restored for library callers


def _read(path: Path) -> str:
    return path.read_text() if path.exists() else ""


# --- config validated by type and range, before anything is created on disk -----------------

@pytest.mark.parametrize("field,value,message", [
    ("stage1_iterations", "300", "stage1_iterations: expected an int, got '300' (a string)"),
    ("stage3_iterations", 30.5, "stage3_iterations: expected an int, got 30.5 (a number)"),
    ("lr_means", "fast", "lr_means: expected a float, got 'fast' (a string)"),
    ("resolve_ambiguous_joints", 1, "resolve_ambiguous_joints: expected a bool, got 1"),
    ("pseudo_min_conf", 1.5, "pseudo_min_conf: must be <= 1, got 1.5"),
    ("lr_quats", 0, "lr_quats: must be > 0, got 0"),
    ("lambda_sam", -0.1, "lambda_sam: must be >= 0, got -0.1"),
    ("stage1_iterations", None, "stage1_iterations: expected an int, got null"),
])
def test_bad_config_values_are_one_line_naming_file_and_field(scene, tmp_path, capsys, field,
                                                              value, message):
    path = tmp_path / "bad.json"
    path.write_text(json.dumps({field: value}))
    out = tmp_path / "out"
    code, err = run_cli(["train", scene, "--out", out, "--config", path], capsys)
    assert code == 1
    assert err.startswith(f"gear: error: {path}: {message}") and "\n" not in err
    assert not out.exists()


def test_every_numeric_field_has_a_range():
    numeric = {name for name, value in json.loads(make_config("full").to_json()).items()
               if not isinstance(value, str | bool)}
    assert numeric == set(RANGES)


def test_every_field_is_type_checked():
    config = make_config("quick")
    for name, value in json.loads(config.to_json()).items():
        wrong = "1" if not isinstance(value, str) else 1
        with pytest.raises(ValueError, match=f"^{name}: expected"):
            config.replace(**{name: wrong})


# --- parts left without Gaussians are dropped ------------------------------------------------

def test_parts_without_gaussians_are_dropped_and_the_rest_renumbered():
    gen = torch.Generator().manual_seed(0)
    ids = torch.tensor([0, 1, 1, 3, 3, 3, 0])  # parts 2 and 4 have no Gaussians
    logits = torch.randn(7, 5, generator=gen) + 10 * torch.nn.functional.one_hot(ids, 5)
    g = Gaussians(dict(means=torch.randn(7, 3, generator=gen), quats=torch.randn(7, 4),
                       log_scales=torch.randn(7, 3), opacity=torch.randn(7),
                       colors=torch.randn(7, 3), logits=logits))
    motion = PartMotion(5)
    with torch.no_grad():
        motion.qr.copy_(torch.nn.functional.normalize(torch.randn(4, 4, generator=gen), dim=1))
        motion.qd.copy_(torch.randn(4, 4, generator=gen))
        motion.prismatic[3] = True
    kept, smaller, dropped = drop_empty_parts(g, motion)
    assert dropped == [2, 4]
    assert kept.num_parts == 3 and smaller.num_parts == 3
    assert kept.part_ids().tolist() == [0, 1, 1, 2, 2, 2, 0]
    before, after = motion.motion(1.0), smaller.motion(1.0)
    for b, a in zip(before, after, strict=True):
        assert torch.equal(a, b[[0, 1, 3]])
    assert smaller.prismatic.tolist() == [False, False, True]
    same = drop_empty_parts(kept, smaller)
    assert same[0] is kept and same[2] == []


def test_a_model_whose_every_movable_part_emptied_keeps_its_static_part():
    g = Gaussians(dict(means=torch.zeros(3, 3), quats=torch.tensor([[1.0, 0, 0, 0]] * 3),
                       log_scales=torch.zeros(3, 3), opacity=torch.zeros(3),
                       colors=torch.zeros(3, 3),
                       logits=torch.tensor([[5.0, 0.0, 0.0]] * 3)))  # all static
    kept, smaller, dropped = drop_empty_parts(g, PartMotion(3))
    assert dropped == [1, 2]
    assert kept.num_parts == 1 and smaller.num_parts == 1
    assert kept.part_ids().tolist() == [0, 0, 0]
    assert smaller.qr.shape[0] == 0 and smaller.qd.shape[0] == 0  # no movable part left


def test_more_parts_than_the_data_has_exports_no_empty_links(scene, tmp_path):
    result = train(scene, tmp_path / "out", make_config("quick", {**CONFIG, "num_parts": 8}),
                   quiet=True)
    ids = np.load(tmp_path / "out" / "parts.npy")
    joints = json.loads((tmp_path / "out" / "joints.json").read_text())["joints"]
    assert [j["part"] for j in joints] == list(range(1, len(joints) + 1))
    for joint in joints:  # every exported link has Gaussians
        assert (ids == joint["part"]).any()
    assert ids.max() <= len(joints)
    assert len(joints) < 7  # the fridge has one door: most of the 7 movable parts stay empty
    assert any(f"dropped {7 - len(joints)} part(s) left without Gaussians" in note
               for note in result.notes)


# --- reproducibility with the CPU executor ---------------------------------------------------

def test_seeded_runs_and_a_resumed_run_give_bit_identical_joints_with_the_cpu_executor(
        scene, tmp_path, monkeypatch):
    # The CPU executor sums every gradient in a fixed order (docs/raster-contract.md), so unlike
    # the wgpu one it makes a seeded run repeat exactly.
    monkeypatch.setenv("GEAR_BACKEND", "cpu")
    config = make_config("quick", CONFIG)
    train(scene, tmp_path / "first", config, quiet=True)
    train(scene, tmp_path / "second", config, quiet=True)
    with interrupted_at("stage3", 7), pytest.raises(KeyboardInterrupt):
        train(scene, tmp_path / "resumed", config, quiet=True)
    train(scene, tmp_path / "resumed", config, resume=True, quiet=True)
    first = (tmp_path / "first" / "joints.json").read_bytes()
    assert json.loads(first)["joints"]  # the door is there: the comparison is not vacuous
    for other in ("second", "resumed"):
        assert (tmp_path / other / "joints.json").read_bytes() == first
        assert np.array_equal(np.load(tmp_path / other / "parts.npy"),
                              np.load(tmp_path / "first" / "parts.npy"))
