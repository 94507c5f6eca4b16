"""Region-mask flaws and depth effects, each on its own."""

import numpy as np

from gear.synth.effects import noisy_depth, parse_effects
from gear.synth.regions import (
    clean_regions,
    jitter_boundaries,
    over_segment,
    shuffle_ids,
    under_segment,
)


def _two_part_image():
    """64x64: part 1 on the left half, part 2 on the right half, background border."""
    parts = np.full((64, 64), 255, np.uint8)
    parts[8:56, 8:32] = 1
    parts[8:56, 32:56] = 2
    facets = np.where(parts == 255, -1, parts.astype(np.int64) * 6)
    return parts, facets


def test_clean_regions_follow_parts_and_drop_specks():
    parts, facets = _two_part_image()
    facets[0, 0] = 99  # a one-pixel facet: below SAM's minimum area
    regions = clean_regions(facets, np.random.default_rng(0))
    assert sorted(np.unique(regions).tolist()) == [0, 1, 2]
    assert regions[0, 0] == 0
    for rid in (1, 2):
        assert len(np.unique(parts[regions == rid])) == 1
    # Ids are shuffled per image: some seed swaps them.
    orders = {int(clean_regions(facets, np.random.default_rng(s))[10, 10]) for s in range(8)}
    assert orders == {1, 2}


def test_over_segment_splits_inside_regions():
    _, facets = _two_part_image()
    regions = clean_regions(facets, np.random.default_rng(0))
    split = over_segment(regions, np.random.default_rng(1), chance=1.0)
    assert len(np.unique(split[split > 0])) > 2
    np.testing.assert_array_equal(split > 0, regions > 0)
    for rid in np.unique(split[split > 0]):  # every piece lies inside one original region
        assert len(np.unique(regions[split == rid])) == 1


def test_under_segment_merges_two_parts():
    parts, facets = _two_part_image()
    regions = clean_regions(facets, np.random.default_rng(0))
    merged = under_segment(regions, parts, np.random.default_rng(0), merges=1)
    assert len(np.unique(merged[merged > 0])) == 1
    assert set(np.unique(parts[merged > 0]).tolist()) == {1, 2}


def test_jitter_moves_boundaries_only():
    _, facets = _two_part_image()
    regions = clean_regions(facets, np.random.default_rng(0))
    jittered = jitter_boundaries(regions, np.random.default_rng(3))
    changed = jittered != regions
    assert changed.any()
    # Far from every boundary (interior of each half) nothing changes.
    assert not changed[20:44, 14:26].any() and not changed[20:44, 38:50].any()
    assert changed.mean() < 0.1


def test_shuffle_keeps_partition():
    regions = np.array([[0, 3, 3], [7, 7, 0]])
    out = shuffle_ids(regions, np.random.default_rng(0))
    assert sorted(np.unique(out).tolist()) == [0, 1, 2]
    assert out[0, 1] == out[0, 2] and out[1, 0] == out[1, 1] and out[0, 0] == 0


def test_depth_effects_separately():
    rng = np.random.default_rng(0)
    depth = np.zeros((64, 64), np.float32)
    depth[10:50, 10:50] = 2.0
    assert noisy_depth(depth, frozenset(), rng) is depth  # off: untouched, no copy
    noisy = noisy_depth(depth, parse_effects("depth-noise"), rng)
    np.testing.assert_array_equal(noisy > 0, depth > 0)  # noise alone drops nothing
    assert 0.0035 < np.std(noisy[depth > 0] - 2.0) / 2.0 < 0.0045  # sigma 0.4%, 1600 samples
    dropped = noisy_depth(depth, parse_effects(["depth-dropout"]), rng)
    assert not dropped[depth == 0].any()
    assert set(np.unique(dropped).tolist()) <= {0.0, 2.0}
    assert 0.02 < (dropped[depth > 0] == 0).mean() < 0.9
