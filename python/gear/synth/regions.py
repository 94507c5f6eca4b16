"""Class-agnostic region masks that imitate SAM output, and their deliberate flaws.

Clean masks: connected regions of one primitive (a box, a handle, one material of a mesh) and
one dominant surface orientation: SAM tends to give a handle its own mask and to split a box
into its visible faces, but never crosses a part boundary it can see. Tiny regions are dropped
(SAM's minimum area) and ids are shuffled per image so they carry no meaning across images.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from skimage import measure

MIN_AREA_FRACTION = 2e-4  # regions smaller than this share of the image become 0 (no region)


def clean_regions(facets: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Region ids (int32, 0 = none) from a facet-key image (-1 = background)."""
    min_area = max(4, int(MIN_AREA_FRACTION * facets.size))
    # One pass: 4-connected components of equal facet keys (background is key -1 -> 0).
    labels = measure.label(facets + 1, background=0, connectivity=1)
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    keep = sizes >= min_area
    remap = np.zeros(len(sizes), dtype=np.int32)
    remap[keep] = np.arange(1, int(keep.sum()) + 1)
    return shuffle_ids(remap[labels], rng)


def shuffle_ids(regions: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    ids = np.unique(regions[regions > 0])
    lut = np.zeros(int(regions.max(initial=0)) + 1, dtype=np.int32)
    lut[ids] = rng.permutation(len(ids)) + 1
    return lut[regions]


def over_segment(regions: np.ndarray, rng: np.random.Generator, chance: float = 0.5) -> np.ndarray:
    """Split large regions into 2-3 pieces by random straight cuts."""
    out = regions.copy()
    next_id = int(regions.max(initial=0)) + 1
    min_area = max(16, int(20 * MIN_AREA_FRACTION * regions.size))
    for rid in np.unique(regions[regions > 0]):
        ys, xs = np.nonzero(regions == rid)
        if len(ys) < min_area or rng.random() > chance:
            continue
        for _ in range(rng.integers(1, 3)):  # one or two cuts
            k = rng.integers(len(ys))
            angle = rng.uniform(0, np.pi)
            side = (xs - xs[k]) * np.cos(angle) + (ys - ys[k]) * np.sin(angle) > 0
            side &= out[ys, xs] == out[ys[k], xs[k]]  # cut one current piece only
            if 0 < side.sum() < len(ys):
                out[ys[side], xs[side]] = next_id
                next_id += 1
    return out


def under_segment(
    regions: np.ndarray, parts: np.ndarray, rng: np.random.Generator, merges: int = 2
) -> np.ndarray:
    """Merge up to `merges` pairs of touching regions that belong to different parts."""
    out = regions.copy()
    for _ in range(merges):
        pairs = _touching_pairs(out, parts)
        if not pairs:
            break
        a, b = pairs[rng.integers(len(pairs))]
        out[out == b] = a
    return out


def _touching_pairs(regions: np.ndarray, parts: np.ndarray) -> list[tuple[int, int]]:
    pairs = set()
    for da, db in ((regions[:, :-1], regions[:, 1:]), (regions[:-1], regions[1:])):
        sel = (da > 0) & (db > 0) & (da != db)
        for a, b in zip(da[sel].tolist(), db[sel].tolist(), strict=True):
            pairs.add((min(a, b), max(a, b)))
    majority = _majority_part(regions, parts)
    return sorted(p for p in pairs if majority[p[0]] != majority[p[1]])


def _majority_part(regions: np.ndarray, parts: np.ndarray) -> dict[int, int]:
    out = {}
    for rid in np.unique(regions[regions > 0]):
        values, counts = np.unique(parts[regions == rid], return_counts=True)
        out[int(rid)] = int(values[np.argmax(counts)])
    return out


def jitter_boundaries(
    regions: np.ndarray, rng: np.random.Generator, amplitude: float = 0.012
) -> np.ndarray:
    """Wobble region boundaries: resample labels through a smooth random displacement field of
    about `amplitude` x image size pixels."""
    h, w = regions.shape
    amp = max(1.0, amplitude * max(h, w))
    sigma = max(2.0, 0.03 * max(h, w))
    field = [ndimage.gaussian_filter(rng.normal(size=(h, w)), sigma) for _ in range(2)]
    field = [f * amp / (np.abs(f).max() + 1e-12) for f in field]
    yy, xx = np.mgrid[0:h, 0:w]
    y = np.clip(np.round(yy + field[0]).astype(np.int64), 0, h - 1)
    x = np.clip(np.round(xx + field[1]).astype(np.int64), 0, w - 1)
    return regions[y, x]
