"""`RUNS/summary.csv` and `RUNS/summary.md`: one row per scene (status, wall time, joints
found, the metrics when the scene has ground truth, the error when it failed) and the mean of
each metric over the scenes that have it."""

from __future__ import annotations

import csv
import io
from pathlib import Path

from gear.batch.outcome import Outcome
from gear.evaluate import SUMMARY
from gear.run_folder import write_atomic

CSV, MARKDOWN = "summary.csv", "summary.md"


def metric_means(outcomes: list[Outcome]) -> dict[str, float | None]:
    """The mean of each metric over the scenes where it was computed (None when none)."""
    means: dict[str, float | None] = {}
    for key, _ in SUMMARY:
        values = [o.metrics[key] for o in outcomes if o.metrics.get(key) is not None]
        means[key] = sum(values) / len(values) if values else None
    return means


def write_summary(runs: Path, outcomes: list[Outcome]) -> tuple[Path, Path]:
    """Both files, each written atomically; returns their paths."""
    outcomes = sorted(outcomes, key=lambda o: o.scene)
    means = metric_means(outcomes)
    write_atomic(runs / CSV, _csv(outcomes, means))
    write_atomic(runs / MARKDOWN, _markdown(outcomes, means))
    return runs / CSV, runs / MARKDOWN


def _csv(outcomes: list[Outcome], means: dict[str, float | None]) -> str:
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(["scene", "status", "wall_s", "joints", *(k for k, _ in SUMMARY), "peak_mb",
                     "attempts", "resumed_from", "error"])
    for o in outcomes:
        writer.writerow([o.scene, o.status, f"{o.seconds:.1f}", _blank(o.joints),
                         *(_blank(o.metrics.get(k)) for k, _ in SUMMARY),
                         _blank(None if o.peak_mb is None else round(o.peak_mb)), o.attempts,
                         o.resumed, o.error])
    writer.writerow(["mean", "", "", "", *(_blank(means[k]) for k, _ in SUMMARY), "", "", "",
                     ""])
    return out.getvalue()


def _markdown(outcomes: list[Outcome], means: dict[str, float | None]) -> str:
    shown = [(k, label) for k, label in SUMMARY if means[k] is not None]  # skip empty columns
    head = ["scene", "status", "wall (s)", "joints", *(label for _, label in shown)]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for o in outcomes:
        cells = [o.scene, o.status, f"{o.seconds:.0f}", _blank(o.joints),
                 *(_fmt(o.metrics.get(k)) for k, _ in shown)]
        lines.append("| " + " | ".join(cells) + " |")
    mean_row = ["**mean**", "", "", "", *(_fmt(means[k]) for k, _ in shown)]
    lines.append("| " + " | ".join(mean_row) + " |")
    done = sum(o.status == "done" for o in outcomes)
    text = [f"# Batch summary: {done} of {len(outcomes)} scene(s) done", "", *lines]
    failed = [o for o in outcomes if o.error]
    if failed:
        text += ["", "## Failed scenes", ""]
        text += [f"- **{o.scene}** ({o.status}): {o.error.replace('|', '/')}" for o in failed]
    resumed = [o for o in outcomes if o.resumed]
    if resumed:
        text += ["", "## Resumed from checkpoints", ""]
        text += [f"- {o.scene}: {o.resumed} ({o.attempts} attempts)" for o in resumed]
    return "\n".join(text) + "\n"


def _blank(value: object) -> str:
    return "" if value is None else str(value)


def _fmt(value: float | None) -> str:
    if value is None:
        return "-"
    return f"{value:.4f}" if abs(value) < 10 else f"{value:.2f}"
