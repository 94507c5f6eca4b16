"""Point-set geometry on the CPU (Rust, multithreaded): k nearest neighbours, voxel grids shared
by several point sets, set operations, dilation and connected components.

Points are float32 internally (the dtype of Gaussian centres); float64 or integer input is
converted once, and torch tensors are accepted (detached, moved to the CPU). Voxel occupancy
is dense (a bool array ``[X, Y, Z]``) when the grid has at most ``max_dense_cells`` cells,
otherwise sparse (the sorted linear keys ``(i * Y + j) * Z + k`` of the occupied voxels);
both give the same results.
"""

from __future__ import annotations

import functools
import numbers
import operator
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from gear import _core

#: Largest grid kept dense: 2^25 cells is 32 MB of occupancy and 128 MB of int32 labels.
DEFAULT_MAX_DENSE_CELLS = 2**25


def knn(
    points: np.ndarray, k: int, queries: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` nearest of ``points`` to each query, nearest first.

    Returns ``(indices int64 [M, k], distances float32 [M, k])`` (Euclidean). With ``queries``
    None, the queries are ``points`` themselves and each point's own index is excluded (an
    identical duplicate still counts, at distance 0). Equal distances come in arbitrary but
    deterministic order.

    Raises ValueError naming the argument for k < 1, NaN/Inf coordinates, or fewer candidates
    than ``k`` (``N < k``, or ``N - 1 < k`` with self excluded; no padding is invented). Zero
    queries give empty ``[0, k]`` arrays.
    """
    k = _count(k, "k", minimum=1)
    pts = _points(points, "points")
    qs = None if queries is None else _points(queries, "queries")
    return _core.knn(pts, k, qs)


class NearestTree:
    """A k-d tree over reference points (``[N, 3]``), built once for many :meth:`query` calls:
    the native tree of :func:`knn`, searched on the calling thread for a few hundred queries
    and by every core for more.

    ``data`` holds the points in float64 (callers read matched points from it); the search runs
    in float32 like :func:`knn`, so a query between two points equidistant to within float32
    precision may get either. Raises ValueError for non-finite points."""

    def __init__(self, points: np.ndarray) -> None:
        self.data = np.asarray(points, dtype=np.float64)
        self._tree = _core.KnnTree(_points(self.data, "points"))

    def __len__(self) -> int:
        return len(self.data)

    def query(self, queries: np.ndarray, k: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """``(distances float64, indices int64)`` of the ``k`` nearest points to each query
        ``[M, 3]``, nearest first: shape ``[M]`` for ``k = 1``, ``[M, k]`` above (the order and
        shapes of scipy's ``cKDTree.query``). Raises ValueError for k < 1, more neighbours than
        points, or a non-finite query."""
        k = _count(k, "k", minimum=1)
        indices, distances = self._tree.query(_points(queries, "queries"), k)
        distances = distances.astype(np.float64)
        if k == 1:
            return distances[:, 0], indices[:, 0]
        return distances, indices


def nearest_neighbours(points: np.ndarray, k: int) -> np.ndarray:
    """Indices [N, k] of each point's k nearest other points, k clipped to N - 1 (a set too
    small for one neighbour gives [N, 0]): the neighbour lists of the Gaussians."""
    pts = np.ascontiguousarray(points, dtype=np.float32)
    k = min(k, len(pts) - 1)
    if k < 1:
        return np.zeros((len(pts), 0), dtype=np.int64)
    return np.asarray(knn(pts, k)[0], dtype=np.int64)


class Occupancy:
    """The occupied voxels of one set in a grid of ``shape``: dense or sparse (see module doc).

    Supports ``a & b`` (intersection), ``a | b`` (union) and ``a - b`` (difference) between
    occupancies of the same shape; a dense and a sparse operand give a sparse result.
    """

    __slots__ = ("_dense", "_keys", "shape")

    def __init__(
        self,
        shape: tuple[int, int, int],
        *,
        dense: np.ndarray | None = None,
        keys: np.ndarray | None = None,
    ) -> None:
        if (dense is None) == (keys is None):
            raise ValueError("Occupancy: give exactly one of dense= or keys=")
        self.shape = tuple(int(n) for n in shape)
        if len(self.shape) != 3 or min(self.shape) < 0:
            raise ValueError(f"shape: expected three sizes >= 0, got {shape}")
        self._dense = None if dense is None else np.ascontiguousarray(dense, dtype=bool)
        self._keys = None if keys is None else np.ascontiguousarray(keys, dtype=np.int64)
        if self._dense is not None and self._dense.shape != self.shape:
            raise ValueError(f"dense: shape {self._dense.shape} differs from {self.shape}")
        if self._keys is not None:
            k = self._keys
            cells = int(np.prod(self.shape, dtype=np.float64))
            if k.ndim != 1 or np.any(k[1:] <= k[:-1]) or (k.size and (k[0] < 0 or k[-1] >= cells)):
                raise ValueError(
                    f"keys: expected strictly increasing linear keys in [0, {cells}) (1-D)"
                )

    @property
    def is_sparse(self) -> bool:
        return self._keys is not None

    @property
    def dense(self) -> np.ndarray | None:
        """The bool ``[X, Y, Z]`` array, or None for a sparse occupancy."""
        return self._dense

    @property
    def keys(self) -> np.ndarray:
        """Sorted int64 linear keys of the occupied voxels (computed for a dense occupancy)."""
        if self._keys is not None:
            return self._keys
        return np.flatnonzero(self._dense).astype(np.int64, copy=False)

    @property
    def count(self) -> int:
        return len(self._keys) if self._keys is not None else int(self._dense.sum())

    def coords(self) -> np.ndarray:
        """int64 ``[M, 3]`` voxel indices of the occupied voxels, in key order."""
        return np.stack(np.unravel_index(self.keys, self.shape), axis=1).astype(np.int64)

    def to_dense(self, max_cells: int = DEFAULT_MAX_DENSE_CELLS) -> np.ndarray:
        """The bool ``[X, Y, Z]`` array; ValueError if the grid has more than ``max_cells``."""
        if self._dense is not None:
            return self._dense
        cells = int(np.prod(self.shape, dtype=np.float64))
        if cells > max_cells:
            raise ValueError(
                f"max_cells: a dense {self.shape} grid has {cells} cells, more than the "
                f"bound {max_cells}; keep it sparse or raise the bound"
            )
        out = np.zeros(cells, dtype=bool)
        out[self._keys] = True
        return out.reshape(self.shape)

    def contains(self, voxels: np.ndarray) -> np.ndarray:
        """bool ``[N]``: whether each voxel index ``[N, 3]`` is occupied (False outside)."""
        v = np.asarray(voxels, dtype=np.int64).reshape(-1, 3)
        inside = np.all((v >= 0) & (v < np.array(self.shape)), axis=1)
        out = np.zeros(len(v), dtype=bool)
        if self._dense is not None:
            vi = v[inside]
            out[inside] = self._dense[vi[:, 0], vi[:, 1], vi[:, 2]]
        else:
            out[inside] = _positions(self._keys, _linear(v[inside], self.shape)) >= 0
        return out

    def _set_op(self, other: Occupancy, op: str) -> Occupancy:
        if not isinstance(other, Occupancy):
            return NotImplemented
        if other.shape != self.shape:
            raise ValueError(f"other: grid shape {other.shape} differs from {self.shape}")
        if self._dense is not None and other._dense is not None:
            a, b = self._dense, other._dense
            cells = a & b if op == "and" else a | b if op == "or" else a & ~b
            return Occupancy(self.shape, dense=cells)
        return Occupancy(self.shape, keys=_core.keys_set_op(op, self.keys, other.keys, self.shape))

    def __and__(self, other: Occupancy) -> Occupancy:
        return self._set_op(other, "and")

    def __or__(self, other: Occupancy) -> Occupancy:
        return self._set_op(other, "or")

    def __sub__(self, other: Occupancy) -> Occupancy:
        return self._set_op(other, "sub")

    def __repr__(self) -> str:
        kind = "sparse" if self.is_sparse else "dense"
        return f"Occupancy({kind}, shape={self.shape}, count={self.count})"


@dataclass(frozen=True, eq=False)
class VoxelGrid:
    """A grid shared by several point sets; voxel ``(i, j, k)`` covers
    ``origin + voxel_size * ([i, i+1) x [j, j+1) x [k, k+1))``."""

    origin: np.ndarray  # float64 [3]: min corner of the union of the sets' bounding boxes
    voxel_size: float
    shape: tuple[int, int, int]
    occupancy: tuple[Occupancy, ...]  # one per input set, in order
    max_dense_cells: int = DEFAULT_MAX_DENSE_CELLS

    @property
    def cells(self) -> int:
        return int(np.prod(self.shape, dtype=np.float64))

    @property
    def is_sparse(self) -> bool:
        return self.cells > self.max_dense_cells

    def voxel_of(self, points: np.ndarray) -> np.ndarray:
        """int64 ``[N, 3]``: the voxel of each point (possibly outside the grid)."""
        return _core.voxel_indices(_points(points, "points"), *self._spec())

    def voxelise(self, points: np.ndarray) -> Occupancy:
        """Occupancy of ``points`` in this grid (points outside it are ignored)."""
        pts = _points(points, "points")
        if self.is_sparse:
            return Occupancy(self.shape, keys=_core.occupancy_keys(pts, *self._spec()))
        return Occupancy(self.shape, dense=_core.occupancy_dense(pts, *self._spec()))

    def centres(self, voxels: np.ndarray) -> np.ndarray:
        """float64 ``[M, 3]``: the centres of voxel indices ``[M, 3]``."""
        return self.origin + (np.asarray(voxels, dtype=np.float64) + 0.5) * self.voxel_size

    def point_labels(
        self, points: np.ndarray, labels: np.ndarray, occ: Occupancy | None = None
    ) -> np.ndarray:
        """int32 ``[N]``: the label of each point's voxel (0 if empty or outside the grid).

        ``labels`` is what :func:`components` returned: a dense ``[X, Y, Z]`` array, or for a
        sparse occupancy one label per key, in which case that ``occ`` must be given too.
        """
        v = self.voxel_of(points)
        inside = np.all((v >= 0) & (v < np.array(self.shape)), axis=1)
        out = np.zeros(len(v), dtype=np.int32)
        vi = v[inside]
        if labels.ndim == 3:
            if labels.shape != self.shape:
                raise ValueError(f"labels: shape {labels.shape} differs from grid {self.shape}")
            out[inside] = labels[vi[:, 0], vi[:, 1], vi[:, 2]]
            return out
        if occ is None or labels.shape != (occ.count,):
            raise ValueError("occ: sparse labels need the occupancy they label (one per key)")
        pos = _positions(occ.keys, _linear(vi, self.shape))
        out[inside] = np.where(pos >= 0, labels[np.maximum(pos, 0)], 0)
        return out

    def _spec(self) -> tuple[tuple[float, float, float], float, tuple[int, int, int]]:
        return tuple(self.origin.tolist()), self.voxel_size, self.shape


def box_diagonal(points: np.ndarray) -> float:
    """The diagonal of the axis-aligned box bounding ``points`` [N, 3] (N >= 1): an object's
    size for search widths and tolerances."""
    return float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))


def share_in_line(points: np.ndarray, other: np.ndarray, direction: np.ndarray,
                  margin: float, trim: float = 0.0) -> float:
    """The share of ``points`` [N, 3] that fall, seen along ``direction``, inside the box
    bounding ``other`` [M, 3] across it, grown by ``margin`` on every side: how much of one set
    lies in line with the other along a slide (e.g. a drawer's front and back, not two drawers
    of a column pulled by the same travel). With ``trim`` > 0 the box spans the ``trim`` to
    1 - ``trim`` quantiles of ``other`` across the slide, so a few strays do not stretch it.
    0 for empty ``points`` or ``other``."""
    points, other = np.asarray(points, np.float64), np.asarray(other, np.float64)
    if len(points) == 0 or len(other) == 0:
        return 0.0
    direction = np.asarray(direction, dtype=np.float64)
    direction = direction / max(float(np.linalg.norm(direction)), 1e-12)
    across = np.linalg.svd(direction[None, :])[2][1:]  # two unit vectors normal to it
    own, section = points @ across.T, other @ across.T
    lo = np.quantile(section, trim, axis=0) - margin
    hi = np.quantile(section, 1.0 - trim, axis=0) + margin
    return float(np.all((own >= lo) & (own <= hi), axis=1).mean())


def voxel_grid(
    point_sets: Sequence[np.ndarray],
    voxel_size: float,
    max_dense_cells: int = DEFAULT_MAX_DENSE_CELLS,
) -> VoxelGrid:
    """Voxelises several point sets ``[N_i, 3]`` in one grid at ``voxel_size``.

    The origin is the min corner of the union of the sets' bounding boxes and the shape just
    covers their max corner. The occupancy is dense up to ``max_dense_cells`` cells, sparse
    beyond (same results). Raises ValueError naming the argument for a non-positive or
    non-finite voxel size, NaN/Inf points, all sets empty, or more than 2^62 cells.
    """
    if isinstance(point_sets, np.ndarray):
        raise ValueError("point_sets: expected a sequence of [N, 3] arrays; wrap one set in a list")
    size = _positive(voxel_size, "voxel_size")
    bound = _count(max_dense_cells, "max_dense_cells", minimum=0)
    sets = [_points(s, f"point_sets[{i}]") for i, s in enumerate(point_sets)]
    origin, shape = _core.grid_enclosing(sets, size)
    grid = VoxelGrid(np.array(origin), size, tuple(shape), (), bound)
    occupancy = tuple(grid.voxelise(s) for s in sets)
    return VoxelGrid(grid.origin, size, grid.shape, occupancy, bound)


def dilate(occ: np.ndarray | Occupancy, radius: int) -> np.ndarray | Occupancy:
    """Dilation by a ``(2 radius + 1)^3`` cube, clipped to the grid; same type as ``occ``."""
    r = _count(radius, "radius", minimum=0)
    if isinstance(occ, Occupancy):
        if occ.is_sparse:
            return Occupancy(occ.shape, keys=_core.dilate_keys(occ.keys, occ.shape, r))
        return Occupancy(occ.shape, dense=_core.dilate_dense(occ.dense, r))
    return _core.dilate_dense(_grid_array(occ), r)


def components(
    occ: np.ndarray | Occupancy, connectivity: int = 26
) -> tuple[np.ndarray, np.ndarray]:
    """Connected components of the occupied voxels (``connectivity`` 26 or 6).

    Returns ``(labels, sizes)``: int32 labels with 0 = empty, 1 = the largest component, 2 the
    next, ... (equal sizes ordered by their first voxel in C order), and int64 ``sizes``
    largest first (``sizes[l - 1]`` voxels have label ``l``). ``labels`` is ``[X, Y, Z]`` for
    a bool array or dense occupancy, and one label per key (aligned with ``occ.keys``) for a
    sparse occupancy.
    """
    conn = _count(connectivity, "connectivity", minimum=0)
    if isinstance(occ, Occupancy):
        if occ.is_sparse:
            return _core.components_keys(occ.keys, occ.shape, conn)
        return _core.components_dense(occ.dense, conn)
    return _core.components_dense(_grid_array(occ), conn)


def piece_labels(point_sets: Sequence[np.ndarray], voxel_size: float,
                 grow: int = 1) -> list[np.ndarray]:
    """Each set's points labelled by the 26-connected piece their voxel belongs to, the pieces
    being those of the union of all sets' cells at ``voxel_size``, grown by ``grow`` cells
    (labels as :func:`components`: 1 = the largest piece). Two points share a label when
    a chain of occupied cells, bridging gaps under ``grow`` cells, joins them."""
    grid = voxel_grid(point_sets, voxel_size)
    cells = dilate(functools.reduce(operator.or_, grid.occupancy), grow)
    pieces, _ = components(cells, connectivity=26)
    sparse = None if pieces.ndim == 3 else cells
    return [grid.point_labels(points, pieces, sparse) for points in point_sets]


def _points(points: np.ndarray, name: str) -> np.ndarray:
    """``points`` as a C-contiguous float32 ``[N, 3]`` array (converted once if needed).
    A torch tensor (Gaussian centres) is detached and brought to the CPU first."""
    if hasattr(points, "detach"):
        points = points.detach().cpu().numpy()
    arr = np.asarray(points)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name}: expected shape [N, 3], got {list(arr.shape)}")
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise TypeError(f"{name}: expected real coordinates, got dtype {arr.dtype}")
    return np.ascontiguousarray(arr, dtype=np.float32)


def _grid_array(occ: np.ndarray) -> np.ndarray:
    arr = np.asarray(occ)
    if arr.ndim != 3:
        raise ValueError(f"occ: expected a 3-D occupancy array, got shape {list(arr.shape)}")
    return np.ascontiguousarray(arr, dtype=bool)


def _count(value: int, name: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ValueError(f"{name}: expected an integer, got {value!r}")
    if value < minimum:
        raise ValueError(f"{name}: must be at least {minimum}, got {value}")
    return int(value)


def _positive(value: float, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name}: expected a number, got {value!r}")
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"{name}: must be a positive finite number, got {value}")
    return float(value)


def _linear(voxels: np.ndarray, shape: tuple[int, int, int]) -> np.ndarray:
    """Linear keys of in-grid voxel indices ``[M, 3]``."""
    return (voxels[:, 0] * shape[1] + voxels[:, 1]) * shape[2] + voxels[:, 2]


def _positions(keys: np.ndarray, wanted: np.ndarray) -> np.ndarray:
    """Index of each wanted key in sorted ``keys``, or -1 where it is absent."""
    pos = np.searchsorted(keys, wanted)
    found = pos < len(keys)
    found[found] = keys[pos[found]] == wanted[found]
    return np.where(found, pos, -1)
