"""KNN and connected components (gear.geometry) against scipy, timed in the same run.

KNN: each point's k nearest others among N points near a surface (as Gaussian centres are),
against cKDTree build + query(k + 1, workers=-1), both including the tree build and using all
cores. Components: 26-connected labelling of random grids against ndimage.label (which does
not sort components by size, so the baseline does less work). Ratio = scipy time / gear time
(wall clock), so > 1 means gear is faster; "cpu ratio" compares CPU time summed over threads
(the work done, less sensitive to a busy machine). Runs alternate gear and scipy and keep each
one's best time.
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from gear import geometry

KNN_SIZES = (10_000, 100_000, 1_000_000)
KNN_KS = (3, 16)
GRID_SIZES = (128, 256)
FILLS = (0.05, 0.30)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--quick", action="store_true",
                        help="skip the largest rows (N = 1M, 256^3 grids)")
    parser.add_argument("--only", choices=("knn", "components"), help="run one family only")
    parser.add_argument("--repeat", type=int, default=3,
                        help="timed runs per side (best kept; fewer once a row takes > 5 s)")
    parser.add_argument("--seed", type=int, default=0)


def run(args: argparse.Namespace) -> int:
    rng = np.random.default_rng(args.seed)
    print(f"gear.geometry vs scipy on {os.cpu_count()} cores; ratio = scipy / gear (> 1: faster)")
    print(f"{'case':<34} {'gear ms':>10} {'scipy ms':>10} {'ratio':>7} {'cpu ratio':>9}  check")
    if args.only in (None, "knn"):
        for n in KNN_SIZES:
            if args.quick and n > 100_000:
                continue
            points = surface_points(rng, n)
            for k in KNN_KS:
                knn_row(points, k, args.repeat)
    if args.only in (None, "components"):
        for size in GRID_SIZES:
            if args.quick and size > 128:
                continue
            for fill in FILLS:
                occ = rng.random((size,) * 3, dtype=np.float32) < fill
                components_row(occ, fill, args.repeat)
    return 0


def surface_points(rng: np.random.Generator, n: int) -> np.ndarray:
    """n points within 1% of a unit sphere, float32 like Gaussian centres."""
    directions = rng.normal(size=(n, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    radii = 1.0 + 0.01 * rng.normal(size=(n, 1))
    return (directions * radii).astype(np.float32)


def knn_row(points: np.ndarray, k: int, repeat: int) -> None:
    def ours() -> np.ndarray:
        return geometry.knn(points, k)[1]

    def scipy_knn() -> np.ndarray:
        return cKDTree(points).query(points, k + 1, workers=-1)[0][:, 1:]

    mine, ref = best_times(ours, scipy_knn, repeat)
    err = float(np.abs(mine.result - ref.result).max())
    report(f"knn N={len(points):>9,} k={k:<2}", mine, ref, f"max |dd| {err:.1e}")


def components_row(occ: np.ndarray, fill: float, repeat: int) -> None:
    structure = np.ones((3, 3, 3), bool)

    def ours() -> int:
        return len(geometry.components(occ, 26)[1])

    def scipy_label() -> int:
        return ndimage.label(occ, structure=structure)[1]

    mine, ref = best_times(ours, scipy_label, repeat)
    n_ours, n_ref = mine.result, ref.result
    check = f"{n_ours} components" + ("" if n_ours == n_ref else f" != scipy {n_ref}")
    report(f"components {occ.shape[0]}^3 fill {fill:.0%}", mine, ref, check)


@dataclass
class Timing:
    """Best wall time, best CPU time (all threads) and the last result of one side."""

    wall: float = float("inf")
    cpu: float = float("inf")
    result: object = None


def best_times(a: Callable[[], object], b: Callable[[], object], repeat: int) -> list[Timing]:
    """Timings of a and b, alternating them so both see the same machine load."""
    timings = [Timing(), Timing()]
    spent = 0.0
    for i in range(max(1, repeat)):
        if i > 0 and spent > 5.0:  # big rows: one or two runs are enough
            break
        for fn, t in zip((a, b), timings, strict=True):
            wall0, cpu0 = time.perf_counter(), time.process_time()
            t.result = fn()
            wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
            t.wall, t.cpu = min(t.wall, wall), min(t.cpu, cpu)
            spent += wall
    return timings


def report(case: str, mine: Timing, ref: Timing, check: str) -> None:
    print(f"{case:<34} {mine.wall * 1e3:>10.1f} {ref.wall * 1e3:>10.1f} "
          f"{ref.wall / mine.wall:>7.2f} {ref.cpu / max(mine.cpu, 1e-9):>9.2f}  {check}",
          flush=True)
