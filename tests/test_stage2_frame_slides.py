"""Stage 2's drawers side by side: flat trays whose fronts touch form one dynamic piece; each
is cut off and pushed along the body's frame by its own travel, read from where each line of
cells along the slide ends (docs/method.md, "Stage 2", "Drawers side by side")."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from gear.pipeline.stage2 import frame_slides, parts
from gear.pipeline.stage2.parts import SURFACE_TOLERANCE_VOXELS, coarse_init
from stage2_surfaces import OneView
from test_coarse import box_surface

VOXEL = 0.02
# The body: x across, y from the front (y = 0) inwards, z up.
BODY = (np.array([0.0, 0.0, 0.0]), np.array([1.0, 0.8, 0.6]))
# Two flat trays side by side (fronts touching at x = 0.5), 3 voxels tall, closed inside the
# body; in the open state pulled out along -y by different travels.
TRAYS = [(np.array([0.05, 0.0, 0.25]), np.array([0.5, 0.45, 0.31])),
         (np.array([0.5, 0.0, 0.25]), np.array([0.95, 0.45, 0.31]))]
PULLS = (0.10, 0.26)


def tray(lo, hi, n, rng):
    """An open-top tray: its front (y = lo), bottom, sides and back."""
    return box_surface(lo, hi, n, rng, skip=(5,))


def body(n, rng):
    """The body's faces, its front without the trays' openings."""
    points = box_surface(*BODY, n, rng)
    front = np.abs(points[:, 1]) < 1e-9
    opening = (points[:, 0] > 0.05) & (points[:, 0] < 0.95) & (points[:, 2] > 0.25) & (
        points[:, 2] < 0.31)
    return points[~(front & opening)]


def counter(seed=0, n_body=40000, n_tray=6000):
    """(closed, open, tray of each open centre or -1): closed, only the trays' fronts show (the
    rest is inside the body, which no view sees into); open, the trays pulled out by PULLS, of
    which what is out of the body shows."""
    rng = np.random.default_rng(seed)
    closed = [body(n_body, rng)]
    opened = [body(n_body, rng)]
    owner = [np.full(len(opened[0]), -1)]
    for index, ((lo, hi), pull) in enumerate(zip(TRAYS, PULLS, strict=True)):
        shut = tray(lo, hi, n_tray, rng)
        closed.append(shut[np.abs(shut[:, 1] - lo[1]) < 1e-9])  # its front alone
        out = tray(lo, hi, n_tray, rng) - np.array([0.0, pull, 0.0])
        out = out[out[:, 1] < 0]  # what is pulled out: the rest is inside the body
        opened.append(out)
        owner.append(np.full(len(out), index))
    return np.concatenate(closed), np.concatenate(opened), np.concatenate(owner)


def seen_as_closed(closed):
    """The closed state's images: a point near its centres is on the surface, a point inside the
    body is hidden, any other is seen through."""
    tree = cKDTree(closed)

    def look(points, tolerance):
        on = tree.query(points)[0] < tolerance
        inside = np.all((points > BODY[0] + tolerance) & (points < BODY[1] - tolerance), axis=1)
        return on, ~on & ~inside

    return OneView(look)


def run(closed, opened):
    """coarse_init with K from the data, the closed state's images."""
    surfaces = {"start": seen_as_closed(closed), "end": seen_as_closed(opened)}
    return coarse_init(closed, opened, None, VOXEL, surfaces=surfaces)


def test_trays_side_by_side_are_one_piece_that_no_single_motion_claims(monkeypatch):
    closed, opened, _ = counter()
    monkeypatch.setattr(parts, "frame_slides", lambda *args: [])
    result = run(closed, opened)
    assert result.canonical == "end"
    assert result.num_parts == 1, result.notes


def test_each_tray_is_pushed_back_by_its_own_travel():
    closed, opened, owner = counter()
    result = run(closed, opened)
    assert result.num_parts == 3, result.notes
    labels = np.asarray(result.logits).argmax(1)
    # Centres within a few voxels of the body's front share cells with it (static, dilated):
    # stage 2 leaves them to stage 3.
    clear_of_body = opened[:, 1] < -3 * VOXEL
    for index, pull in enumerate(PULLS):
        held = labels[(owner == index) & clear_of_body]
        part = int(np.bincount(held, minlength=3).argmax())
        assert part != 0
        assert (held == part).mean() > 0.9
        assert (labels[owner == 1 - index] == part).mean() < 0.05  # the other tray elsewhere
        rot, trans = result.candidates[part - 1][0]
        np.testing.assert_allclose(rot, np.eye(3))
        # Pushed in along +y, to within 1.5 voxels of the pull: a surface counts within the
        # images' tolerance, so the shortest clear push may stop a voxel short.
        assert abs(trans[1] - pull) <= 1.5 * VOXEL, (index, trans)
        # Along the body's frame, which its faces give to a small fraction of a degree.
        assert np.degrees(np.arccos(trans[1] / np.linalg.norm(trans))) < 0.2
        # Held no deeper than the push plus the images' tolerance, past the true pull.
        deepest = result.held_slides[part - 1]
        np.testing.assert_allclose(np.cross(deepest, trans), 0.0, atol=1e-12)
        assert pull <= deepest @ trans / np.linalg.norm(trans)
        assert np.linalg.norm(deepest) == pytest.approx(
            np.linalg.norm(trans) + SURFACE_TOLERANCE_VOXELS * VOXEL)


def test_a_piece_meeting_no_target_matter_along_the_frame_gives_no_drawer():
    """A floater off a corner of the body meets nothing pushed along any direction of the
    frame: no drawer, while the trays beside it are still found."""
    closed, opened, _ = counter()
    rng = np.random.default_rng(5)
    floater = box_surface([1.1, -0.2, 0.7], [1.16, -0.14, 0.76], 2000, rng)
    opened = np.concatenate([opened, floater])
    split = parts.split_static_dynamic(opened, closed, VOXEL)
    split.on_surface, split.surface_tolerance = seen_as_closed(closed), 2 * VOXEL
    cell = tuple(split.grid.voxel_of(floater[:1])[0])
    mask = split.labels[0] == split.labels[0][cell]
    inside = np.all(split.grid.voxel_of(opened)[:, None] == np.argwhere(mask)[None], axis=2)
    points_in = lambda m: opened[inside.any(axis=1)]  # noqa: E731
    assert frame_slides.frame_slides(split, mask, np.eye(3), points_in) == []
    assert run(closed, opened).num_parts == 3


@pytest.mark.parametrize("values, weights, expected", [
    ([3, 4, 9], [1, 1, 5], 9), ([5, 3], [4, 4], 3), ([7], [2], 7), ([2, 8, 4], [3, 1, 3], 4)])
def test_weighted_median(values, weights, expected):
    assert frame_slides._weighted_median(values, weights) == expected
