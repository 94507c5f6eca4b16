"""One scene of a batch, run inside a Ray worker: train (or continue what an earlier attempt
left), export, and evaluate when the scene has ground truth, all into RUNS/<scene>/ through the
run-folder machinery (gear.run_folder: lock, completion marker, resume).

A validation failure comes back as an `invalid` outcome, so Ray never retries it; anything else
raises, and Ray retries the task, whose next attempt continues from the run's last checkpoint.
"""

from __future__ import annotations

import json
import os
import resource
import socket
import time
from pathlib import Path

from gear.batch.outcome import DONE, INVALID, Outcome, record_attempt
from gear.batch.scenes import BatchScene, files_fingerprint
from gear.checkpoint import LAST
from gear.cli import UserError
from gear.config import TrainConfig
from gear.data import SceneError, load_scene
from gear.export.assembly import ExportOptions
from gear.run_folder import COMPLETE, RUN_ENTRIES, RunFolderError, is_export, write_atomic

EXPORT = "export"  # the scene's URDF + MJCF folder inside its run folder
# Problems with the input, not the run: retrying cannot help.
VALIDATION_ERRORS = (SceneError, RunFolderError, UserError)


def thread_env(cpus: int) -> dict[str, str]:
    """Environment of a task's worker: every thread pool a run uses sized to its CPUs (torch,
    the CPU rasterizer, lavapipe, OpenMP in the mesh and convex-decomposition libraries), so
    runs packed on one machine do not oversubscribe it."""
    n = str(cpus)
    return {"GEAR_TORCH_THREADS": n, "GEAR_THREADS": n, "LP_NUM_THREADS": n,
            "OMP_NUM_THREADS": n}


def run_scene(scene: BatchScene, run_dir: str, config_json: str,
              export_options: ExportOptions) -> Outcome:
    """The whole pipeline on `scene` into `run_dir`; raises on a crash (for Ray to retry)."""
    run = Path(run_dir)
    t0 = time.perf_counter()
    attempts = record_attempt(run, f"pid {os.getpid()} on {socket.gethostname()} at "
                                   f"{time.strftime('%Y-%m-%d %H:%M:%S %Z')}")
    try:
        notes = _train(scene, run, TrainConfig(**json.loads(config_json)))
    except VALIDATION_ERRORS as err:
        outcome = Outcome(scene.name, INVALID, error=_one_line(err),
                          fingerprint=files_fingerprint(scene.path))
    else:
        notes += _export(run, scene.name, export_options)
        joints = json.loads((run / "joints.json").read_text())["joints"]
        outcome = Outcome(scene.name, DONE, joints=len(joints), metrics=_evaluate(run, scene),
                          resumed=_resumed(run), notes=notes)
    outcome.seconds = time.perf_counter() - t0
    outcome.attempts = attempts
    outcome.peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux
    return outcome


def _train(scene: BatchScene, run: Path, config: TrainConfig) -> list[str]:
    """Trains unless an earlier attempt finished; continues an attempt that left a checkpoint,
    and replaces one that stopped before its first checkpoint (nothing to continue)."""
    from gear.train import train

    if (run / COMPLETE).is_file():
        return []
    if (run / "checkpoints" / LAST).is_file():
        mode = {"resume": True}
    elif run.is_dir() and any(p.name in RUN_ENTRIES or is_export(p) for p in run.iterdir()):
        mode = {"overwrite": True}
    else:
        mode = {}
    return train(scene.path, run, config, quiet=True, **mode).notes


def _export(run: Path, name: str, options: ExportOptions) -> list[str]:
    """URDF and MJCF in RUNS/<scene>/export/ (kept when an earlier attempt wrote it: an export
    folder appears whole or not at all); round-trip problems become notes."""
    from gear.export.bundle import export_twin
    from gear.export.urdf import roundtrip_errors

    folder = run / EXPORT
    if is_export(folder):
        return []
    result = export_twin(run, folder, folder, name=name, options=options, quiet=True)
    try:
        problems = roundtrip_errors(result.urdf, result.assembly)
    except ValueError as err:
        problems = [f"gear's URDF reader refused the file ({err})"]
    return result.notes + [f"export round-trip: {p}" for p in problems]


def _evaluate(run: Path, scene: BatchScene) -> dict[str, float | None]:
    """gear.evaluate's summary metrics, written to metrics.json as `gear eval` does; empty when
    the scene has no ground truth."""
    from gear.evaluate import SUMMARY, evaluate

    loaded = load_scene(scene.path)
    if loaded.gt is None:
        return {}
    metrics = evaluate(run, scene.path, scene=loaded)
    write_atomic(run / "metrics.json", json.dumps(metrics, indent=2) + "\n")
    return {key: metrics.get(key) for key, _ in SUMMARY}


def _resumed(run: Path) -> str:
    """Where the run's attempts continued from checkpoints, from its log."""
    points = []
    for line in (run / "log.jsonl").read_text().splitlines():
        try:
            message = json.loads(line).get("message", "")
        except ValueError:
            continue  # a line cut short by a killed attempt
        if message.startswith("resuming from "):
            points.append(message.removeprefix("resuming from "))
    return "; ".join(points)


def _one_line(err: Exception) -> str:
    if isinstance(err, SceneError):
        return "invalid scene: " + "; ".join(err.problems)
    return str(err).replace("\n", " ")
