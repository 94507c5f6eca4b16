"""Runs the batch's scenes on Ray: one task per scene with its resources declared (CPUs,
memory), so Ray packs as many runs as fit on each machine; a crash or a dead worker is retried
(`retries`) and the retry continues from the run's last checkpoint (gear.batch.task).

Ray is imported here only: it is an optional extra (`pip install gear-twin[batch]`).
"""

from __future__ import annotations

import logging
import socket
from collections.abc import Callable
from pathlib import Path

from gear.batch.outcome import FAILED, Outcome, count_attempts
from gear.batch.progress import BatchProgress
from gear.batch.scenes import BatchError, BatchScene
from gear.batch.task import run_scene, thread_env
from gear.export.assembly import ExportOptions

INSTALL_HINT = "gear batch needs Ray: pip install 'gear-twin[batch]' (or pip install ray)"
CANCEL_GRACE_S = 60  # after Ctrl-C, how long running tasks get to save their checkpoints
PROBE_S = 5  # how long a cluster address gets to answer before Ray is asked to join it
POLL_S = 1.0


def ray_available() -> bool:
    try:
        import ray  # noqa: F401
    except ImportError:
        return False
    return True


def run_scenes(scenes: list[BatchScene], runs: Path, config_json: str,
               export_options: ExportOptions, *, address: str | None, cpus: int,
               memory_gb: float, retries: int, progress: BatchProgress,
               settled: Callable[[Outcome], None]) -> None:
    """Runs every scene; `settled(outcome)` is called as each one finishes for good. Joins
    the Ray cluster at `address` (or the one this process already joined; a local one when
    neither), and leaves a cluster it started itself shut down."""
    import ray

    started = not ray.is_initialized()
    if started:
        if address is not None:
            _probe(address)
        ray.init(address=address, include_dashboard=False, log_to_driver=False,
                 logging_level=logging.WARNING)
    try:
        slots = _slots(ray.cluster_resources(), cpus, memory_gb)
        # A fresh worker process per run (max_calls=1): no run inherits another's memory, GPU
        # device or thread settings, and the peak memory it reports is its own.
        task = ray.remote(max_calls=1)(run_scene).options(
            num_cpus=cpus, memory=int(memory_gb * 2**30), max_retries=retries,
            retry_exceptions=True, runtime_env={"env_vars": thread_env(cpus)})
        runs = runs.absolute()  # the workers' working folder is not the driver's
        pending = {task.remote(scene, str(runs / scene.name), config_json, export_options): scene
                   for scene in scenes}
        _collect(ray, pending, runs, slots, progress, settled)
    finally:
        if started:
            ray.shutdown()


def _probe(address: str) -> None:
    """A HOST:PORT (or ray://HOST:PORT) address that nothing answers on is one line now, not
    minutes of Ray retrying to connect."""
    host, sep, port = address.removeprefix("ray://").rpartition(":")
    if not sep or not port.isdigit():
        return  # "auto", or a form Ray resolves itself
    try:
        socket.create_connection((host, int(port)), timeout=PROBE_S).close()
    except OSError as err:
        raise BatchError(f"--address {address}: no Ray cluster answers there "
                         f"({err.strerror or err}); start one with `ray start --head`") from None


def _slots(resources: dict, cpus: int, memory_gb: float) -> int:
    """How many runs the cluster holds at once; a batch no node can run is refused up front
    (Ray would otherwise wait forever)."""
    total_cpus = resources.get("CPU", 0)
    if total_cpus < cpus:
        raise BatchError(f"--cpus-per-run {cpus}: the Ray cluster has {total_cpus:g} CPU(s)")
    total_gb = resources.get("memory", 0) / 2**30
    if total_gb < memory_gb:
        raise BatchError(f"--memory-per-run {memory_gb:g}: the Ray cluster has {total_gb:.1f} GB "
                         "for tasks")
    return max(1, min(int(total_cpus // cpus), int(total_gb // memory_gb)))


def _collect(ray, pending: dict, runs: Path, slots: int,  # noqa: ANN001 (Ray module)
             progress: BatchProgress, settled: Callable[[Outcome], None]) -> None:
    try:
        while pending:
            # Tasks beyond the cluster's slots wait in Ray's queue: "running" counts the others.
            progress.update(min(len(pending), slots))
            ready, _ = ray.wait(list(pending), num_returns=1, timeout=POLL_S)
            for ref in ready:
                scene = pending.pop(ref)
                outcome = _result(ray, ref, scene)
                outcome.attempts = outcome.attempts or count_attempts(runs / scene.name)
                settled(outcome)
                progress.finished(outcome, min(len(pending), slots))
    except KeyboardInterrupt:
        # Cancelling raises KeyboardInterrupt in each running task: train saves a checkpoint
        # (as on Ctrl-C), so `--resume` continues from here.
        for ref in pending:
            ray.cancel(ref)
        ray.wait(list(pending), num_returns=len(pending), timeout=CANCEL_GRACE_S)
        raise


def _result(ray, ref, scene: BatchScene) -> Outcome:  # noqa: ANN001 (Ray module and ref)
    """The task's outcome, or a `failed` one with the last error once Ray gave up."""
    try:
        return ray.get(ref)
    except ray.exceptions.RayTaskError as err:  # the run raised on every attempt
        cause = err.cause if err.cause is not None else err
        return Outcome(scene.name, FAILED, error=f"{type(cause).__name__}: {cause}"
                       .replace("\n", " ")[:500])
    except ray.exceptions.RayError as err:  # its worker died on every attempt, or similar
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        return Outcome(scene.name, FAILED, error=f"{type(err).__name__}: {first}"[:500])
