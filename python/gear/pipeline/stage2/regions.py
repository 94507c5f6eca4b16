"""Stage 2's split of one dynamic piece into the regions that move apart: neighbouring doors
or drawers whose dynamic voxels touch form one piece, and one rigid motion of the whole piece
can land most of it on target matter (a few doors turned by 20-40 degrees also land, within
a voxel, when pushed back flat), so the cells a motion misses cannot tell them apart. The
regions are found by the motion each part of the piece needs instead (docs/method.md,
"Stage 2", splitting).

The piece is cut into chunks of about CHUNK_CELLS cells; every chunk proposes its own motions
(`init_motion`), and each centre's residual under a motion is its distance to the nearest
target centre once moved, capped at RESIDUAL_CAP_VOXELS (a centre that lands nowhere costs
the same whatever the motion). Adjacent regions, at first the chunks, are merged while the
best single motion of the two together costs at most MERGE_COST more per centre than their
two motions apart: two chunks of one door share its motion and merge for nearly nothing, two
doors do not."""

from __future__ import annotations

import numpy as np
from scipy.cluster.vq import kmeans2

from gear.articulation import RigidMotion
from gear.geometry import NearestTree
from gear.pipeline.stage2.hypotheses import Hypothesis
from gear.pipeline.stage2.voxels import MIN_PART_VOXELS, VoxelSplit, init_motion

CHUNK_CELLS = 30
MAX_CHUNKS = 32
# Centres scored per piece (an even subsample beyond): the decisions rest on mean residuals.
MAX_POINTS = 4000
ICP_STEPS = 25
ICP_POINTS = 500
RESIDUAL_CAP_VOXELS = 1.5
MERGE_COST = 0.04
# Two motions agree when they move a piece's centres to within this many voxels of each other
# (median): the same rigid part, read from two fragments.
AGREE_VOXELS = 2.0
# The 26 neighbour offsets of a cell.
_NEIGHBOURS = np.argwhere(np.ones((3, 3, 3), dtype=bool)) - 1
_NEIGHBOURS = _NEIGHBOURS[np.any(_NEIGHBOURS != 0, axis=1)]



def _chunks(cells: np.ndarray) -> np.ndarray:
    """A chunk index per cell [M]: k-means of the cell coordinates into about CHUNK_CELLS cells
    each (seeded: the same piece always gives the same chunks)."""
    count = min(len(cells) // CHUNK_CELLS, MAX_CHUNKS)
    _, chunk = kmeans2(cells.astype(np.float64), count, seed=np.random.default_rng(0),
                       minit="++")
    return np.unique(chunk, return_inverse=True)[1]  # empty clusters leave no gaps


def _adjacent_pairs(cells: np.ndarray, chunk: np.ndarray, shape: tuple[int, ...]) -> set:
    """Pairs (a, b), a < b, of chunks with 26-neighbouring cells."""
    index = np.full(shape, -1, dtype=np.int64)
    index[tuple(cells.T)] = chunk
    pairs = set()
    for offset in _NEIGHBOURS:
        near = cells + offset
        inside = np.all((near >= 0) & (near < np.array(shape)), axis=1)
        other = index[tuple(near[inside].T)]
        own = chunk[inside]
        differ = (other >= 0) & (other != own)
        lo = np.minimum(own[differ], other[differ])
        hi = np.maximum(own[differ], other[differ])
        pairs.update(zip(lo.tolist(), hi.tolist(), strict=True))
    return pairs


def _residuals(split: VoxelSplit, points: np.ndarray, motions: list[Hypothesis]) -> np.ndarray:
    """[motions, points]: each centre's capped distance to the nearest target centre once moved,
    as a fraction of the cap."""
    cap = RESIDUAL_CAP_VOXELS * split.grid.voxel_size
    out = np.empty((len(motions), len(points)))
    for row, motion in enumerate(motions):
        moved = points @ np.asarray(motion.rot).T + np.asarray(motion.trans)
        dist, _ = split.target_tree.query(moved, k=1)
        out[row] = np.minimum(dist / cap, 1.0)
    return out


def refine_rigid(
    points: np.ndarray, rot: np.ndarray, trans: np.ndarray, tree: NearestTree, steps: int
) -> RigidMotion:
    """(R, t) after `steps` of trimmed ICP of `points` onto the centres of `tree`: each step
    pairs the nearest 80 % of the moved points with their nearest centres and solves the
    rigid fit of those pairs (the part of a piece the target hides must not drag the rest).
    Stops early at a fixed point: a step that pairs the same points with the same centres as
    the step before solves the same fit, so every later step would repeat it bit for bit."""
    rot, trans = np.asarray(rot, dtype=np.float64), np.asarray(trans, dtype=np.float64)
    pairs = None
    for _ in range(steps):
        moved = points @ rot.T + trans
        dist, index = tree.query(moved, k=1)
        near = dist <= np.percentile(dist, 80)
        paired = np.where(near, index, -1)
        if pairs is not None and np.array_equal(paired, pairs):
            break
        pairs = paired
        src, dst = points[near], tree.data[index[near]]
        src_c, dst_c = src.mean(axis=0), dst.mean(axis=0)
        u, _, vt = np.linalg.svd((src - src_c).T @ (dst - dst_c))
        flip = np.sign(np.linalg.det(vt.T @ u.T))
        rot = vt.T @ np.diag([1.0, 1.0, flip]) @ u.T
        trans = dst_c - rot @ src_c
    return rot, trans


def refined_cost(
    split: VoxelSplit, points: np.ndarray, starts: tuple[Hypothesis, ...]
) -> tuple[float, Hypothesis]:
    """The one rigid motion of the centres `points` that costs them least (mean capped residual
    per centre, on a subsample of ICP_POINTS) among `starts` each refined by trimmed ICP on
    them (refine_rigid), as (cost, motion). Motions fitted to pieces of a part may each miss
    the part's; the part's own lies between them."""
    fit_to = points[:: -(-len(points) // ICP_POINTS)]
    best = None
    for start in starts:
        rot, trans = refine_rigid(fit_to, start.rot, start.trans, split.target_tree, ICP_STEPS)
        motion = Hypothesis(start.kind, rot, trans)
        cost = float(_residuals(split, fit_to, [motion]).mean())
        if best is None or cost < best[0]:
            best = (cost, motion)
    if best is None:
        raise ValueError("refined_cost: no motion to start from")
    return best


def one_motion(
    split: VoxelSplit, pieces: list[tuple[np.ndarray, Hypothesis]]
) -> tuple[float, Hypothesis]:
    """The one rigid motion of several pieces together (refined_cost, from each piece's
    motion) and how much more it costs their centres than each piece's own motion, per centre
    (compare with MERGE_COST), as (extra cost, motion); `pieces` holds (centres, own motion)
    pairs."""
    points = np.concatenate([p for p, _ in pieces])
    apart = np.concatenate([_residuals(split, p, [m])[0] for p, m in pieces])
    together, motion = refined_cost(split, points, tuple(m for _, m in pieces))
    return together - float(apart[:: -(-len(points) // ICP_POINTS)].mean()), motion


def extra_residual(
    split: VoxelSplit, points: np.ndarray, motion: Hypothesis, own: list[Hypothesis]
) -> float:
    """How much more `motion` costs the centres `points` than the best of their `own` motions,
    as the mean capped residual per centre (compare with MERGE_COST)."""
    costs = _residuals(split, points, [motion, *own]).mean(axis=1)
    return float(costs[0] - costs[1:].min()) if len(own) else 0.0


def motion_regions(
    split: VoxelSplit, mask: np.ndarray, points: np.ndarray, readings: list[Hypothesis]
) -> list[np.ndarray]:
    """The cells of `mask` (a piece holding the canonical centres `points`, whose own motions
    are `readings`) as the regions that need motions of their own, largest first; one region
    (a mask like `mask`) when the piece moves as one, or is too small to cut into chunks."""
    cells = np.argwhere(mask)
    if len(cells) < 2 * CHUNK_CELLS:
        return [mask]
    chunk = _chunks(cells)
    points = points[:: -(-len(points) // MAX_POINTS)]
    index = np.full(mask.shape, -1, dtype=np.int64)
    index[tuple(cells.T)] = chunk
    point_cells = split.grid.voxel_of(points)
    inside = np.all((point_cells >= 0) & (point_cells < np.array(mask.shape)), axis=1)
    point_chunk = np.full(len(points), -1, dtype=np.int64)
    point_chunk[inside] = index[tuple(point_cells[inside].T)]

    motions = [h for h in readings if h.trusted]
    for c in range(chunk.max() + 1):
        held = point_chunk == c
        if (chunk == c).sum() >= MIN_PART_VOXELS and held.sum() >= 4:
            sub = np.zeros_like(mask)
            sub[tuple(cells[chunk == c].T)] = True
            # A chunk's own readings: no blob sweep (seconds each; the piece's readings have
            # it), target pieces of at least a fifth of the piece, as for the piece itself
            # (docs/method.md: a twentieth found more doors and cut a blurred door in two).
            motions += [h for h in init_motion(split, sub, points[held], len(cells),
                                               sweep=False) if h.trusted]
    if not motions:
        return [mask]
    residual = _residuals(split, points, motions)

    # Per region: its chunks, its centres' residual summed per motion, its centre count.
    regions = {c: ({c}, residual[:, point_chunk == c].sum(axis=1), int((point_chunk == c).sum()))
               for c in range(chunk.max() + 1)}
    pairs = _adjacent_pairs(cells, chunk, mask.shape)
    agree = AGREE_VOXELS * split.grid.voxel_size
    refined: dict[tuple[frozenset, frozenset], float] = {}
    while pairs:
        def extra(pair: tuple[int, int]) -> float:
            (chunks_a, sum_a, n_a), (chunks_b, sum_b, n_b) = regions[pair[0]], regions[pair[1]]
            # Two readings of one rigid part: its regions' best motions put its centres
            # within AGREE_VOXELS of each other (a noisy model fits each half a little
            # differently, but the same turn).
            a, b = motions[int(sum_a.argmin())], motions[int(sum_b.argmin())]
            held = points[np.isin(point_chunk, list(chunks_a | chunks_b))]
            if np.median(np.linalg.norm(held @ (a.rot - b.rot).T + (a.trans - b.trans),
                                        axis=1)) <= agree:
                return 0.0
            merged = float((sum_a + sum_b).min())
            # The candidates were fitted to chunks; one rigid motion of the two together may
            # lie between them: each region's best, refined on both.
            key = (frozenset(chunks_a), frozenset(chunks_b))
            if key not in refined:
                refined[key] = refined_cost(split, held, (a, b))[0] * (n_a + n_b)
            merged = min(merged, refined[key])
            return (merged - sum_a.min() - sum_b.min()) / max(1, n_a + n_b)

        a, b = min(sorted(pairs), key=extra)
        if extra((a, b)) > MERGE_COST:
            break
        chunks_b, sum_b, n_b = regions.pop(b)
        chunks_a, sum_a, n_a = regions[a]
        regions[a] = (chunks_a | chunks_b, sum_a + sum_b, n_a + n_b)
        pairs = {(min(p, q), max(p, q)) for p, q in
                 ((a if p == b else p, a if q == b else q) for p, q in pairs) if p != q}
    masks = []
    for members, _, _ in regions.values():
        region = np.zeros_like(mask)
        region[tuple(cells[np.isin(chunk, list(members))].T)] = True
        masks.append(region)
    return sorted(masks, key=lambda m: -int(m.sum()))
