"""`gear batch` on a local Ray with 2 CPUs, started here: a batch of two good tiny scenes and a
broken one (the good ones finish with outputs and summary rows, the broken one is reported
with its validation message and not retried); a run whose worker is killed mid-run is retried
and resumes from its checkpoint; a second `--resume` does no work."""

from __future__ import annotations

import contextlib
import csv
import io
import json
import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from gear.batch.outcome import Outcome
from gear.batch.plan import plan_batch
from gear.batch.scenes import BatchError, list_scenes
from gear.cli import main
from gear.run_folder import COMPLETE, LOCK
from gear.synth import generate

ray = pytest.importorskip("ray")

# The quick profile cut to a few dozen iterations (48 px, 4 views: seconds per run), and the
# cheapest collision decomposition: the test is about the batch, not the twin's quality.
CONFIG = dict(stage1_iterations=40, stage3_iterations=30, em_interval=5, densify_from=10,
              densify_until=30, densify_interval=10, stage3_densify_until=15,
              joint_classify_iteration=15, classify_tune_steps=2, checkpoint_every=10,
              init_max_points=600, max_gaussians=1200, num_parts=2, mesh_voxel=0.06,
              mesh_trunc=0.18)
CHEAP_EXPORT = ["--concavity", "1", "--max-pieces", "1", "--faces", "500"]
BROKEN_IMAGE = "end/train/rgba/0000.png"


@pytest.fixture(scope="module")
def local_ray():
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False,
             logging_level=logging.WARNING)
    yield ray.get_runtime_context().gcs_address
    ray.shutdown()


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("scenes")
    generate("fridge", root / "fridge", res=48, views=4, test_views=1)
    generate("drawer_cabinet", root / "drawer", res=48, views=4, test_views=1)
    shutil.copytree(root / "fridge", root / "broken")
    (root / "broken" / BROKEN_IMAGE).write_bytes(b"\x89PNG truncated")
    return root


def write_config(folder: Path, **changes: object) -> Path:
    path = folder / "batch_config.json"
    path.write_text(json.dumps({**CONFIG, **changes}))
    return path


def run_batch(argv: list) -> tuple[int, str, str]:
    """`gear batch` in this process (on the Ray the fixture started): exit code and output."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(["batch", *map(str, argv), "--quiet"])
    return code, out.getvalue(), err.getvalue()


def summary_rows(runs: Path) -> dict[str, dict]:
    with (runs / "summary.csv").open() as fh:
        return {row["scene"]: row for row in csv.DictReader(fh)}


@pytest.fixture(scope="module")
def first_batch(local_ray, scenes, tmp_path_factory):
    runs = tmp_path_factory.mktemp("batch") / "runs"
    config = write_config(runs.parent)
    t0 = time.perf_counter()
    code, out, err = run_batch([scenes, "--out", runs, "--profile", "quick", "--config", config,
                                "--cpus-per-run", 1, "--memory-per-run", 1, *CHEAP_EXPORT])
    return runs, config, code, out, err, time.perf_counter() - t0


def test_two_good_scenes_finish_and_the_broken_one_is_reported_not_retried(first_batch):
    runs, _config, code, out, err, seconds = first_batch
    print(f"batch of 3 scenes, 2 concurrent runs: {seconds:.1f} s")
    assert code == 1, err  # one scene failed: the batch says so in its exit code
    rows = summary_rows(runs)
    assert sorted(rows) == ["broken", "drawer", "fridge", "mean"]
    for name in ("fridge", "drawer"):
        row, run = rows[name], runs / name
        assert row["status"] == "done" and row["error"] == "" and row["attempts"] == "1"
        assert (run / COMPLETE).is_file() and (run / "export" / f"{name}.urdf").is_file()
        assert (run / "export" / f"{name}.xml").is_file()
        assert int(row["joints"]) == len(json.loads((run / "joints.json").read_text())["joints"])
        # Each scene has ground truth, so it was evaluated; the row holds metrics.json's values.
        metrics = json.loads((run / "metrics.json").read_text())
        assert float(row["part_iou"]) == pytest.approx(metrics["part_iou"])
        assert 0 < float(row["part_iou"]) <= 1 and float(row["cd_w"]) > 0
        assert f"{name}: done in " in out
    means = rows["mean"]
    assert float(means["part_iou"]) == pytest.approx(
        (float(rows["fridge"]["part_iou"]) + float(rows["drawer"]["part_iou"])) / 2)
    broken = rows["broken"]
    assert broken["status"] == "invalid" and broken["attempts"] == "1"  # never retried
    assert f"{BROKEN_IMAGE}: unreadable image" in broken["error"]
    assert not (runs / "broken" / "log.jsonl").exists()  # stopped before any training
    assert "broken: invalid in " in out and BROKEN_IMAGE in out
    markdown = (runs / "summary.md").read_text()
    assert "2 of 3 scene(s) done" in markdown and "| **mean** |" in markdown
    assert f"**broken** (invalid): invalid scene: {BROKEN_IMAGE}" in markdown


def test_a_second_resume_does_no_work(first_batch, scenes):
    runs, config, *_ = first_batch
    before = {p: p.stat().st_mtime_ns for p in runs.rglob("*") if p.is_file()
              and not p.name.startswith("summary.")}
    t0 = time.perf_counter()
    code, out, _ = run_batch([scenes, "--out", runs, "--profile", "quick", "--config", config,
                              "--resume"])
    assert "3 scene(s), 3 settled earlier (skipped), 0 to run" in out
    assert code == 1  # the broken scene is still broken: reported again from its record
    after = {p: p.stat().st_mtime_ns for p in runs.rglob("*") if p.is_file()
             and not p.name.startswith("summary.")}
    assert after == before  # no file written or touched: no scene ran
    assert summary_rows(runs)["fridge"]["status"] == "done"
    print(f"second --resume: {time.perf_counter() - t0:.2f} s")


def test_resume_checks_a_scene_that_failed_validation_again_once_its_files_change(
        first_batch, scenes):
    runs, *_ = first_batch
    image = scenes / "broken" / BROKEN_IMAGE
    stamp = image.stat().st_mtime_ns
    try:
        os.utime(image, ns=(stamp + 10**9, stamp + 10**9))  # "fixed" by the user
        plan = plan_batch(scenes, runs, resume=True)
        assert [s.name for s in plan.todo] == ["broken"]
        assert sorted(o.scene for o in plan.settled) == ["drawer", "fridge"]
    finally:
        os.utime(image, ns=(stamp, stamp))


def test_a_killed_worker_is_retried_and_the_retry_resumes(local_ray, scenes, tmp_path):
    runs = tmp_path / "runs"
    listing = tmp_path / "scenes.txt"
    listing.write_text(f"# one scene, given by a list file\n{scenes / 'fridge'}\n")
    # Long enough a stage 1 to be killed in, with frequent checkpoints.
    config = write_config(tmp_path, stage1_iterations=400, checkpoint_every=20)
    # The batch runs in its own process joining the test's Ray by --address, as on a cluster.
    proc = subprocess.Popen(
        [sys.executable, "-m", "gear", "batch", str(listing), "--out", str(runs), "--profile",
         "quick", "--config", str(config), "--address", local_ray, "--retries", "1",
         "--memory-per-run", "1", "--quiet", *CHEAP_EXPORT],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    run = runs / "fridge"
    try:
        killed = None
        deadline = time.monotonic() + 300
        while killed is None and proc.poll() is None and time.monotonic() < deadline:
            if (run / "checkpoints" / "last.pt").is_file():
                holder = _lock_holder(run)
                if holder is not None:
                    killed = holder
                    os.kill(killed, signal.SIGKILL)  # the worker dies mid-run, as on OOM
            time.sleep(0.05)
        assert killed is not None, "the run never reached a checkpoint"
        out, err = proc.communicate(timeout=600)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, out + err
    outcome = Outcome.load(run)
    assert outcome.status == "done" and outcome.attempts == 2
    assert outcome.resumed.startswith("stage1 iteration ")
    log = (run / "log.jsonl").read_text()
    assert f"took over a stale lock in {run} (left by PID {killed}" in log
    assert (run / COMPLETE).is_file() and (run / "export" / "fridge.urdf").is_file()
    assert "fridge: done in " in out and "2 attempts" in out


def _lock_holder(run: Path) -> int | None:
    """The PID in the run's lock file; None while there is none (or it is being written)."""
    try:
        return json.loads((run / LOCK).read_text()).get("pid")
    except (OSError, ValueError):
        return None


def test_without_ray_the_command_says_how_to_install_it(scenes, tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray raises ImportError
    code = main(["batch", str(scenes), "--out", str(tmp_path / "runs")])
    err = capsys.readouterr().err.strip()
    assert code == 1
    assert err == ("gear: error: gear batch needs Ray: pip install 'gear-twin[batch]' "
                   "(or pip install ray)")
    assert not (tmp_path / "runs").exists()


def test_an_address_where_no_cluster_answers_is_one_line(scenes, tmp_path):
    with socket.socket() as free:  # a port nothing listens on
        free.bind(("127.0.0.1", 0))
        port = free.getsockname()[1]
    # In its own process: this one may be joined to the test's Ray already.
    proc = subprocess.run([sys.executable, "-m", "gear", "batch", str(scenes), "--out",
                           str(tmp_path / "runs"), "--address", f"127.0.0.1:{port}", "--quiet"],
                          capture_output=True, text=True, timeout=300)
    err = proc.stderr.strip()
    assert proc.returncode == 1
    assert err.startswith(f"gear: error: --address 127.0.0.1:{port}: no Ray cluster answers "
                          "there (Connection refused)") and "\n" not in err


def test_a_new_batch_over_an_earlier_ones_runs_is_refused(first_batch, scenes, capsys):
    runs, *_ = first_batch
    code = main(["batch", str(scenes), "--out", str(runs)])
    err = capsys.readouterr().err.strip()
    assert code == 1 and "\n" not in err
    assert err == (f"gear: error: --out {runs}: already holds runs of broken, drawer, fridge; "
                   "continue that batch with --resume, or choose another folder")


def test_scene_lists_resolve_relative_paths_and_refuse_clashing_names(scenes, tmp_path):
    listing = tmp_path / "list.txt"
    listing.write_text(f"\n# comment\n{scenes / 'fridge'}\n")
    assert [(s.name, s.path) for s in list_scenes(listing)] == [("fridge", scenes / "fridge")]
    (tmp_path / "a" / "fridge").mkdir(parents=True)
    listing.write_text("a/fridge\n")  # relative to the list's folder, not to the working one
    assert [s.path for s in list_scenes(listing)] == [tmp_path / "a" / "fridge"]
    listing.write_text(f"{scenes / 'fridge'}\na/fridge\n")
    with pytest.raises(BatchError, match="two scenes would share the run folder 'fridge'"):
        list_scenes(listing)
    with pytest.raises(BatchError, match="no such folder or scene list"):
        list_scenes(tmp_path / "missing")
