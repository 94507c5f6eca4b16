"""Drawers pushed along the body's frame, one travel per drawer (docs/method.md, "Stage 2",
"Drawers side by side").

Flat drawers side by side (trays a few voxels tall, their fronts touching) form one dynamic
piece whose drawers were pulled by different travels, and a whole-voxel shift of the piece
cannot tell a tray pushed back into its slot from one lifted onto the slab above it: both land
on matter the target reconstructed. What does tell them apart is the front. Seen along the
direction a drawer slides, each line of cells through it ends at its front, and the push that
brings that end back onto the target's matter is the drawer's travel, the same on every line
through the same drawer. So the piece's lines (columns of cells along a direction of the
body's frame) are grouped by that push and by adjacency across the direction; each group's
push is then read from the target images: the shortest along the direction that leaves none of
its centres where the images see empty space (a drawer pushed in disappears into the cabinet,
where no view looks, so the voxels alone cannot confirm it)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from gear.pipeline.stage2.hypotheses import Hypothesis
from gear.pipeline.stage2.voxels import SLIDE_TOLERANCE, VoxelSplit

# Pushes are tried up to this many voxels.
MAX_TRAVEL_VOXELS = 40
# A direction is read only when at least this share of the piece's columns meet target matter
# when pushed along it: a drawer pulled out of a cabinet meets the cabinet's face, a push
# sideways or up meets nothing.
MIN_COLUMNS_MEETING = 0.5
# Columns whose pushes differ by at most this many voxels may be one drawer, and a group holds
# at least this many columns.
TRAVEL_TOLERANCE_VOXELS = 1
MIN_GROUP_COLUMNS = 3
# Groups of columns beside each other whose image-read pushes differ by at most this many
# voxels are one drawer (a drawer's front is reconstructed a voxel or so uneven).
SAME_DRAWER_VOXELS = 1
# A drawer's push leaves at most 1 - this share of its centres where the target images see
# empty space (as a part's motion must land all but that share of it: parts.SPLIT_FRACTION).
MIN_CLEAR = 0.8


@dataclass
class FrameSlide:
    """Cells of a piece (a grid mask), the push that moves them (along a direction of the body's
    frame) and the deepest push the drawer may take: the same direction, as long as the push
    plus the images' tolerance. The images read a push up to that tolerance short of where the
    front lands, and see nothing of a drawer pushed deeper (it disappears into the cabinet):
    only the bound keeps stage 3 from sliding it on."""

    cells: np.ndarray
    motion: Hypothesis
    deepest: np.ndarray


@dataclass
class _Columns:
    """The cells of a piece as columns along a direction `along`: each cell's column (index
    into the columns), each column's place across the direction (2D, from 0) and its cells'
    outermost centre along the direction."""

    along: np.ndarray
    of_cell: np.ndarray
    place: np.ndarray
    outermost: np.ndarray


def _columns(centres: np.ndarray, frame: np.ndarray, axis: int, sign: float,
             voxel_size: float) -> _Columns:
    """The columns of the cells at `centres` along `sign` times frame direction `axis`."""
    along = sign * frame[axis]
    across = np.stack([frame[(axis + 1) % 3], frame[(axis + 2) % 3]])
    place = np.floor(centres @ across.T / voxel_size).astype(np.int64)
    place -= place.min(axis=0)
    places, of_cell = np.unique(place, axis=0, return_inverse=True)
    of_cell = of_cell.ravel()
    depth = centres @ along
    front = np.full(len(places), -np.inf)
    np.maximum.at(front, of_cell, depth)
    outermost = np.empty((len(places), 3))
    at_front = np.flatnonzero(depth >= front[of_cell])
    outermost[of_cell[at_front]] = centres[at_front]
    return _Columns(along, of_cell, places, outermost)


def _meeting_push(split: VoxelSplit, columns: _Columns) -> np.ndarray:
    """Per column, the whole-voxel push (1..MAX_TRAVEL_VOXELS) against `columns.along` that
    first brings its outermost cell onto target matter; 0 when none does."""
    shape = np.array(split.grid.shape)
    push = np.zeros(len(columns.outermost), dtype=np.int64)
    for travel in range(1, MAX_TRAVEL_VOXELS + 1):
        moved = columns.outermost - travel * split.grid.voxel_size * columns.along
        cells = split.grid.voxel_of(moved)
        inside = np.all((cells >= 0) & (cells < shape), axis=1) & (push == 0)
        meets = np.zeros(len(push), dtype=bool)
        meets[inside] = split.exact_target[tuple(cells[inside].T)]
        push[meets] = travel
    return push


def _column_groups(columns: _Columns, push: np.ndarray) -> np.ndarray:
    """Per column, its group (0: none): the columns beside each other (8-connected across the
    direction) whose pushes lie within TRAVEL_TOLERANCE_VOXELS of the most common push among
    the columns not yet grouped, taken in turn, each group MIN_GROUP_COLUMNS or more."""
    grid = np.zeros(columns.place.max(axis=0) + 1, dtype=np.int64)
    grid[tuple(columns.place.T)] = push
    group = np.zeros_like(grid)
    left = grid > 0
    groups = 0
    while left.any():
        counts = np.bincount(grid[left])
        mode = int(counts.argmax())
        if counts[mode] < MIN_GROUP_COLUMNS:
            break
        band = left & (np.abs(grid - mode) <= TRAVEL_TOLERANCE_VOXELS)
        labels, found = ndimage.label(band, structure=np.ones((3, 3), dtype=bool))
        sizes = np.bincount(labels.ravel())
        for label in range(1, found + 1):
            if sizes[label] >= MIN_GROUP_COLUMNS:
                groups += 1
                group[labels == label] = groups
        # Columns of the band in no group of their own are not tried again.
        left &= ~band
    return group[tuple(columns.place.T)]


def _seen_push(points: np.ndarray, along: np.ndarray, split: VoxelSplit) -> int:
    """The shortest whole-voxel push of `points` against `along` that leaves nearly as few of
    them where the target images see empty space as the push leaving fewest does (within
    SLIDE_TOLERANCE); 0 when every push leaves more than 1 - MIN_CLEAR of them there."""
    clear = np.empty(MAX_TRAVEL_VOXELS)
    for travel in range(1, MAX_TRAVEL_VOXELS + 1):
        moved = points - travel * split.grid.voxel_size * along
        _, through = split.on_surface(moved, split.surface_tolerance)
        clear[travel - 1] = 1.0 - through.mean()
    if clear.max() < MIN_CLEAR:
        return 0
    return int(np.flatnonzero(clear >= (1 - SLIDE_TOLERANCE) * clear.max())[0]) + 1


def _same_drawers(columns: _Columns, group: np.ndarray,
                  pushes: dict[int, int]) -> tuple[np.ndarray, dict[int, int]]:
    """Per column, its drawer, and the drawer of each group with a push: each column in no
    group with a push given to a group beside it (growing one column at a time), then groups
    beside each other (8-connected) whose pushes differ by at most SAME_DRAWER_VOXELS joined.
    A drawer's lines that met no matter (a handle's, a front's edge) lie between its groups
    and would otherwise keep them apart."""
    grid = np.zeros(columns.place.max(axis=0) + 1, dtype=np.int64)
    grid[tuple(columns.place.T)] = np.where(np.isin(group, list(pushes)), group, 0)
    occupied = np.zeros(grid.shape, dtype=bool)
    occupied[tuple(columns.place.T)] = True
    while True:
        fill = occupied & (grid == 0)
        grown = ndimage.grey_dilation(grid, size=(3, 3))
        fill &= grown > 0
        if not fill.any():
            break
        grid[fill] = grown[fill]
    parent = {g: g for g in pushes}

    def root(g: int) -> int:
        while parent[g] != g:
            g = parent[g]
        return g

    padded = np.pad(grid, 1)
    rows, cols = grid.shape
    for dx, dy in ((0, 1), (1, 0), (1, 1), (1, -1)):
        beside = padded[1 + dx:1 + dx + rows, 1 + dy:1 + dy + cols]
        pairs = np.unique(np.stack([grid.ravel(), beside.ravel()], axis=1), axis=0)
        for x, y in pairs[(pairs[:, 0] > 0) & (pairs[:, 1] > 0) & (pairs[:, 0] != pairs[:, 1])]:
            if abs(pushes[int(x)] - pushes[int(y)]) <= SAME_DRAWER_VOXELS:
                parent[root(int(x))] = root(int(y))
    of_group = {g: root(g) for g in pushes}
    drawer = np.array([of_group.get(int(g), 0) for g in grid[tuple(columns.place.T)]],
                      dtype=np.int64)
    return drawer, of_group


def frame_slides(split: VoxelSplit, mask: np.ndarray, frame: np.ndarray,
                 points_in: Callable[[np.ndarray], np.ndarray]) -> list[FrameSlide]:
    """The drawers of the piece `mask` (a grid mask) pushed along a direction of the body's
    `frame` [3, 3], each with its own travel (see the module); `points_in(cells)` gives the
    canonical centres in a grid mask. Empty without the target images, or when no direction
    of the frame brings MIN_COLUMNS_MEETING of the piece's columns onto target matter."""
    if split.on_surface is None:
        return []
    cells = np.argwhere(mask)
    centres = split.grid.centres(cells)
    best = None
    for axis in range(3):
        for sign in (1.0, -1.0):
            columns = _columns(centres, frame, axis, sign, split.grid.voxel_size)
            push = _meeting_push(split, columns)
            meeting = float((push > 0).mean())
            if meeting >= MIN_COLUMNS_MEETING and (best is None or meeting > best[0]):
                best = (meeting, columns, push)
    if best is None:
        return []
    _, columns, push = best
    group = _column_groups(columns, push)
    pushes = {}
    for g in np.unique(group[group > 0]):
        travel = _seen_push(points_in(_cells_mask(split, cells[group[columns.of_cell] == g])),
                            columns.along, split)
        if travel:
            pushes[int(g)] = travel
    if not pushes:
        return []
    drawer, of_group = _same_drawers(columns, group, pushes)
    cells_of_group = np.bincount(group[columns.of_cell])
    slides = []
    for d in np.unique(drawer[drawer > 0]):
        # The drawer's push: its groups' pushes, the median over their cells (the columns
        # that joined them have none of their own).
        members = [g for g in pushes if of_group[g] == d]
        travel = _weighted_median([pushes[g] for g in members],
                                  [cells_of_group[g] for g in members])
        piece = _cells_mask(split, cells[drawer[columns.of_cell] == d])
        shift = -travel * split.grid.voxel_size * columns.along
        motion = split.score(np.argwhere(piece), "slide", np.eye(3), shift)
        reach = travel * split.grid.voxel_size + split.surface_tolerance
        slides.append(FrameSlide(piece, motion, -reach * columns.along))
    return slides


def _weighted_median(values: list[int], weights: list[int]) -> int:
    """The median of `values` counted `weights` times each."""
    order = np.argsort(values)
    cumulative = np.cumsum(np.asarray(weights)[order])
    return int(np.asarray(values)[order][np.searchsorted(cumulative, cumulative[-1] / 2)])


def _cells_mask(split: VoxelSplit, cells: np.ndarray) -> np.ndarray:
    """The grid mask of `cells` [M, 3]."""
    mask = np.zeros(split.grid.shape, dtype=bool)
    mask[tuple(cells.T)] = True
    return mask
