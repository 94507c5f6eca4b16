"""What a batch has to do: which scenes run, and which are settled already (`--resume`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from gear.batch.outcome import DONE, INVALID, Outcome, forget_attempts
from gear.batch.scenes import BatchError, BatchScene, files_fingerprint, list_scenes
from gear.run_folder import COMPLETE, writable_folder


@dataclass
class Plan:
    todo: list[BatchScene]
    settled: list[Outcome]  # scenes `--resume` skips, with their recorded outcomes

    def describe(self, cpus: int) -> str:
        total = len(self.todo) + len(self.settled)
        skipped = f", {len(self.settled)} settled earlier (skipped)" if self.settled else ""
        return (f"gear batch: {total} scene(s){skipped}, {len(self.todo)} to run with {cpus} "
                "CPU(s) each")


def plan_batch(spec: Path, runs: Path, *, resume: bool) -> Plan:
    """Without `resume`, every scene's run folder must be new or empty (a batch never mixes
    with an earlier one). With it, a scene is skipped when it finished, or when it failed
    validation and its files have not changed since; every other scene runs, continuing
    whatever its folder holds."""
    scenes = list_scenes(spec)
    writable_folder(runs)
    todo: list[BatchScene] = []
    settled: list[Outcome] = []
    busy: list[str] = []
    for scene in scenes:
        run_dir = runs / scene.name
        if not resume:
            if run_dir.is_dir() and any(run_dir.iterdir()):
                busy.append(scene.name)
            todo.append(scene)
            continue
        outcome = Outcome.load(run_dir)
        if outcome is not None and _settled(outcome, run_dir, scene):
            settled.append(outcome)
        else:
            todo.append(scene)
    if busy:
        shown = ", ".join(busy[:3]) + (f" and {len(busy) - 3} more" if len(busy) > 3 else "")
        raise BatchError(f"--out {runs}: already holds runs of {shown}; continue that batch with "
                         "--resume, or choose another folder")
    if not resume:
        for scene in todo:
            forget_attempts(runs / scene.name)
    return Plan(todo, settled)


def _settled(outcome: Outcome, run_dir: Path, scene: BatchScene) -> bool:
    if outcome.status == DONE:
        return (run_dir / COMPLETE).is_file()
    return outcome.status == INVALID and outcome.fingerprint == files_fingerprint(scene.path)
