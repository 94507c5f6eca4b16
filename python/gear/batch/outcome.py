"""One scene's result in a batch, kept in its run folder as `batch.json` (written atomically,
after everything else of the scene): `--resume` reads it to skip what is settled."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

from gear.run_folder import write_atomic

RECORD = "batch.json"
DONE, INVALID, FAILED = "done", "invalid", "failed"
# RUNS/.attempts/<scene>.log: a line per attempt started. Kept beside the run folders, not in
# them, so the run-folder machinery (which clears a run folder it replaces) never touches it.
ATTEMPTS = ".attempts"


@dataclass
class Outcome:
    scene: str
    # done: trained, exported (and evaluated when the scene has ground truth); invalid: failed
    # validation, not retried; failed: crashed, or its worker died, on every attempt.
    status: str
    seconds: float = 0.0  # wall time of the attempt that settled it
    joints: int | None = None
    metrics: dict[str, float | None] = field(default_factory=dict)  # gear.evaluate's summary
    error: str = ""
    resumed: str = ""  # where the attempts continued from a checkpoint, when they did
    peak_mb: float | None = None  # the task's peak resident memory
    attempts: int = 0  # attempts started on this scene (across `--resume`d batches)
    notes: list[str] = field(default_factory=list)
    fingerprint: dict[str, list[int]] | None = None  # scene files, when invalid

    def save(self, run_dir: Path) -> None:
        run_dir.mkdir(parents=True, exist_ok=True)
        write_atomic(run_dir / RECORD, json.dumps(asdict(self), indent=1) + "\n")

    @classmethod
    def load(cls, run_dir: Path) -> Outcome | None:
        """The recorded outcome, or None when there is none (or it cannot be read: the scene
        is then run again)."""
        try:
            return cls(**json.loads((run_dir / RECORD).read_text()))
        except (OSError, ValueError, TypeError):
            return None


def _attempt_log(run_dir: Path) -> Path:
    return run_dir.parent / ATTEMPTS / f"{run_dir.name}.log"


def record_attempt(run_dir: Path, who: str) -> int:
    """Notes an attempt starting on `run_dir`'s scene; returns how many have started."""
    path = _attempt_log(run_dir)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("a") as fh:  # one short append per attempt: lines never interleave
        fh.write(who + "\n")
    return count_attempts(run_dir)


def count_attempts(run_dir: Path) -> int:
    path = _attempt_log(run_dir)
    return len(path.read_text().splitlines()) if path.is_file() else 0


def forget_attempts(run_dir: Path) -> None:
    """A new batch on this scene counts from zero."""
    _attempt_log(run_dir).unlink(missing_ok=True)
