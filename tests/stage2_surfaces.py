"""Stand-ins for stage 2's SurfaceTest (what a state's images see at each point) in tests."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

Look = Callable[[np.ndarray, float], tuple[np.ndarray, np.ndarray]]


class OneView:
    """A surface test from a yes/no `look(points, tolerance) -> (on_surface, seen_through)`,
    counted as one view seeing everything: each answer is one vote (a `look` that counts
    views instead gives its counts as the votes)."""

    def __init__(self, look: Look) -> None:
        self.look = look

    def __call__(self, points: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
        return self.look(points, tolerance)

    def votes(self, points: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
        on, through = self.look(points, tolerance)
        return on.astype(np.int64), through.astype(np.int64)
