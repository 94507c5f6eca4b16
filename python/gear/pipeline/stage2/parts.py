"""Stage 2's parts: the canonical state, the number of parts K, which components move
together, the part logits and the motion candidates handed to stage 3 (docs/method.md,
"Stage 2")."""

from __future__ import annotations

import heapq
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np

from gear import geometry
from gear.articulation import RigidMotion
from gear.data.scene import other_state
from gear.geometry import NearestTree
from gear.pipeline.stage2.frame import body_frame
from gear.pipeline.stage2.frame_slides import FrameSlide, frame_slides
from gear.pipeline.stage2.hypotheses import DETECT_OVERLAP, IDENTITY, Hypothesis, fit_plane
from gear.pipeline.stage2.regions import (
    AGREE_VOXELS,
    MERGE_COST,
    extra_residual,
    motion_regions,
    one_motion,
)
from gear.pipeline.stage2.seen_through import claim_seen_through
from gear.pipeline.stage2.voxels import (
    MAX_TARGET_CANDIDATES,
    MIN_PART_VOXELS,
    TIE_MARGIN,
    Scale,
    SurfaceTest,
    VoxelSplit,
    init_motion,
    split_static_dynamic,
)

# Logit seeding: +SEED inside a part's component (-SEED for the other parts); elsewhere the
# static part gets +LEAN and the movable parts -LEAN (static-leaning, still easy to overturn).
SEED_LOGIT = 3.0
STATIC_LEAN = 1.0
# K from the data: a canonical piece is a part when it has at least MIN_PART_VOXELS voxels,
# holds MIN_PART_FRACTION of the canonical centres and some motion maps it onto the target's
# dynamic voxels (overlap >= DETECT_OVERLAP).
MIN_PART_FRACTION = 0.01
# ... or, small and long (_large_enough), this fraction of the centres over this fraction of
# the object's extent.
MIN_SMALL_PART_FRACTION = 0.006
MIN_PART_EXTENT = 0.15
# With the target state's images (`surfaces`), a part must also be seen to move: at least
# this fraction of its centres seen on the target's surface once moved, and seen through (empty)
# where they were. Real doors score well above it, floaters well below (docs/method.md,
# "K from the data").
MIN_SEEN_CHANGE = 0.6
SURFACE_TOLERANCE_VOXELS = 2.0
MIN_SEEN_THERE = 0.5
# A piece whose best motion leaves at least this fraction of its cells off target matter is
# split: the rest gets a motion of its own (_split_by_motion).
SPLIT_FRACTION = 0.2
# A piece joins a sliding part only when at least this share of its cross-section across the
# slide lies within the part's (_in_line).
IN_LINE_SHARE = 0.5
IN_LINE_MARGIN = 3.0
# With the target images, a piece also moves with a part when, under the part's motion, the
# images see it at least this share as much on their surfaces as under its own motion, and see
# through at most SEEN_THROUGH_AT_MOST of its centres (_seen_alike). A real sink cabinet's
# 32.7 degree door came as two pieces, the upper and the lower part of its front; moved by the
# door's turn the lower one comes to rest about two voxels behind the closed front the target
# state reconstructed (landed 0.38), on the target's surfaces 0.22 and seen through nowhere,
# against 0.36 under a slide that lands it 0.71 on other matter. A door moved by its
# neighbour's turn or a drawer's slide is seen at most 0.2 as much (the real fast models), or
# seen through.
SEEN_ALIKE_SHARE = 0.5
SEEN_THROUGH_AT_MOST = 0.05
MIN_SEEN_ON_SURFACE = 0.1


@dataclass
class CoarseInit:
    """Stage-2 result: canonical state, part count, per-Gaussian part logits [N_canonical, K]
    (float32), one canonical -> target (R 3x3, t 3) per movable part, the voxel size used and
    human-readable notes on the choices made."""

    canonical: str
    num_parts: int
    logits: np.ndarray
    motions: list[RigidMotion]
    voxel_size: float
    notes: list[str] = field(default_factory=list)
    # Per movable part: its motion first, then any near-tie of the other kind (hinge vs slide)
    # for stage3.joint_types.classify_joints to decide by the images.
    candidates: list[list[RigidMotion]] = field(default_factory=list)
    # Per movable part: the deepest shift its slide is held to in stage 3 (direction and
    # reach of a drawer pushed along the body's frame, frame_slides), else None.
    held_slides: list[np.ndarray | None] = field(default_factory=list)


def _check_points(points: np.ndarray, name: str) -> np.ndarray:
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"{name}: expected shape [N, 3], got {list(pts.shape)}")
    if len(pts) < 4:
        raise ValueError(f"{name}: needs at least 4 points, got {len(pts)}")
    if not np.isfinite(pts).all():
        raise ValueError(f"{name}: contains non-finite coordinates")
    return pts


def mean_nn_distance(queries: np.ndarray, reference: np.ndarray) -> float:
    _, dist = geometry.knn(reference.astype(np.float32), 1, queries=queries.astype(np.float32))
    return float(dist[:, 0].mean())


def choose_canonical(start: np.ndarray, end: np.ndarray) -> tuple[str, str]:
    """The state whose centres lie farther, on average, from the other state's."""
    d_start = mean_nn_distance(start, end)
    d_end = mean_nn_distance(end, start)
    canonical = "end" if d_end > d_start else "start"
    return (
        canonical,
        f"canonical '{canonical}' (mean NN distance start->end {d_start:.4g}, "
        f"end->start {d_end:.4g})",
    )


def seed_logits(part_of_point: np.ndarray, num_parts: int) -> np.ndarray:
    """Logits [N, K]: +SEED/-SEED for points of a part's component, static-leaning elsewhere."""
    n = len(part_of_point)
    logits = np.full((n, num_parts), -STATIC_LEAN, dtype=np.float32)
    logits[:, 0] = STATIC_LEAN
    seeded = part_of_point > 0
    logits[seeded] = -SEED_LOGIT
    logits[seeded, part_of_point[seeded]] = SEED_LOGIT
    return logits


def _moves_along(
    split: VoxelSplit, cells: np.ndarray, points: np.ndarray, motion: Hypothesis,
    hyps: list[Hypothesis], region: bool = False,
) -> bool:
    """Whether a component (its `cells` and centres `points`, its own readings `hyps`, the
    best first) moves with an existing part: that part's `motion` explains it (is trusted on
    its cells) and lands it nearly as well as the component's own best motion (within
    TIE_MARGIN when it explains at least as much of the change), or agrees with that motion,
    moving its centres to within AGREE_VOXELS of where its own motion puts them (median). Both
    readings fit the same turn of a lever to its two fragments; the small one's own fit may
    land its few cells a little better, which is noise, not a second part. A `region` (cut
    off because it needs a motion of its own, regions.motion_regions) must also pass the test
    that cut it: `motion` may cost its centres at most MERGE_COST more than its own."""
    own = hyps[0]
    shared = split.score(cells, motion.kind, motion.rot, motion.trans)
    if not shared.trusted:
        return False
    if region and extra_residual(split, points, motion, hyps) > MERGE_COST:
        return False  # cut off by the test that it needs a motion of its own
    if shared.landed >= own.landed - 0.05:
        return True
    if _seen_alike(split, points, motion, own):
        return True
    if shared.landed >= own.landed - TIE_MARGIN and shared.explained >= own.explained:
        return True  # own lands a little more, but on matter that did not change
    apart = np.linalg.norm(points @ (np.asarray(motion.rot) - np.asarray(own.rot)).T
                           + (np.asarray(motion.trans) - np.asarray(own.trans)), axis=1)
    return bool(np.median(apart) <= AGREE_VOXELS * split.grid.voxel_size)


def _seen_alike(split: VoxelSplit, points: np.ndarray, motion: Hypothesis,
                own: Hypothesis) -> bool:
    """Whether the target images (split.on_surface) see the centres `points` moved by `motion`
    about as well as moved by their piece's `own` motion: on the target's surface at least
    MIN_SEEN_ON_SURFACE of them and SEEN_ALIKE_SHARE as many as under `own`, seen through at
    most SEEN_THROUGH_AT_MOST. The voxel landing cannot tell a piece the target state hides,
    or holds a voxel or two apart, from one moved into empty space; the images can."""
    if split.on_surface is None:
        return False

    def seen(m: Hypothesis) -> tuple[float, float]:
        moved = points @ np.asarray(m.rot).T + np.asarray(m.trans)
        on, through = split.on_surface(moved, split.surface_tolerance)
        return float(on.mean()), float(through.mean())

    on, through = seen(motion)
    if on < MIN_SEEN_ON_SURFACE or through > SEEN_THROUGH_AT_MOST:
        return False
    return on >= SEEN_ALIKE_SHARE * seen(own)[0]


def _joins(split: VoxelSplit, pieces: np.ndarray, part: _Part, cells: np.ndarray,
           points: np.ndarray, hyps: list[Hypothesis], is_region: bool) -> bool:
    """Whether a piece (`cells`, `points`, its own readings `hyps`) moves with `part` under one
    of the part's readings, in line with the part's cells (computed once, when needed)."""
    part_cells = None
    for h in part.hypotheses:
        if not _moves_along(split, cells, points, h, hyps, is_region):
            continue
        if part_cells is None:
            part_cells = np.argwhere(np.isin(pieces, part.components))
        if _in_line(cells, part_cells, h):
            return True
    return False


def _in_line(cells: np.ndarray, part_cells: np.ndarray, motion: Hypothesis) -> bool:
    """Whether a piece's `cells` lie in line with a part's `part_cells` along the part's
    `motion` when it is a slide: at least IN_LINE_SHARE of the piece's cells fall, seen along
    the slide, inside the box bounding the part's cells (grown by IN_LINE_MARGIN cells: the
    walls of a drawer's box reach past its front's edges by a cell or two). The front and back
    of one pulled drawer do; two drawers of a column pulled by the same travel do not, and stay
    two parts although one motion lands both. (The box, not the part's own cross-section: a
    sparse model leaves holes in a drawer's front.) Turns always pass."""
    if motion.kind != "slide":
        return True
    share = geometry.share_in_line(cells, part_cells, motion.trans, IN_LINE_MARGIN)
    return share >= IN_LINE_SHARE


@dataclass
class _Part:
    components: list[int]
    hypotheses: list[Hypothesis]  # the motion first, then a near-tie of the other kind
    # The deepest shift of a slide held to the body's frame (frame_slides), else None.
    held: np.ndarray | None = None

    @property
    def motion(self) -> Hypothesis:
        return self.hypotheses[0]


def seen_change(
    points: np.ndarray, motion: Hypothesis, on_surface: SurfaceTest, tolerance: float
) -> float:
    """Whether the target images see a component move: the smaller of the fraction of its
    centres on the target's surface where `motion` puts them (of those the images can see
    there) and the fraction seen through (empty) where they are. Matter only one state reveals
    (a cabinet's interior, hidden behind the closed door, not empty) or a surface the two
    reconstructions merely place a little differently (still there) scores low.

    A centre that the motion puts behind the target's surface in every view (neither on it nor
    seen through) is out of sight, not contradicted: a pushed-in drawer's box disappears into
    the cabinet. Counting it as missed rejected a well-trained drawer whose hidden box holds
    half of its Gaussians; a component moved wholly out of sight is still not seen to move."""
    moved = points @ np.asarray(motion.rot).T + np.asarray(motion.trans)
    landed, in_front = on_surface(moved, tolerance)
    visible = landed | in_front
    stayed, vacated = on_surface(points, tolerance)
    landed_share = landed.sum() / visible.sum() if visible.any() else 0.0
    seen_there = stayed | vacated
    vacated_share = (vacated.sum() / seen_there.sum() if seen_there.mean() >= MIN_SEEN_THERE
                     else vacated.mean())
    return float(min(landed_share, vacated_share))


def change_in_sight(split: VoxelSplit, cells: np.ndarray, motion: Hypothesis) -> float:
    """The share of target change that `cells` [M, 3] moved by `motion` cover (as
    Hypothesis.explained), counted over the moved cells the target images (`split.on_surface`,
    within `split.surface_tolerance`) can see where they land (on the surface or seen
    through); 0 without images. A drawer pushed in puts most of its box inside the
    cabinet, where the closed state has no matter and no view looks: counted over all its
    cells, the true slide of a real tall cabinet's drawer covered 0.285, under DETECT_OVERLAP;
    over those in sight, its front, 0.52."""
    if split.on_surface is None:
        return 0.0
    moved = split.grid.centres(cells) @ np.asarray(motion.rot).T + np.asarray(motion.trans)
    on, seen_through = split.on_surface(moved, split.surface_tolerance)
    in_sight = cells[on | seen_through]
    if len(in_sight) == 0:
        return 0.0
    return split.score(in_sight, motion.kind, motion.rot, motion.trans).explained


def _split_by_motion(split: VoxelSplit, mask: np.ndarray, motion: Hypothesis) -> list[np.ndarray]:
    """The 26-connected pieces (of at least MIN_PART_VOXELS cells) of the cells of `mask` that
    `motion` does not land on target matter, when those are at least MIN_PART_VOXELS cells and
    SPLIT_FRACTION of `mask`; else none. A door and the drawer beside it touch, so their
    dynamic voxels form one component, but no one rigid motion lands both; a rigid part whose
    motion leaves a few cells where the target saw nothing (its hidden side) stays whole."""
    cells = np.argwhere(mask)
    rest = cells[~split.landing(cells, motion)]
    if len(rest) < max(MIN_PART_VOXELS, SPLIT_FRACTION * len(cells)):
        return []
    rest_mask = np.zeros_like(mask)
    rest_mask[tuple(rest.T)] = True
    labels, sizes = geometry.components(rest_mask, connectivity=26)
    return [labels == i for i, size in enumerate(sizes, start=1) if size >= MIN_PART_VOXELS]


def _pieces_apart(
    split: VoxelSplit, mask: np.ndarray, hyps: list[Hypothesis],
    points_of: Callable[[np.ndarray], np.ndarray], total: int | None, extent: float,
    by_regions: bool,
) -> tuple[list[_Piece], list[_Piece]]:
    """The pieces to cut off the cells `mask` as parts of their own, with their motions
    (_own_motion; `points_of(cells)` gives the canonical centres in `cells`): first the cells
    its motion (the reading in `hyps` landing most) leaves off target matter
    (_split_by_motion), then, of what remains, the regions that need motions of their own
    (regions.motion_regions, all but the largest; not when `by_regions` is False: the piece is
    such a region already): touching doors turned by a few tens of degrees land nearly whole
    under one slide, so only the motions of their regions tell them apart. Returns (the missed
    pieces, the regions)."""
    # Split by the reading landing most: a door folded by half a turn shows the target its
    # formerly hidden face, so its fold lands only half of it where the slide of the slab
    # lands all.
    widest = max(hyps, key=lambda h: h.landed)

    def parts_of(masks: list[np.ndarray]) -> list[_Piece]:
        found = [(m, _own_motion(split, m, points_of(m), total, extent)) for m in masks]
        return [_Piece(m, motion) for m, motion in found if motion is not None]

    rest = parts_of(_split_by_motion(split, mask, widest))
    remaining = mask.copy()
    for piece in rest:
        remaining &= ~piece.cells
    regions = motion_regions(split, remaining, points_of(remaining), hyps) if by_regions else []
    return rest, parts_of(regions[1:])


@dataclass
class _Piece:
    """Cells cut off a piece (a grid mask) and the motion that makes them a part of their own."""

    cells: np.ndarray
    motion: Hypothesis


def _own_motion(
    split: VoxelSplit, piece: np.ndarray, points: np.ndarray, total: int | None, extent: float,
) -> Hypothesis | None:
    """The motion of the cells `piece` (holding `points`) when they are a part of their own:
    at least 4 centres (with K unknown, `total` canonical centres, _large_enough), and a
    motion that lands all but SPLIT_FRACTION of it and explains DETECT_OVERLAP of the change
    it maps onto, other than a half-turn fold; else None. A fold shows the target a slab's
    formerly hidden face, so where things land cannot tell a door folded flat from what it
    uncovers: that stays one piece (the images, not the voxels, tell a fold)."""
    if len(points) < 4 or (total is not None and not _large_enough(points, total, extent)):
        return None
    own = init_motion(split, piece, points)[0]
    if own.fold or own.explained < DETECT_OVERLAP or own.landed < 1 - SPLIT_FRACTION:
        return None
    return own


def _remainder_taken(split: VoxelSplit, remainder: np.ndarray, pieces: list[_Piece],
                     own: Hypothesis) -> list[np.ndarray] | None:
    """The cells of `pieces` grown by all of `remainder` (what is left of the piece they were
    cut off), when their motions together land all but SPLIT_FRACTION of the remainder and
    more of it than its own motion `own` does; else None. Two doors stacked on one hinge line
    and turned by different angles form one piece: the reading landing most leaves each door's
    far side off target matter, and those are cut off with their own turns, but the strip
    along the shared hinge moves little under any turn about the line and stays behind as a
    piece mixing both doors, landed half by any one turn (a real cabinet's: 0.53) and 0.95 by
    the two doors' turns. It is no part: each of its cells goes to the nearest piece whose
    motion lands it (the nearest piece when none does)."""
    cells = np.argwhere(remainder)
    if len(cells) == 0:
        return None
    lands = np.stack([split.landing(cells, piece.motion) for piece in pieces], axis=1)
    landed = float(lands.any(axis=1).mean())
    if landed < 1 - SPLIT_FRACTION or landed <= own.landed:
        return None
    dist = np.stack([NearestTree(np.argwhere(piece.cells)).query(cells)[0] for piece in pieces],
                    axis=1)
    landing_dist = np.where(lands, dist, np.inf)
    nearest = np.where(lands.any(axis=1), landing_dist.argmin(axis=1), dist.argmin(axis=1))
    grown = [piece.cells.copy() for piece in pieces]
    for index, piece_cells in enumerate(grown):
        piece_cells[tuple(cells[nearest == index].T)] = True
    return grown


def _large_enough(points: np.ndarray, total: int, extent: float) -> bool:
    """Whether a piece of `points` (of `total` canonical centres, the object `extent` across)
    is big enough to be a part when K is unknown: MIN_PART_FRACTION of the centres, or, for a
    small or thin part (a lever, a temple of glasses), MIN_SMALL_PART_FRACTION of them spread
    over MIN_PART_EXTENT of the object. Noise clusters of that many centres are compact."""
    if len(points) >= MIN_PART_FRACTION * total:
        return True
    if len(points) < max(4, MIN_SMALL_PART_FRACTION * total):
        return False
    return bool(fit_plane(points).extents[0] >= MIN_PART_EXTENT * extent)


def find_parts(
    canon: np.ndarray, target: np.ndarray, num_parts: int | None, voxel_size: float,
    on_surface: SurfaceTest | None = None, dilation_radius: int = 1,
) -> tuple[list[_Part], np.ndarray, list[str]]:
    """Movable parts (their canonical pieces and initial motion) and each canonical point's
    piece label.

    The dynamic region is explained by as few rigid motions as it needs. Pieces (at first the
    canonical components) are visited largest first. One that an earlier part's motion moves
    onto target matter about as well as its own best motion joins that part: a pulled drawer
    leaves two separate dynamic pieces, its front and its back. Otherwise the cells its best
    motion does not land, when enough (_split_by_motion), are cut off as pieces of their own
    and visited in turn, and the motion is fitted again to the cells it explains. With K given,
    parts whose motion is trusted come first and untrusted pieces (identity motion) fill the
    remaining slots. With K unknown, a piece becomes a part only above the size floors and when
    its motion explains at least DETECT_OVERLAP of the change it maps onto, and, given
    `on_surface`, when the target images see it move (seen_change >= MIN_SEEN_CHANGE).
    """
    split = split_static_dynamic(canon, target, voxel_size, dilation_radius)
    split.on_surface = on_surface
    split.surface_tolerance = SURFACE_TOLERANCE_VOXELS * voxel_size
    wanted = None if num_parts is None else num_parts - 1
    search = _PartSearch(split, canon, wanted)
    search.run()
    parts = search.parts
    if wanted is not None:
        parts += search.spare[: max(0, wanted - len(parts))]
    return parts, search.canon_labels, search.notes


class _PartSearch:
    """find_parts' visit of the pieces, largest first: the pieces' grid labels (cut pieces get
    fresh ones), each canonical centre's piece label, the parts found so far, the target cells
    they land on (_first_on_free_matter), and the notes."""

    def __init__(self, split: VoxelSplit, canon: np.ndarray, wanted: int | None) -> None:
        self.split, self.canon, self.wanted = split, canon, wanted
        self.pieces = split.labels[0].copy()
        self.canon_labels = split.grid.point_labels(canon, self.pieces)
        sizes = split.sizes[0]
        self.notes = [
            f"voxel size {split.grid.voxel_size:.4g}: {len(sizes)} canonical and "
            f"{len(split.sizes[1])} target dynamic components (largest {sizes[:6].tolist()})"
        ]
        self.extent = Scale.extent_of(canon)
        self._point_cells = split.grid.voxel_of(canon)
        self._in_grid = np.all(
            (self._point_cells >= 0) & (self._point_cells < np.array(split.grid.shape)), axis=1)
        visit = max(MAX_TARGET_CANDIDATES, 2 * (wanted or 0))
        # Max-heap of (voxels, piece label).
        self.queue = [(-int(size), comp) for comp, size in enumerate(sizes[:visit], start=1)]
        heapq.heapify(self.queue)
        self.next_label = len(sizes) + 1
        self.parts: list[_Part] = []
        self.spare: list[_Part] = []
        self.regions_of: set[int] = set()  # pieces that are already one motion's region
        self.claimed = np.zeros(split.grid.shape, dtype=bool)
        # The body's frame (the faces of the centres in no dynamic piece), along which a piece
        # that claims no part may still be drawers side by side (_drawers); only with K from
        # the images.
        self.frame = (body_frame(canon[self.canon_labels == 0])
                      if wanted is None and split.on_surface is not None else None)

    def centres_in(self, mask: np.ndarray) -> np.ndarray:
        """The canonical centres in the cells of `mask`."""
        inside = np.zeros(len(self.canon), dtype=bool)
        inside[self._in_grid] = mask[tuple(self._point_cells[self._in_grid].T)]
        return self.canon[inside]

    def run(self) -> None:
        while self.queue:
            size, comp = heapq.heappop(self.queue)
            self._visit(comp, -size)

    def _visit(self, comp: int, voxels: int) -> None:
        """One piece: joined to a part, cut, made a part (or drawers), or left static."""
        mask = self.pieces == comp
        points = self.canon[self.canon_labels == comp]
        if voxels < MIN_PART_VOXELS or len(points) < 4:
            return
        if self.wanted is None and not _large_enough(points, len(self.canon), self.extent):
            return
        hyps = init_motion(self.split, mask, points)
        if self._joined(comp, mask, points, hyps):
            return
        # Cutting a component multiplies the candidates for parts: with K unknown, only the
        # target images can reject the pieces that merely land somewhere (safe180's interior,
        # uncovered by its door, lands on the closed door once shifted), so without them
        # components stay whole.
        if hyps[0].trusted and (self.split.on_surface is not None or self.wanted is not None):
            cut = self._cut(comp, mask, hyps)
            if cut is None:
                return
            points, hyps = cut
        self._place(comp, mask, points, hyps)

    def _joined(self, comp: int, mask: np.ndarray, points: np.ndarray,
                hyps: list[Hypothesis]) -> bool:
        """Whether the piece joins a part found before it (_joins). Any reading of a part
        counts: a safe door's dial, a component of its own, moves with the door only under
        the half turn that may not be the door's first reading."""
        cells = np.argwhere(mask)
        owner = next((p for p in self.parts if _joins(
            self.split, self.pieces, p, cells, points, hyps, comp in self.regions_of)), None)
        if owner is None:
            return False
        owner.components.append(comp)
        self.claimed |= self.split.landing_cells(cells, owner.motion)
        return True

    def _cut(self, comp: int, mask: np.ndarray,
             hyps: list[Hypothesis]) -> tuple[np.ndarray, list[Hypothesis]] | None:
        """Cuts off the piece `mask` (in place) the pieces that are parts of their own
        (_pieces_apart), queued to be visited in turn, or hands it all to them
        (_remainder_taken). Returns the centres and readings of what is left of it to place,
        or None when nothing is. A piece is cut off only when it is a part of its own: big
        enough, with a motion that lands it and claims change. The far end of a small lever,
        missed by its slightly wrong first turn, is neither."""
        total = len(self.canon) if self.wanted is None else None
        missed, apart = _pieces_apart(self.split, mask, hyps, self.centres_in, total,
                                      self.extent, comp not in self.regions_of)
        rest = missed + apart
        remainder = mask.copy()
        for piece in rest:
            remainder &= ~piece.cells
        points = self.centres_in(remainder)
        taken = None
        if rest and len(points) >= 4:
            hyps = init_motion(self.split, remainder, points)
            taken = _remainder_taken(self.split, remainder, rest, hyps[0])
        cut = [piece.cells for piece in rest] if taken is None else taken
        for index, piece_cells in enumerate(cut):
            mask &= ~piece_cells
            label = self._new_piece(piece_cells)
            if index >= len(missed):
                self.regions_of.add(label)  # one motion's region: not cut again
            heapq.heappush(self.queue, (-int(piece_cells.sum()), label))
        if not rest:
            return points, hyps
        self.canon_labels = self.split.grid.point_labels(self.canon, self.pieces)
        self.notes.append(f"component {comp}: {len(rest)} piece(s) its motion does not "
                          "explain split off")
        if taken is not None:
            self.notes.append(f"component {comp}: what remains of it joins those pieces, whose "
                              f"motions land more of it than its own ({hyps[0].landed:.2f})")
            return None
        return (points, hyps) if len(points) >= 4 else None

    def _new_piece(self, cells: np.ndarray) -> int:
        """Labels the grid mask `cells` as a new piece; returns its label."""
        label = self.next_label
        self.pieces[cells] = label
        self.next_label += 1
        return label

    def _place(self, comp: int, mask: np.ndarray, points: np.ndarray,
               hyps: list[Hypothesis]) -> None:
        """The piece `mask` (holding `points`, read as `hyps`) as a part when it claims one,
        else (K given) a spare, else drawers side by side when it holds any."""
        cells = np.argwhere(mask)
        hyps, free = _first_on_free_matter(self.split, self.claimed, cells, hyps)
        if free is not None:
            self.notes.append(f"component {comp}: its {hyps[1].kind} lands only {free:.2f} "
                              f"on matter no earlier part lands on: {hyps[0].kind} first")
        detected, seen = _claims_a_part(self.split, cells, points, hyps[0],
                                        images=self.wanted is None)
        if seen is not None:
            self.notes.append(f"component {comp} not a part: the target images see only "
                              f"{seen:.2f} of it move")
        elif not detected and self.wanted is None and hyps[0].trusted:
            self.notes.append(f"component {comp} not a part: its {hyps[0].kind} explains "
                              f"{hyps[0].explained:.2f} of the change it maps onto, under "
                              f"{DETECT_OVERLAP}")
        if hyps[0].trusted and (detected or self.wanted is not None):
            if self.wanted is None and self._one_motion_with_a_part(comp, points, hyps[0]):
                return
            if self.wanted is None or len(self.parts) < self.wanted:
                self.parts.append(_Part([comp], hyps))
                self.claimed |= self.split.landing_cells(cells, hyps[0])
        elif self.wanted is not None:
            self.spare.append(_Part([comp], [IDENTITY]))
        elif self.frame is not None:
            self._add_drawers(comp, mask)

    def _one_motion_with_a_part(self, comp: int, points: np.ndarray, own: Hypothesis) -> bool:
        """Whether the piece `comp` (holding `points`, its motion `own`), about to become a part
        of its own (K unknown), joins a part found before it instead: one rigid motion of the
        two together (regions.one_motion) costs their centres at most MERGE_COST more than
        their two motions apart (the test that keeps two chunks of one door together) and
        lands each of them within TIE_MARGIN of its own motion (a piece that lands nowhere
        under any motion, matter only one state shows, costs as much alone as joined), in
        line with it when it slides (_in_line: two drawers of a column pulled alike stay two
        parts). Two pieces of one thick lid read apart fit two turns 21 degrees apart (the
        real stapler at fast: the smaller piece's own turn, 23 degrees off the hinge, lands
        it 0.93 and the lid's, 1.8 degrees off, only 0.79), while one motion of both lands
        each about as well (0.91 and 0.89 against 0.92 and 0.93) and costs 0.001 less per
        centre."""
        cells = np.argwhere(self.pieces == comp)
        for part in self.parts:
            part_cells = np.argwhere(np.isin(self.pieces, part.components))
            if not _in_line(cells, part_cells, part.motion):
                continue
            part_points = self.canon[np.isin(self.canon_labels, part.components)]
            if len(part_points) < 4:
                continue
            extra, joint = one_motion(self.split, [(part_points, part.motion), (points, own)])
            if extra > MERGE_COST or not all(
                    self.split.score(c, "hinge", joint.rot, joint.trans).landed
                    >= motion.landed - TIE_MARGIN
                    for c, motion in ((part_cells, part.motion), (cells, own))):
                continue
            part.components.append(comp)
            self.claimed |= self.split.landing_cells(cells, part.motion)
            self.notes.append(f"component {comp}: one motion of it and the part of components "
                              f"{part.components[:-1]} lands both and costs {extra:+.3f} per "
                              "centre against their two motions apart: joined")
            return True
        return False

    def _add_drawers(self, comp: int, mask: np.ndarray) -> None:
        """The drawers side by side in a piece that claims no part as a whole (_drawers), each
        a part of its own held to its slide."""
        drawers = _drawers(self.split, mask, self.frame, self.centres_in, len(self.canon),
                           self.extent)
        for drawer in drawers:
            label = self._new_piece(drawer.cells)
            self.parts.append(_Part([label], [drawer.motion], held=drawer.deepest))
            self.claimed |= self.split.landing_cells(np.argwhere(drawer.cells), drawer.motion)
        if drawers:
            self.canon_labels = self.split.grid.point_labels(self.canon, self.pieces)
            travels = ", ".join(f"{np.linalg.norm(d.motion.trans):.3g}" for d in drawers)
            self.notes.append(f"component {comp}: {len(drawers)} drawer(s) pushed along the "
                              f"body's frame by {travels}")


def _drawers(split: VoxelSplit, mask: np.ndarray, frame: np.ndarray,
             points_of: Callable[[np.ndarray], np.ndarray], total: int,
             extent: float) -> list[FrameSlide]:
    """The drawers of a piece (`mask`) that claims no part as a whole, pushed along the body's
    `frame` each by its own travel (frame_slides.frame_slides; `points_of(mask)` gives the
    canonical centres in a grid mask), those big enough for a part (_large_enough, of `total`
    centres, the object `extent` across) that the target images see move (seen_change)."""
    kept = []
    for drawer in frame_slides(split, mask, frame, points_of):
        points = points_of(drawer.cells)
        if len(points) < 4 or not _large_enough(points, total, extent):
            continue
        if seen_change(points, drawer.motion, split.on_surface,
                       split.surface_tolerance) >= MIN_SEEN_CHANGE:
            kept.append(drawer)
    return kept


def _claims_a_part(split: VoxelSplit, cells: np.ndarray, points: np.ndarray,
                   motion: Hypothesis, images: bool) -> tuple[bool, float | None]:
    """Whether the piece `cells` (holding the canonical centres `points`) moved by `motion`
    claims a part: its motion explains DETECT_OVERLAP of the change it maps onto, over all
    its moved cells or (a trusted motion) over those in sight (change_in_sight); and, when
    `images` and the split has them, the target images see it move (seen_change >=
    MIN_SEEN_CHANGE). Returns the verdict and, when the images alone rejected it, how much of
    it they saw move (else None)."""
    detected = motion.explained >= DETECT_OVERLAP or (
        motion.trusted and change_in_sight(split, cells, motion) >= DETECT_OVERLAP)
    if not (detected and images and split.on_surface is not None):
        return detected, None
    seen = seen_change(points, motion, split.on_surface, split.surface_tolerance)
    if seen >= MIN_SEEN_CHANGE:
        return True, None
    return False, seen


def _first_on_free_matter(split: VoxelSplit, claimed: np.ndarray, cells: np.ndarray,
                          hyps: list[Hypothesis]) -> tuple[list[Hypothesis], float | None]:
    """A piece's readings `hyps` reordered when its first, a hinge, goes first over a slide
    by the near-tie rule only thanks to target matter that earlier parts land on: two parts
    cannot fill the same place, so with the `claimed` cells taken out the hinge must still
    land within TIE_MARGIN of the slide. A short drawer of a mirror-symmetric cabinet is
    also "folded" by a half turn onto the other column's drawer (storage7 at 128²: the fold
    landed 0.91 and went first over a slide landing 0.99; on what no other part lands on it
    lands 0.10). Returns the readings, and the hinge's landing on free matter when it moved
    behind the slide (else None)."""
    if hyps[0].kind != "hinge" or not claimed.any():
        return hyps, None
    slide = next((h for h in hyps[1:] if h.kind == "slide"), None)
    if slide is None:
        return hyps, None
    free = split.without(claimed)
    hinge_free = free.score(cells, "hinge", hyps[0].rot, hyps[0].trans).landed
    slide_free = free.score(cells, "slide", slide.rot, slide.trans).landed
    if hinge_free >= slide_free - TIE_MARGIN:
        return hyps, None
    return [slide, *(h for h in hyps if h is not slide)], hinge_free


def _holds_a_part(parts: list[_Part], canon_labels: np.ndarray) -> bool:
    """Whether some part has a trusted motion and at least MIN_PART_FRACTION of the centres."""
    return any(
        p.motion.trusted
        and np.isin(canon_labels, p.components).mean() >= MIN_PART_FRACTION
        for p in parts
    )


def coarse_init(
    means_start: np.ndarray,
    means_end: np.ndarray,
    num_parts: int | None = None,
    voxel_size: float | None = None,
    surfaces: Mapping[str, SurfaceTest] | None = None,
    dilation_radius: int = 1,
) -> CoarseInit:
    """Stage 2 on the two states' centres: canonical state, K, part logits and initial part
    motions (docs/method.md, "Stage 2").

    `num_parts` (K, static part included) and `voxel_size` are estimated from the data when None.
    `surfaces[state]`, when given, is that state's SurfaceTest (from its images); K estimation
    then keeps only parts the target state's images see move. `dilation_radius` (voxels) grows
    the static set before the dynamic components are cut out of each state.
    """
    start = _check_points(means_start, "means_start")
    end = _check_points(means_end, "means_end")
    if num_parts is not None and (int(num_parts) != num_parts or num_parts < 1):
        raise ValueError(f"num_parts must be a positive integer, got {num_parts}")
    if voxel_size is not None and not (np.isfinite(voxel_size) and voxel_size > 0):
        raise ValueError(f"voxel_size must be a positive number, got {voxel_size}")

    canonical, note = choose_canonical(start, end)
    canon, target = (start, end) if canonical == "start" else (end, start)
    notes = [note]
    target_surface = None if surfaces is None else surfaces[other_state(canonical)]
    on_surface = target_surface if num_parts is None else None
    radius = dilation_radius
    if voxel_size is not None:
        size = float(voxel_size)
        parts, canon_labels, more = find_parts(canon, target, num_parts, size, on_surface, radius)
    elif num_parts is not None:
        scale = Scale.of(np.concatenate([canon, target]))
        size = scale.voxel_size(single_part=num_parts == 2)
        parts, canon_labels, more = find_parts(canon, target, num_parts, size, on_surface, radius)
        if num_parts == 2 and not _holds_a_part(parts, canon_labels):
            # A motion under one coarse voxel (a door turned by 2 degrees, a drawer pulled by
            # 1 % of the object) leaves the coarse grid nothing, or a few stray cells. The fine
            # grid sees it, and sampling noise too: only a part passing the voxel tests of K
            # unknown counts (not the image check: K is given, as on the coarse grid).
            fine = scale.voxel_size(single_part=False)
            found, labels, notes_fine = find_parts(canon, target, None, fine, None, radius)
            if found:
                notes.append("the coarse grid shows no part that moves; the fine grid does")
                size, parts, canon_labels, more = fine, found[:1], labels, notes_fine
    else:
        # Detect and initialise on the fine grid, even when one part is found: the paper's
        # coarse grid cost hinges and degrees of angle (docs/method.md, "K from the data").
        size = Scale.of(np.concatenate([canon, target])).voxel_size(single_part=False)
        parts, canon_labels, more = find_parts(canon, target, None, size, on_surface, radius)
        notes.append(f"K = {len(parts) + 1} estimated from the data")
    notes += more

    if not parts:
        notes.append("no motion detected between the two states: one static part")
        logits = seed_logits(np.zeros(len(canon), np.int64), 1)
        return CoarseInit(canonical, 1, logits, [], size, notes, [])

    k = len(parts) + 1 if num_parts is None else int(num_parts)
    part_of_point = np.zeros(len(canon), dtype=np.int64)
    candidates = []
    for index, part in enumerate(parts, start=1):
        part_of_point[np.isin(canon_labels, part.components)] = index
        candidates.append([(h.rot, h.trans) for h in part.hypotheses])
        scores = ", ".join(
            f"{h.kind} (landed {h.landed:.2f}, explained {h.explained:.2f})"
            for h in part.hypotheses
        )
        notes.append(
            f"part {index}: components {part.components} "
            f"({int((part_of_point == index).sum())} Gaussians), init {scores}"
        )
    held_slides = [part.held for part in parts]
    for index in range(len(parts) + 1, k):
        candidates.append([(np.eye(3), np.zeros(3))])
        held_slides.append(None)
        notes.append(f"part {index}: no dynamic component left; identity init, no seeded logits")
    motions = [c[0] for c in candidates]
    if target_surface is not None:
        part_of_point, claimed = claim_seen_through(
            canon, part_of_point, motions, target_surface, SURFACE_TOLERANCE_VOXELS * size, size)
        if claimed:
            notes.append(f"{claimed} static Gaussians the target images see through joined "
                         "the part whose motion puts them on its surface")
    logits = seed_logits(part_of_point, k)
    return CoarseInit(canonical, k, logits, motions, size, notes, candidates, held_slides)
