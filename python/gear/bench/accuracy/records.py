"""The accuracy benchmark's records: one `Run` per training + evaluation, their CSV form, the
markdown table and the plots (docs/evaluation.md)."""

from __future__ import annotations

import csv
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

# metrics.json key, column/plot label, log-scale axis
METRICS = [
    ("axis_ang", "Axis Ang (deg)", True),
    ("axis_pos", "Axis Pos (x10)", True),
    ("geo_dist_deg", "Geo Dist rev (deg)", True),
    ("geo_dist_m", "Geo Dist pri", True),
    ("cd_s", "CD-s", True),
    ("cd_m", "CD-m", True),
    ("cd_w", "CD-w", True),
    ("part_iou", "Part IoU", False),
    ("psnr", "PSNR (dB)", False),
]
# A part whose surface moves less than this in the training images is below what any image
# method can see (gear.bench.accuracy.visibility).
VISIBLE_PX = 1.0
# The pipeline's timed steps in the order they run (training's `timings` keys) and their column
# labels: stage 1 (both states at once; runs of older versions timed the start (A) and end (B)
# state one after the other), stage 2, stage 3, writing the outputs.
STAGES = {"stage1": "stage 1", "stage1-start": "stage 1 A", "stage1-end": "stage 1 B",
          "stage2": "stage 2", "stage3": "stage 3", "outputs": "outputs"}


@dataclass
class Run:
    """One training + evaluation: what was run, how long each stage took, what it scored."""

    scene: str
    budget: str
    variant: str = "default"
    iterations: int = 0  # stage-1 iterations per state (= stage-3 iterations)
    timings: dict[str, float] = field(default_factory=dict)
    metrics: dict[str, float | None] = field(default_factory=dict)
    type_mismatches: int = 0
    status: str = "ok"
    # Structure found vs true: part count K (static included) and joint types ("2R+1P").
    parts_true: int | None = None
    parts_found: int | None = None
    types_true: str = ""
    types_found: str = ""
    # Process CPU time of training (every thread): on a shared machine wall times vary with the
    # load, CPU times compare.
    cpu_seconds: float | None = None
    # How many pixels each true moving part's surface moves between the states in the training
    # images (trans_info order; empty when unknown).
    part_motion_px: list[float] = field(default_factory=list)
    # The true joint types of the parts that move VISIBLE_PX or more ("" when unknown).
    types_visible: str = ""

    @property
    def parts_visible(self) -> int | None:
        """True part count (static included) counting only parts that move a pixel or more."""
        if not self.part_motion_px:
            return None
        return 1 + sum(px >= VISIBLE_PX for px in self.part_motion_px)

    def structure_right(self, visible: bool = False) -> bool | None:
        """Whether K and the joint types found are the true ones (with `visible`, those of the
        parts that move a pixel or more); None when either is unknown."""
        parts, types = ((self.parts_visible, self.types_visible) if visible
                        else (self.parts_true, self.types_true))
        if self.status != "ok" or parts is None or self.parts_found is None or not types:
            return None
        return parts == self.parts_found and types == self.types_found

    @property
    def total_seconds(self) -> float:
        return float(sum(self.timings.values()))

    def row(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "scene": self.scene, "budget": self.budget, "variant": self.variant,
            "iterations": self.iterations, "total_s": round(self.total_seconds, 2),
            "cpu_s": None if self.cpu_seconds is None else round(self.cpu_seconds, 2),
        }
        out.update({f"time_{k}_s": round(v, 2) for k, v in sorted(self.timings.items())})
        out.update({key: self.metrics.get(key) for key, _, _ in METRICS})
        out["type_mismatches"] = self.type_mismatches
        out.update({"parts_true": self.parts_true, "parts_found": self.parts_found,
                    "types_true": self.types_true, "types_found": self.types_found})
        out["part_motion_px"] = ";".join(f"{px:.3g}" for px in self.part_motion_px) or None
        out["types_visible"] = self.types_visible
        out["status"] = self.status
        return out


def write_csv(records: Sequence[Run], path: Path) -> None:
    rows = [r.row() for r in records]
    columns: list[str] = []
    for row in rows:
        columns += [c for c in row if c not in columns]
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=columns)
        writer.writeheader()
        for row in rows:
            writer.writerow({c: "" if row.get(c) is None else row.get(c) for c in columns})


def read_csv(path: Path) -> list[Run]:
    """The runs of an accuracy.csv written by `write_csv` (for --append)."""
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))

    def number(text: str | None) -> float | None:
        return float(text) if text else None

    records = []
    for row in rows:
        timings = {key[len("time_"):-len("_s")]: float(value) for key, value in row.items()
                   if key.startswith("time_") and key.endswith("_s") and value}
        records.append(Run(
            row["scene"], row["budget"], row["variant"], int(row["iterations"] or 0), timings,
            {key: number(row.get(key)) for key, _, _ in METRICS},
            int(row["type_mismatches"] or 0), row["status"],
            _integer(row.get("parts_true")), _integer(row.get("parts_found")),
            row.get("types_true") or "", row.get("types_found") or "", number(row.get("cpu_s")),
            [float(px) for px in (row.get("part_motion_px") or "").split(";") if px],
            row.get("types_visible") or "",
        ))
    return records


def _integer(text: str | None) -> int | None:
    return int(float(text)) if text else None


def type_counts(types: Sequence[str]) -> str:
    """["revolute", "prismatic", "revolute"] -> "2R+1P" (order-free, so found and true compare
    as text); "-" for no joints."""
    revolute = sum(t in ("revolute", "rotate") for t in types)
    prismatic = sum(t in ("prismatic", "translate") for t in types)
    parts = [f"{n}{letter}" for n, letter in ((revolute, "R"), (prismatic, "P")) if n]
    return "+".join(parts) or "-"


def _cell(value: float | None) -> str:
    if value is None or not math.isfinite(value):
        return "-"
    return f"{value:.3f}" if abs(value) < 100 else f"{value:.1f}"


def markdown_table(records: Sequence[Run], machine: str) -> str:
    """One row per run: budget, stage times (in the order the stages run), metrics; failures
    shown as such."""
    timed = {k for r in records for k in r.timings}
    stages = [s for s in STAGES if s in timed] + sorted(timed - set(STAGES))
    header = ["scene", "budget", "variant", "iters",
              *[f"{STAGES.get(s, s)} (s)" for s in stages], "total (s)", "CPU (s)",
              *[label for _, label, _ in METRICS], "type mism."]
    lines = [f"Machine: {machine}", "", "| " + " | ".join(header) + " |",
             "|" + "---|" * len(header)]
    for r in records:
        cells = [r.scene, r.budget, r.variant, str(r.iterations)]
        cells += [_cell(r.timings.get(s)) for s in stages]
        cells += [_cell(r.total_seconds), _cell(r.cpu_seconds)]
        if r.status == "ok":
            cells += [_cell(r.metrics.get(key)) for key, _, _ in METRICS]
        else:
            cells += [r.status.replace("|", "/")] + [""] * (len(METRICS) - 1)
        cells.append(str(r.type_mismatches))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def suite_table(records: Sequence[Run], machine: str) -> str:
    """The real-asset suite's table: one row per object and budget, structure found vs true,
    the joint and part errors and the wall time."""
    header = ["object", "budget", "K found / true", "types found / true",
              "smallest part motion (px)", "Axis Ang (deg)", "Axis Pos (x10)",
              "Geo Dist rev (deg)", "Geo Dist pri", "CD-m", "Part IoU", "wall (s)", "status"]
    lines = [f"Machine: {machine}", "", "| " + " | ".join(header) + " |",
             "|" + "---|" * len(header)]
    for r in records:
        found = "-" if r.parts_found is None else str(r.parts_found)
        true = "-" if r.parts_true is None else str(r.parts_true)
        if r.parts_visible is not None and r.parts_visible != r.parts_true:
            true += f" ({r.parts_visible} move >= {VISIBLE_PX:g} px)"
        smallest = min(r.part_motion_px) if r.part_motion_px else None
        cells = [r.scene, r.budget, f"{found} / {true}",
                 f"{r.types_found or '-'} / {r.types_true or '-'}", _cell(smallest)]
        cells += [_cell(r.metrics.get(key)) for key in
                  ("axis_ang", "axis_pos", "geo_dist_deg", "geo_dist_m", "cd_m", "part_iou")]
        cells += [_cell(r.total_seconds) if r.timings else "-", r.status.replace("|", "/")]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n" + suite_summary(records)


def suite_summary(records: Sequence[Run]) -> str:
    """Per budget (and variant): on how many scenes K and the joint types are right, in all
    and on those with at most 3 parts, counting every true part and only those that move a
    pixel or more."""
    groups: dict[str, list[Run]] = {}
    for r in records:
        label = r.budget if r.variant == "default" else f"{r.budget} {r.variant}"
        groups.setdefault(label, []).append(r)
    lines = []
    for label, runs in groups.items():
        small = [r for r in runs if r.parts_true is not None and r.parts_true <= 3]
        lines.append(f"- {label}: K and types right on {_right(runs, False)} scenes "
                     f"({_right(small, False)} with at most 3 parts); on the parts that move "
                     f">= {VISIBLE_PX:g} px: {_right(runs, True)} ({_right(small, True)})")
    return ("\n" + "\n".join(lines) + "\n") if lines else ""


def _right(runs: Sequence[Run], visible: bool) -> str:
    """"N of M": how many of `runs` have K and the types right (Run.structure_right)."""
    return f"{sum(bool(r.structure_right(visible)) for r in runs)} of {len(runs)}"


def plot(records: Sequence[Run], path: Path) -> None:
    """Each metric against total training time; one line per scene (and variant)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import LogLocator, NullFormatter, ScalarFormatter

    ok = [r for r in records if r.status == "ok" and r.total_seconds > 0]
    cols = 3
    rows = math.ceil(len(METRICS) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.2 * rows), squeeze=False)
    lines: dict[str, list[Run]] = {}
    for r in ok:
        label = r.scene if r.variant == "default" else f"{r.scene} {r.variant}"
        lines.setdefault(label, []).append(r)
    # One colour per line in every panel, so the single legend holds for all of them.
    colours = {name: f"C{i % 10}" for i, name in enumerate(lines)}
    for ax, (key, label, log_y) in zip(axes.flat, METRICS, strict=False):
        drawn = False
        for name, runs in lines.items():
            points = sorted((r.total_seconds, r.metrics.get(key)) for r in runs
                            if r.metrics.get(key) is not None)
            if log_y:  # zeros cannot sit on a log axis: shown at the axis floor instead
                points = [(t, max(v, 1e-4)) for t, v in points]
            if points:
                ax.plot(*zip(*points, strict=True), marker="o", label=name,
                        color=colours[name])
                drawn = True
        ax.set_xscale("log")
        # Labelled ticks at 1-2-5 steps: plain decades often leave a short time range unlabelled.
        ax.xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(ScalarFormatter())
        ax.xaxis.set_minor_formatter(NullFormatter())
        if log_y and drawn:
            ax.set_yscale("log")
        if not drawn:
            ax.text(0.5, 0.5, "not computed", ha="center", va="center", transform=ax.transAxes)
        ax.set_title(label)
        ax.set_xlabel("training time (s)")
        ax.grid(True, which="both", alpha=0.3)
    for ax in list(axes.flat)[len(METRICS):]:
        ax.axis("off")
    if lines:
        handles = [plt.Line2D([], [], color=c, marker="o", label=n) for n, c in colours.items()]
        _legend_below(fig, handles)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def _legend_below(fig, handles: list) -> None:  # noqa: ANN001 (a matplotlib Figure)
    """One legend for every panel, under the grid, where it hides no data."""
    fig.tight_layout()
    fig.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, 0.0),
               ncol=min(4, len(handles)), fontsize=8, frameon=False)


def plot_ablation(records: Sequence[Run], path: Path) -> None:
    """Ablation runs share a budget, so time is no axis: one panel per metric (and one for the
    wall time), the variants along x, one bar per scene."""
    plot_bars(records, path, along=lambda r: r.variant, bars=lambda r: r.scene)


def plot_bars(records: Sequence[Run], path: Path, along: Callable[[Run], str],
              bars: Callable[[Run], str]) -> None:
    """One panel per metric (and one for the wall time); runs grouped along x by `along`, one
    bar colour per value of `bars` (ablation: variants x scenes; real suite: objects x
    budgets)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    ok = [r for r in records if r.status == "ok"]
    groups = list(dict.fromkeys(along(r) for r in ok))
    series = list(dict.fromkeys(bars(r) for r in ok))
    value = {(bars(r), along(r)): r for r in ok}
    panels = [("__time", "total time (s)", False), *METRICS]
    cols = 3
    rows = math.ceil(len(panels) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(5.0 * cols, 3.0 * rows), squeeze=False)
    width = 0.8 / max(1, len(series))
    x = np.arange(len(groups))
    for ax, (key, label, log_y) in zip(axes.flat, panels, strict=False):
        drawn = False
        for i, bar in enumerate(series):
            heights = []
            for group in groups:
                run = value.get((bar, group))
                v = None if run is None else (
                    run.total_seconds if key == "__time" else run.metrics.get(key))
                heights.append(np.nan if v is None else v)
            if not np.all(np.isnan(heights)):
                ax.bar(x + (i - (len(series) - 1) / 2) * width, heights, width,
                       color=f"C{i % 10}")
                drawn = True
        if log_y and drawn:
            ax.set_yscale("log")
        if not drawn:
            ax.text(0.5, 0.5, "not computed", ha="center", va="center", transform=ax.transAxes)
        ax.set_title(label)
        ax.set_xticks(x, groups, rotation=45, ha="right", fontsize=7)
        ax.grid(True, axis="y", which="both", alpha=0.3)
    for ax in list(axes.flat)[len(panels):]:
        ax.axis("off")
    handles = [plt.Rectangle((0, 0), 1, 1, color=f"C{i % 10}", label=s)
               for i, s in enumerate(series)]
    _legend_below(fig, handles)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def write_results(records: Sequence[Run], out: Path, machine: str,
                  suite: bool = False) -> dict[str, Path]:
    """accuracy.csv, accuracy.md and accuracy.png in `out`; returns their paths. A suite's
    table has one row per object and its plot one bar group per object; variants of one budget
    (an ablation) get bars, budgets a line per scene (and variant) against time."""
    out.mkdir(parents=True, exist_ok=True)
    paths = {"csv": out / "accuracy.csv", "md": out / "accuracy.md", "png": out / "accuracy.png"}
    write_csv(records, paths["csv"])
    paths["md"].write_text((suite_table if suite else markdown_table)(records, machine))
    if suite:
        plot_bars(records, paths["png"], along=lambda r: r.scene, bars=lambda r: r.budget)
    elif len({r.budget for r in records}) == 1 and any(r.variant != "default" for r in records):
        plot_ablation(records, paths["png"])
    else:
        plot(records, paths["png"])
    return paths
