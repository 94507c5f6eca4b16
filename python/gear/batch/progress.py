"""The batch's progress: one bar over the scenes (done / running / failed) and a line per
finished scene printed above it."""

from __future__ import annotations

from tqdm import tqdm

from gear.batch.outcome import DONE, Outcome


def describe(outcome: Outcome) -> str:
    """One line on a finished scene: its status, time, joints and headline metrics, or why it
    failed."""
    head = f"{outcome.scene}: {outcome.status} in {outcome.seconds:.0f} s"
    if outcome.status != DONE:
        return f"{head}: {outcome.error}"
    parts = [f"{outcome.joints} joint(s)"]
    for key, label in (("axis_ang", "Axis Ang"), ("geo_dist_deg", "Geo Dist"),
                       ("part_iou", "Part IoU")):
        value = outcome.metrics.get(key)
        if value is not None:
            parts.append(f"{label} {value:.3g}")
    if outcome.resumed:
        parts.append(f"resumed from {outcome.resumed}")
    if outcome.attempts > 1:
        parts.append(f"{outcome.attempts} attempts")
    return f"{head}: " + ", ".join(parts)


class BatchProgress:
    """`update` with the current counts; `finished` for each settled scene."""

    def __init__(self, total: int, quiet: bool = False) -> None:
        self.quiet = quiet
        self._bar = tqdm(total=total, desc="batch", unit="scene", disable=quiet)
        self._done = self._failed = 0
        self._shown = ""

    def update(self, running: int) -> None:
        counts = f"done {self._done}, running {running}, failed {self._failed}"
        if counts != self._shown:  # redraw on change only: a quiet log when output is a file
            self._shown = counts
            self._bar.set_postfix_str(counts)

    def finished(self, outcome: Outcome, running: int) -> None:
        if outcome.status == DONE:
            self._done += 1
        else:
            self._failed += 1
        line = describe(outcome)
        if self.quiet:
            print(line, flush=True)
        else:
            self._bar.write(line)
        self._bar.update(1)
        self.update(running)

    def close(self) -> None:
        self._bar.close()
