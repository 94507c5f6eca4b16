"""Stage 2's voxel grid: the object's scale and voxel size, the static/dynamic split of the two
states' centres with the components of each, and the initial motion of a component scored on
that grid (docs/method.md, "Stage 2")."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Protocol

import numpy as np
from scipy.ndimage import maximum_filter

from gear import geometry
from gear.articulation import RigidMotion
from gear.geometry import NearestTree
from gear.pipeline.stage2.hypotheses import (
    DETECT_OVERLAP,
    IDENTITY,
    MIN_OVERLAP,
    PARALLEL_COS,
    SWEEP_STEP_DEG,
    SWEEP_TARGETS,
    Hypothesis,
    Plane,
    correlate,
    dominant_plane,
    edge_hinges,
    fit_plane,
    hinge_candidates,
    refine_turn,
    rod_hinges,
    surface_fit,
    swept_hinges,
)

# A hinge and a slide landing within this fraction of each other are both kept as candidates
# (stage 3 picks by the images); among slides this close, the shortest wins.
TIE_MARGIN = 0.1
# ... and when both explain enough of the change to claim a part, a slide covering at least
# this much more of it than the hinge goes first; otherwise the hinge does. A drawer's slide
# covers 0.18-0.33 more than the turns that also land it (a real tall cabinet, five training
# seeds); a door opened 180° lands shifted about as well as turned, its slide covering 0.07
# more by chance.
EXPLAIN_MARGIN = 0.15
SLIDE_TOLERANCE = 0.05
# With the target images at hand, the shifts ranking at least this share of the best voxel
# landing (at most RECHECK_SLIDES of them) are judged again by what the images see, when they
# see at least MIN_VISIBLE of the moved cells.
RECHECK_SHARE = 0.5
RECHECK_SLIDES = 24
MIN_VISIBLE = 0.2
# Voxel size from the data: the object's extent divided by these cell counts (a coarse grid for
# one movable part, a fine one to separate neighbouring parts), but never finer than
# SPACING_FACTOR times the median spacing of the centres, or static surfaces would not be seen
# as occupied in both states.
CELLS_SINGLE = 16
CELLS_MULTI = 100
SPACING_FACTOR = 2.0
MIN_PART_VOXELS = 8  # a component smaller than this is no part
REFINE_STARTS = 3  # the best-fitting turns of a thick piece refined (_thick_turn)
FOLD_MARGIN = 0.15  # surface_fit a half-turn fold needs above a turn to go first
BLOB_MARGIN = 0.05  # surface_fit a blob's turn needs above the best slide to be tried
BLOB_LANDED = 0.8  # ... and the fraction of its cells it must land on target matter
IN_PLANE_STEP_DEG = 2.0  # angle step of a flat piece's turns about its normal (in_plane_turns)
IN_PLANE_COS = 0.99  # ... onto target pieces whose normals lie within 8 degrees of its own

MAX_TARGET_CANDIDATES = 16
MAX_DENSE_CELLS = 1 << 26
SPACING_SAMPLES = 20000


class SurfaceTest(Protocol):
    """What a state's images see at each point (stage2.surface.SurfaceTest):
    `test(points [M, 3], tolerance) -> (on_surface [M], seen_through [M])` in some view, and
    `votes` the number of views of each."""

    def __call__(self, points: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
        ...

    def votes(self, points: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
        ...


@dataclass
class Scale:
    """The object's size (largest side of its 0.5-99.5 percentile box) and the median distance
    between neighbouring centres; voxel sizes derive from both (see the module constants)."""

    extent: float
    spacing: float

    @staticmethod
    def extent_of(points: np.ndarray) -> float:
        """The largest side of the 0.5-99.5 percentile box of `points` (strays left out)."""
        lo, hi = np.percentile(points, [0.5, 99.5], axis=0)
        return float((hi - lo).max())

    @classmethod
    def of(cls, points: np.ndarray, seed: int = 0) -> Scale:
        rng = np.random.default_rng(seed)
        count = min(len(points), SPACING_SAMPLES)
        sample = points[rng.choice(len(points), count, replace=False)]
        # k = 2 against the full set: the first neighbour of a sampled point is itself.
        _, dist = geometry.knn(points.astype(np.float32), 2, queries=sample.astype(np.float32))
        scale = cls(cls.extent_of(points), float(np.median(dist[:, 1])))
        if not scale.extent > 0:
            raise ValueError("means: the centres have no extent (all points coincide)")
        return scale

    def voxel_size(self, single_part: bool) -> float:
        cells = CELLS_SINGLE if single_part else CELLS_MULTI
        return max(self.extent / cells, SPACING_FACTOR * self.spacing)


@dataclass
class VoxelSplit:
    """Static/dynamic split in the shared grid and the components of each state."""

    grid: geometry.VoxelGrid
    exact_target: np.ndarray  # target occupancy
    occ_target: np.ndarray  # target occupancy, dilated by one voxel
    dyn_target: np.ndarray  # target dynamic cells, dilated by one voxel
    labels: tuple[np.ndarray, np.ndarray]  # component labels (canonical, target), 0 = none
    sizes: tuple[np.ndarray, np.ndarray]  # voxel counts per label, largest first
    target_tree: NearestTree  # the target centres
    spacing: float  # their median distance to the nearest other centre
    # Target pieces a canonical piece may turn onto (init_motion): (voxels, mask over the
    # target centres), largest first (see target_pieces).
    pieces: list[tuple[int, np.ndarray]]
    # The target images' SurfaceTest and its depth tolerance, when find_parts has them:
    # best_slide then also asks the images (see there).
    on_surface: SurfaceTest | None = None
    surface_tolerance: float = 0.0
    # The planes of `pieces`, fitted once per split (init_motion reads them for every piece
    # and chunk): least-squares planes and dominant planes, by piece index.
    _piece_planes: dict[int, Plane] = field(default_factory=dict, repr=False)
    _dominant_planes: dict[int, Plane | None] = field(default_factory=dict, repr=False)

    @cached_property
    def dyn_count(self) -> int:
        """How many target dynamic cells there are (every hypothesis scored divides by it: a
        sum over the whole grid, once)."""
        return int(self.dyn_target.sum())

    def piece_plane(self, index: int) -> Plane:
        """The least-squares plane (fit_plane) of target piece `index`'s centres."""
        if index not in self._piece_planes:
            self._piece_planes[index] = fit_plane(self.target_tree.data[self.pieces[index][1]])
        return self._piece_planes[index]

    def dominant_piece_plane(self, index: int) -> Plane | None:
        """The plane holding most of target piece `index`'s centres within a voxel
        (hypotheses.dominant_plane), or None when there is none."""
        if index not in self._dominant_planes:
            centres = self.target_tree.data[self.pieces[index][1]]
            self._dominant_planes[index] = dominant_plane(centres, self.grid.voxel_size)
        return self._dominant_planes[index]

    def _moved(self, src_cells: np.ndarray, rot: np.ndarray,
               trans: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The grid cells of `src_cells` [M, 3] moved by p -> R p + t, and which of them lie
        inside the grid."""
        moved = self.grid.centres(src_cells) @ np.asarray(rot).T + np.asarray(trans)
        cells = self.grid.voxel_of(moved)
        return cells, np.all((cells >= 0) & (cells < np.array(self.grid.shape)), axis=1)

    def score(
        self, src_cells: np.ndarray, kind: str, rot: np.ndarray, trans: np.ndarray
    ) -> Hypothesis:
        """The Hypothesis of moving `src_cells` by p -> R p + t (see Hypothesis)."""
        cells, inside = self._moved(src_cells, rot, trans)
        cells = cells[inside]
        landed = self.occ_target[cells[:, 0], cells[:, 1], cells[:, 2]]
        hit = cells[self.dyn_target[cells[:, 0], cells[:, 1], cells[:, 2]]]
        # Distinct cells counted by their flat index (np.unique over rows sorts them as
        # records, several times slower).
        hit_cells = np.unique(np.ravel_multi_index(hit.T, self.grid.shape))
        explained = len(hit_cells) / max(
            1, min(len(src_cells), self.dyn_count)
        )
        return Hypothesis(kind, rot, trans, float(landed.sum()) / len(src_cells), explained)

    def landing(self, src_cells: np.ndarray, motion: Hypothesis) -> np.ndarray:
        """Which of `src_cells` [M, 3] `motion` lands on target matter (within one voxel)."""
        cells, inside = self._moved(src_cells, motion.rot, motion.trans)
        out = np.zeros(len(src_cells), dtype=bool)
        c = cells[inside]
        out[inside] = self.occ_target[c[:, 0], c[:, 1], c[:, 2]]
        return out

    def landing_cells(self, src_cells: np.ndarray, motion: Hypothesis) -> np.ndarray:
        """The target cells (a grid mask, grown by one voxel like the target's occupancy) that
        `src_cells` [M, 3] moved by `motion` fall in."""
        cells, inside = self._moved(src_cells, motion.rot, motion.trans)
        cells = cells[inside]
        out = np.zeros(self.grid.shape, dtype=bool)
        out[cells[:, 0], cells[:, 1], cells[:, 2]] = True
        return np.asarray(geometry.dilate(out, 1))

    def without(self, claimed: np.ndarray) -> VoxelSplit:
        """This split with the target cells `claimed` (a grid mask) taken out of the target's
        occupancy: what is left for a further part to land on."""
        return replace(self, exact_target=self.exact_target & ~claimed,
                       occ_target=self.occ_target & ~claimed)

    def surface_fit(self, points: np.ndarray, rot: np.ndarray, trans: np.ndarray,
                    width: float | None = None) -> float:
        """How closely `points` moved by p -> R p + t lie on the target's centres: the mean of
        exp(-(d / w)^2) over their distances d to the nearest target centre, w twice the
        target's median centre spacing or a voxel, whichever is larger (or `width` when given:
        a coarse-to-fine search starts wider). Unlike the voxel scores it varies smoothly with
        the motion. Not the spacing alone: the two states' reconstructions agree to about a
        voxel, and a long run packs its centres 20-50 times closer than that, where only exact
        coincidences would count (a blade turned by the right angle scored 0.02, as low as any
        wrong turn)."""
        return surface_fit(self.target_tree, points, rot, trans,
                           width or max(2 * self.spacing, self.grid.voxel_size))

    def best_slide(self, src_mask: np.ndarray) -> np.ndarray | None:
        """The whole-voxel translation landing most of `src_mask` on target matter among those
        explaining enough target dynamic cells (None if no shift does); with the target images
        at hand, among the well-ranked shifts, the one landing most of what they see."""
        landed, offset = correlate(self.occ_target, src_mask)
        exact, _ = correlate(self.exact_target, src_mask)
        explained, _ = correlate(self.dyn_target, src_mask)
        need = MIN_OVERLAP * min(int(src_mask.sum()), self.dyn_count)
        # Exact landings break ties within the one-voxel tolerance.
        rank = np.where(explained >= max(need, 1), landed + exact, -1.0)
        top = rank.max()
        if top < 0:
            return None
        near = np.argwhere(rank >= (1 - SLIDE_TOLERANCE) * top) + offset
        if self.on_surface is not None:
            seen = self._seen_to_land(src_mask, rank, offset)
            near = near if seen is None else seen
        # Of the shifts nearly as good as the best, the shortest: a drawer among identical
        # drawers also "fits" where its neighbour is.
        shortest = near[np.argmin(np.linalg.norm(near, axis=1))]
        return shortest * self.grid.voxel_size

    def _seen_to_land(
        self, src_mask: np.ndarray, rank: np.ndarray, offset: np.ndarray
    ) -> np.ndarray | None:
        """Of the shifts ranking at least RECHECK_SHARE of the best, those whose moved cells
        the target images see on their surface nearly as often as under the best such shift
        (of the moved cells they see at all: on the surface or seen through); None when no
        shift shows them MIN_VISIBLE of the cells.

        The voxels count a cell as landed only on matter the target reconstructed. A drawer
        pushed in puts its box inside the cabinet, where the closed state has none, and loses
        to a shift onto its identical neighbour; the images see the front land and see
        nothing where the box went."""
        # Local peaks only: the shifts next to the best are near-copies of it.
        peaks = (rank == maximum_filter(rank, size=3)) & (rank >= RECHECK_SHARE * rank.max())
        flat = np.flatnonzero(peaks)
        flat = flat[np.argsort(-rank.ravel()[flat], kind="stable")[:RECHECK_SLIDES]]
        shifts = np.stack(np.unravel_index(flat, rank.shape), axis=1) + offset
        centres = self.grid.centres(np.argwhere(src_mask))
        shares = np.full(len(shifts), -1.0)
        for i, shift in enumerate(shifts):
            on, through = self.on_surface(centres + shift * self.grid.voxel_size,
                                          self.surface_tolerance)
            visible = int((on | through).sum())
            if visible >= MIN_VISIBLE * len(centres):
                shares[i] = on.sum() / visible
        best = shares.max()
        if best <= 0:
            return None
        return shifts[shares >= (1 - SLIDE_TOLERANCE) * best]


def split_static_dynamic(
    canon: np.ndarray, target: np.ndarray, voxel_size: float, dilation_radius: int = 1
) -> VoxelSplit:
    """Voxels occupied in both states, dilated by `dilation_radius`, are static; the rest of
    each state's occupancy is dynamic, in 26-connected components."""
    lo = np.minimum(canon.min(0), target.min(0))
    hi = np.maximum(canon.max(0), target.max(0))
    cells = np.prod(np.floor((hi - lo) / voxel_size) + 1)
    if cells > MAX_DENSE_CELLS:
        raise ValueError(
            f"voxel_size {voxel_size:.4g} is too small for this object ({cells:.3g} cells, "
            f"limit {MAX_DENSE_CELLS}); use a larger voxel size"
        )
    grid = geometry.voxel_grid([canon, target], voxel_size, max_dense_cells=MAX_DENSE_CELLS)
    occ_c, occ_t = (o.to_dense(MAX_DENSE_CELLS) for o in grid.occupancy)
    static = geometry.dilate(occ_c & occ_t, dilation_radius)
    labels, sizes = [], []
    for occ in (occ_c, occ_t):
        lab, size = geometry.components(occ & ~static, connectivity=26)
        labels.append(lab)
        sizes.append(np.asarray(size, dtype=np.int64))
    # Scores tolerate one voxel: a thin moved surface lands on the neighbour cell of its match.
    near_occ = geometry.dilate(occ_t, 1)
    near_dyn = geometry.dilate(occ_t & ~static, 1)
    tree = NearestTree(target)
    sample = target[:: max(1, len(target) // SPACING_SAMPLES)]
    spacing = float(np.median(tree.query(sample, k=2)[0][:, 1]))
    pieces = target_pieces(grid, target, labels[1], sizes[1])
    return VoxelSplit(grid, occ_t, near_occ, near_dyn, (labels[0], labels[1]), (sizes[0], sizes[1]),
                      tree, max(spacing, 1e-12 * voxel_size), pieces)


def target_pieces(
    grid: geometry.VoxelGrid, target: np.ndarray, labels: np.ndarray, sizes: np.ndarray
) -> list[tuple[int, np.ndarray]]:
    """The target's dynamic components (the MAX_TARGET_CANDIDATES largest) and, besides them,
    each group of components that bridging one-voxel gaps joins, as (voxels, mask over the
    `target` centres), largest first. A thin part (a temple of glasses, a lever) is sampled by
    few centres: the state where it moved may show it as a string of fragments, none planar
    or long enough alone to give its turn, while the canonical state shows it whole."""
    point_labels = grid.point_labels(target, labels)
    pieces = [(int(size), point_labels == j)
              for j, size in enumerate(sizes[:MAX_TARGET_CANDIDATES], start=1)]
    dynamic = labels > 0
    bridged, _ = geometry.components(geometry.dilate(dynamic, 1), connectivity=26)
    bridged = np.where(dynamic, bridged, 0)
    groups = np.unique(bridged[dynamic])
    for group in groups:
        cells = bridged == group
        if len(np.unique(labels[cells])) < 2:
            continue  # one component: listed already
        pieces.append((int(cells.sum()), np.isin(point_labels, np.unique(labels[cells]))))
    pieces.sort(key=lambda piece: -piece[0])
    return pieces[:2 * MAX_TARGET_CANDIDATES]


def blob_hinges(
    split: VoxelSplit, src_mask: np.ndarray, points: np.ndarray, floor: float,
    shift: np.ndarray | None,
) -> list[RigidMotion]:
    """Turns of the cells `src_mask` holding `points`, a piece that is neither a plane nor a
    rod (hypotheses.swept_hinges): about its own principal axes, the target's and those of the
    largest target pieces (at least `floor` voxels). A sweep over so many axes, angles
    and starts also fits part of a drawer or of a noise blob somewhere, so only turns that
    land nearly all of the piece (BLOB_LANDED of its cells on target matter) and its centres
    closer than the best slide `shift` does (by BLOB_MARGIN in VoxelSplit.surface_fit) are
    kept: two touching parts, one blob, are left to the slide and the split by motion."""
    planes = _target_planes(split, floor)
    axes = [*fit_plane(points).axes, *fit_plane(split.target_tree.data).axes,
            *(a for p in planes for a in p.axes)]
    return _swept_turns(split, src_mask, points, planes, axes, SWEEP_STEP_DEG, shift)


def in_plane_turns(
    split: VoxelSplit, src_mask: np.ndarray, points: np.ndarray, floor: float,
    shift: np.ndarray | None,
) -> list[RigidMotion]:
    """Turns of the flat piece `src_mask` (holding `points`) about its own normal onto the
    target pieces parallel to it, kept as in blob_hinges: a blade of scissors, a swivelling
    lid. A slab turned within its plane stays parallel to itself, so no two planes intersect
    to give the axis, and a long piece cut into pieces by what the other state covers leaves
    no rod to align; a slide lands each piece nearly whole and fragments the part. Only onto
    flat pieces within IN_PLANE_COS of parallel (closer than PARALLEL_COS: the real box's
    flap, closed, lies 13 degrees off the other flap opened, and a small turn within its plane
    landed it on the box's rim better than its own hinge). The angle is swept finer than a
    blob's, one axis instead of a dozen: a blade's far end moves by its length times the
    angle's error."""
    normal = fit_plane(points).normal
    planes = [p for p in _target_planes(split, floor)
              if p.is_flat and abs(float(p.normal @ normal)) > IN_PLANE_COS]
    if not planes:
        return []
    return _swept_turns(split, src_mask, points, planes, [normal], IN_PLANE_STEP_DEG, shift)


def _target_planes(split: VoxelSplit, floor: float) -> list[Plane]:
    """The planes of the SWEEP_TARGETS largest target pieces of at least `floor` voxels."""
    return [split.piece_plane(index)
            for index, (size, _) in enumerate(split.pieces[:SWEEP_TARGETS]) if size >= floor]


def _swept_turns(
    split: VoxelSplit, src_mask: np.ndarray, points: np.ndarray, planes: list[Plane],
    axes: list[np.ndarray], step_deg: float, shift: np.ndarray | None,
) -> list[RigidMotion]:
    """The swept turns (hypotheses.swept_hinges, every `step_deg` about each of `axes`) of the
    cells `src_mask` holding `points` that land BLOB_LANDED of its cells and fit its centres
    closer than the best slide `shift` (None: there is none) by BLOB_MARGIN. Each starts with
    the centroid on the target `planes`' centroids, and points a quarter of their two largest
    extents away: the target's piece is often a different part of the blob than the canonical
    one, so centroids mislead."""
    starts = [p.centroid + f * e * a for p in planes
              for e, a in zip(p.extents[:2], p.axes[:2], strict=True) for f in (-0.25, 0.25)]
    starts += [p.centroid for p in planes]
    slide_fit = 0.0 if shift is None else split.surface_fit(points, np.eye(3), shift)
    cells = np.argwhere(src_mask)
    return [(r, t) for r, t in swept_hinges(points, axes, starts, split.target_tree,
                                            split.surface_fit, step_deg=step_deg)
            if split.surface_fit(points, r, t) > slide_fit + BLOB_MARGIN
            and split.score(cells, "hinge", r, t).landed >= BLOB_LANDED]


def near_tie_order(first: Hypothesis, second: Hypothesis) -> tuple[Hypothesis, Hypothesis]:
    """A hinge and a slide landing about as well, in the order stage 3 gets them: the hinge
    first, unless the slide covers clearly more of what changed (EXPLAIN_MARGIN). Stage 3 can
    turn a hinge into a slide (the ε rule), but a part that starts sliding never grows the
    rotation of a door: the images then have to reject a slide the model was already trained
    for (docs/method.md, "Stage 2"). A hinge explaining too little to claim a part is no
    contender, yet still goes first: such a piece is mostly a fragment of a door, which the
    door's part then takes in (parts._moves_along compares with the piece's first reading)."""
    hinge, slide = (second, first) if first.kind == "slide" else (first, second)
    slide_first = (hinge.explained >= DETECT_OVERLAP
                   and slide.explained >= hinge.explained + EXPLAIN_MARGIN)
    return (slide, hinge) if slide_first else (hinge, slide)


def _thick_turn(
    split: VoxelSplit, src_cells: np.ndarray, points: np.ndarray, plane: Plane,
    turns: list[tuple[float, Hypothesis]], slide_landed: float,
) -> tuple[float, Hypothesis]:
    """Of the turns `turns` of the cells `src_cells` holding `points`, as (surface fit,
    hypothesis) best fit first, for a piece that is a plane by its aspect but no slab (`plane`:
    not flat, not a rod): the REFINE_STARTS best refined by hypotheses.refine_turn, the one
    fitting best when it lands at least as many cells on target matter as the best unrefined
    turn and TIE_MARGIN more than the best slide (`slide_landed`), else that turn. Such a
    piece's normal is loosely held (a stapler's lid, 0.38 by 0.21 by 0.15: its plane
    intersections with the target's pieces missed the hinge by 13-25 degrees); a slab's is
    not, and there the surface fit, which also rewards landing on the static body, would
    trade one hinge's accuracy for another's. A drawer's box is thick too, and a turn
    searched for it can land it about as well as its slide, a rival the search made up (a
    real tall cabinet's drawer at the quick profile: a 108-degree turn landing 0.96 of it
    against the slide's 0.95, and stage 3 then kept the turn)."""
    refined = []
    for _, hinge in turns[:REFINE_STARTS]:
        rot, trans = refine_turn(points, hinge.rot, hinge.trans, float(plane.extents[0]),
                                 split.surface_fit)
        refined.append((split.surface_fit(points, rot, trans), rot, trans))
    fit, rot, trans = max(refined, key=lambda r: r[0])
    best = split.score(src_cells, "hinge", rot, trans)
    if not (best.trusted and best.landed >= turns[0][1].landed
            and best.landed >= slide_landed + TIE_MARGIN):
        return turns[0]
    return fit, best


def init_motion(
    split: VoxelSplit, src_mask: np.ndarray, points: np.ndarray, of_size: int | None = None,
    sweep: bool = True,
) -> list[Hypothesis]:
    """Initial motion of the canonical cells `src_mask` (holding the centres `points`), and the
    runner-up of the other kind.

    Candidates: the plane-intersection hinges with every planar target piece (VoxelSplit.pieces)
    above a size floor, a fifth of the cells or of `of_size` when given (for a chunk of a
    larger piece, whose target is larger than the chunk's), when the cells' centres are
    planar; each also about both edges of the slab (the two sides a hinge can be on); for a
    piece neither planar nor a rod, the swept turns of blob_hinges, and for a flat one its
    turns about its normal (in_plane_turns), both unless `sweep` is False; the one whose
    centres land closest (VoxelSplit.surface_fit), for a plane that is neither flat nor a rod
    refined by a local search (_thick_turn, also unless `sweep` is False), and the best
    whole-voxel slide. Among those explaining enough target change, the one landing most
    cells on target matter wins (a hinge on ties); [IDENTITY] when none qualifies. The best
    trusted hypothesis of the other kind follows when it lands within TIE_MARGIN of the winner
    (near_tie_order puts them in order), or whatever it lands when it is a fold: a slab turned
    by half a turn shows the other state its formerly hidden face, so half of it lands where
    that state saw nothing (the back of a closed door), while a slide of the symmetric slab
    lands both faces; the voxels cannot tell the two apart, the images can.
    """
    src_cells = np.argwhere(src_mask)
    canon_plane = fit_plane(points)
    # The best slide, once: the swept turns must beat it, and it is a candidate itself.
    shift = split.best_slide(src_mask)
    floor = max(MIN_PART_VOXELS, 0.2 * (of_size or len(src_cells)))
    hinges = _trusted_turns(split, src_mask, points, canon_plane, floor, shift, sweep)
    slide = None if shift is None else split.score(src_cells, "slide", np.eye(3), shift)
    candidates, spare_hinge = _best_turns(split, src_cells, points, canon_plane, hinges,
                                          slide, sweep)
    if slide is not None:
        candidates.append(slide)
    trusted = [h for h in candidates if h.trusted]
    if not trusted:
        return [IDENTITY]
    # Hypotheses that explain enough change to claim a part outrank those that merely may
    # initialise one: a door shifted sideways onto its static neighbour lands as well as the
    # door turned, but explains little of what changed.
    claiming = [h for h in trusted if h.explained >= DETECT_OVERLAP] or trusted
    # max() keeps the first of equal scores: hinges come first.
    best = max(claiming, key=lambda h: h.landed)
    others = [
        h for h in trusted
        if h.kind != best.kind and (h.fold or h.landed >= best.landed - TIE_MARGIN)
    ]
    chosen = [best]
    if others:
        runner = max(others, key=lambda h: h.landed)
        if runner.landed >= best.landed - TIE_MARGIN:
            best, runner = near_tie_order(best, runner)
        chosen = [best, runner]
    if spare_hinge is not None and any(h.kind == "hinge" for h in chosen):
        chosen.append(spare_hinge)
    return chosen


def _trusted_turns(split: VoxelSplit, src_mask: np.ndarray, points: np.ndarray,
                   canon_plane: Plane, floor: float, shift: np.ndarray | None,
                   sweep: bool) -> list[Hypothesis]:
    """The trusted turns among init_motion's candidates: plane intersections with every planar
    target piece of at least `floor` cells (and rods' turns onto rods), each also about both
    edges of the slab; a flat piece's turns about its normal and a blob's swept turns, both
    unless `sweep` is False."""
    src_cells = np.argwhere(src_mask)
    fold_offsets = split.grid.voxel_size * np.arange(-2.0, 2.5, 0.5)
    candidates: list[Hypothesis] = []
    if canon_plane.is_plane or canon_plane.is_rod:
        for index, (size, _) in enumerate(split.pieces):
            if size < floor:
                break
            plane = split.piece_plane(index)
            if canon_plane.is_plane and not plane.is_plane:
                # A door closed into a front with matter behind it: its turn onto the
                # piece's dominant plane.
                plane = split.dominant_piece_plane(index) or plane
            fold = abs(float(np.dot(canon_plane.normal, plane.normal))) > PARALLEL_COS
            turns = []
            if canon_plane.is_plane and plane.is_plane:
                turns += [(rt, fold) for rt in hinge_candidates(canon_plane, plane, fold_offsets)]
            if canon_plane.is_rod and plane.is_rod:
                turns += [(rt, False) for rt in rod_hinges(canon_plane, plane)]
            for (rot, trans), folded in turns:
                sides = [] if folded else edge_hinges(canon_plane, rot)
                for r, t in [(rot, trans), *sides]:
                    hyp = split.score(src_cells, "hinge", r, t)
                    hyp.fold = folded
                    candidates.append(hyp)
        if canon_plane.is_flat and sweep:
            turns = in_plane_turns(split, src_mask, points, floor, shift)
            candidates += [split.score(src_cells, "hinge", r, t) for r, t in turns]
    elif sweep:
        blobs = blob_hinges(split, src_mask, points, floor, shift)
        candidates += [split.score(src_cells, "hinge", r, t) for r, t in blobs]
    return [h for h in candidates if h.trusted]


def _best_turns(split: VoxelSplit, src_cells: np.ndarray, points: np.ndarray,
                canon_plane: Plane, hinges: list[Hypothesis], slide: Hypothesis | None,
                sweep: bool) -> tuple[list[Hypothesis], Hypothesis | None]:
    """([the hinge of `hinges` that goes first] or [], the other family's best or None). Per
    family (turns, half-turn folds), the hinge whose moved centres lie closest to the target's
    (which side of the slab the hinge is on, which of the angles); a thick plane's best turns
    refined (_thick_turn) unless `sweep` is False."""
    fits = [split.surface_fit(points, h.rot, h.trans) for h in hinges]
    best_of = {}
    for family in (False, True):
        members = [(f, h) for f, h in zip(fits, hinges, strict=True) if h.fold == family]
        if members:
            best_of[family] = max(members, key=lambda m: m[0])
    if False in best_of and sweep and canon_plane.is_plane \
            and not (canon_plane.is_flat or canon_plane.is_rod):
        turns = sorted(((f, h) for f, h in zip(fits, hinges, strict=True) if not h.fold),
                       key=lambda m: -m[0])
        best_of[False] = _thick_turn(split, src_cells, points, canon_plane, turns,
                                     0.0 if slide is None else slide.landed)
    if not best_of:
        return [], None
    # A turn goes first unless a fold lands its centres clearly closer: a symmetric piece (a
    # lever, a knob) also lands on its turned self when flipped by a half turn about the
    # bisector, and the fold's extra pivot offsets fit noise. The other family's hinge stays
    # a candidate for stage 3's images.
    order = sorted(best_of, key=lambda fam: best_of[fam][0] - (FOLD_MARGIN if fam else 0),
                   reverse=True)
    return [best_of[order[0]][1]], (best_of[order[1]][1] if len(order) > 1 else None)
