"""Running a stage: progress bar, log.jsonl, Ctrl-C and checkpoints (docs/architecture.md,
"Checkpoints"). Knows nothing of the method: a stage object brings `step(it)`, `phase(it)`,
`status()`, `snapshot()` and `checkpoint()`; a finished stage hands over its result's
checkpoint form."""

from __future__ import annotations

import json
import signal
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Protocol

import numpy as np
import torch
from tqdm import tqdm

from gear import checkpoint
from gear.config import TrainConfig


class RunLog:
    """log.jsonl (one JSON object per line) plus the console, unless quiet."""

    def __init__(self, path: Path, quiet: bool, append: bool) -> None:
        self.path, self.quiet = path, quiet
        self._fh = open(path, "a" if append else "w")  # a resumed run continues its log

    def write(self, record: dict) -> None:
        self._fh.write(json.dumps(record, default=_jsonable) + "\n")
        self._fh.flush()

    def say(self, message: str) -> None:
        self.write({"message": message})
        if not self.quiet:
            tqdm.write(message)

    def close(self) -> None:
        self._fh.close()


def _jsonable(value: object) -> object:
    if isinstance(value, np.ndarray | torch.Tensor):
        return np.asarray(value).tolist()
    if isinstance(value, np.generic):
        return value.item()
    return str(value)


# Ctrl-C, `kill` / a scheduler's stop (SIGTERM) and a closed terminal (SIGHUP) all end a run
# the same way: with a checkpoint.
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


@contextmanager
def stops_interrupt() -> Iterator[None]:
    """For a whole run, SIGTERM and SIGHUP raise KeyboardInterrupt as Ctrl-C does, so a stop
    outside the iterations (stage 2, the outputs) still unwinds: the output folder is released
    and the last checkpoint stays the run's state. Inside `Runner.run`, `_Interrupt` takes over
    and saves a checkpoint first."""
    previous = {sig: signal.signal(sig, signal.default_int_handler) for sig in STOP_SIGNALS}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


class _Interrupt:
    """Turns the stop signals into a flag checked between iterations, so the checkpoint written
    on interruption is a consistent iteration boundary."""

    def __init__(self) -> None:
        self.requested = False

    def __enter__(self) -> _Interrupt:
        self._previous = {sig: signal.signal(sig, self._handler) for sig in STOP_SIGNALS}
        return self

    def _handler(self, _sig: int, _frame: object) -> None:
        self.requested = True

    def __exit__(self, *exc: object) -> None:
        for sig, previous in self._previous.items():
            signal.signal(sig, previous)


class IterativeStage(Protocol):
    name: str
    events: list[dict]

    def step(self, it: int) -> dict[str, float]: ...
    def gaussian_count(self) -> int | dict[str, int]: ...
    def phase(self, it: int) -> str | None: ...
    def status(self) -> str | None: ...
    def snapshot(self) -> dict: ...
    def checkpoint(self) -> dict: ...


class Runner:
    """One training run's bookkeeping in OUT_DIR: the log, the timings, the results of the
    finished stages and the checkpoint that holds them with the stage under way."""

    def __init__(self, out_dir: Path, config: TrainConfig, quiet: bool,
                 resumed: dict | None = None, scene: dict | None = None) -> None:
        self.config, self.quiet = config, quiet
        self.scene = scene  # the scene's fingerprint, checked on resume
        self.ckpt_dir = out_dir / "checkpoints"
        self.log = RunLog(out_dir / "log.jsonl", quiet, append=resumed is not None)
        self.timings: dict[str, float] = dict(resumed["timings"]) if resumed else {}
        # Checkpoint forms of the finished stages' results, by key ("models", "coarse").
        self.results: dict[str, object] = {}

    def finished(self, key: str, result: object) -> None:
        """Records a finished stage's result (its checkpoint form) for every later save."""
        self.results[key] = result

    def save(self, stage_name: str, iteration: int, stage: IterativeStage | None = None) -> None:
        payload = {
            "stage": stage_name,
            "iteration": iteration,
            "config": json.loads(self.config.to_json()),
            "scene": self.scene,
            **self.results,
            "timings": dict(self.timings),
        }
        if stage is not None:
            payload.update(stage.checkpoint())
        path = checkpoint.save(self.ckpt_dir, payload)
        self.log.write({"event": "checkpoint", "stage": stage_name, "iteration": iteration,
                        "path": str(path)})

    def timed(self, name: str, seconds: float) -> None:
        self.timings[name] = self.timings.get(name, 0.0) + seconds

    def write_events(self, stage: IterativeStage, **extra: object) -> None:
        """Logs the events `stage` has gathered (with the `extra` fields) and clears them."""
        for event in stage.events:
            self.log.write({"stage": stage.name, **extra, **event})
        stage.events.clear()

    def run(self, stage: IterativeStage, start: int, total: int) -> None:
        """Iterations start..total-1 of `stage`, with progress, logging and checkpoints; on
        Ctrl-C, SIGTERM or SIGHUP, a checkpoint at the iteration boundary and
        KeyboardInterrupt."""
        c = self.config
        bar = tqdm(total=total, initial=start, desc=stage.name, disable=self.quiet,
                   dynamic_ncols=True, leave=True)
        t0 = time.perf_counter()
        previous_phase = None
        with _Interrupt() as interrupt:
            for it in range(start, total):
                phase = stage.phase(it)
                if phase is not None and phase != previous_phase:
                    self.log.write({"event": "phase", "stage": stage.name, "iteration": it,
                                    "phase": phase, **stage.snapshot()})
                previous_phase = phase
                terms = stage.step(it)
                self.write_events(stage)
                if it % c.log_every == 0 or it + 1 == total:
                    count = stage.gaussian_count()
                    record = {"stage": stage.name, "iteration": it, "gaussians": count,
                              **({"phase": phase} if phase else {}), **terms}
                    self.log.write(record)
                    postfix = " ".join(f"{k}={v:.4f}" for k, v in terms.items())
                    status = stage.status()
                    if status is not None:
                        postfix += " " + status
                    n = "+".join(map(str, count.values())) if isinstance(count, dict) else count
                    bar.set_postfix_str(f"n={n} {postfix}", refresh=False)
                bar.update(1)
                done = it + 1
                if interrupt.requested:
                    self.timed(stage.name, time.perf_counter() - t0)
                    self.save(stage.name, done, stage)
                    bar.close()
                    message = (f"interrupted: checkpoint saved at {stage.name} iteration {done}; "
                               "continue with --resume")
                    self.log.write({"message": message})
                    print(message, file=sys.stderr)
                    raise KeyboardInterrupt
                if done % c.checkpoint_every == 0 and done < total:
                    self.save(stage.name, done, stage)
        bar.close()
        elapsed = time.perf_counter() - t0
        self.timed(stage.name, elapsed)
        self.log.write({"event": "stage_done", "stage": stage.name, "seconds": elapsed})
