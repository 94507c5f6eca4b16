"""Stage 2 on synthetic surface samples: how many rigid motions the dynamic region needs (K),
which pieces move together, which side of a piece its hinge is on, and small levers."""

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from gear.articulation import PartMotion
from gear.pipeline.stage2 import voxels
from gear.pipeline.stage2.hypotheses import edge_hinges, fit_plane, rod_hinges
from gear.pipeline.stage2.parts import _moves_along, coarse_init
from gear.pipeline.stage2.voxels import Scale, split_static_dynamic
from stage2_surfaces import OneView
from test_coarse import FRONT, box_surface, hinge_motion, line_distance


def angle_between(a, b):
    return float(np.degrees(np.arccos(min(1.0, abs(float(np.dot(a, b)))))))


def door_over_drawer(n=20000, seed=0):
    """A cabinet whose door (upper front, hinged on its left edge, axis -z) opens 60 degrees
    while the drawer right under it is pulled 0.35 out: the open door's lower edge rests on
    the pulled drawer's rim, so the two moved pieces touch. Returns the states, the door's
    hinge (axis, pivot) and the drawer's pull."""
    rng = np.random.default_rng(seed)
    hinge_axis, hinge_pivot = np.array([0.0, 0.0, -1.0]), np.array([0.0, -0.025, 0.0])
    pull = np.array([0.0, -0.35, 0.0])

    def state(open_):
        body = box_surface([0, 0, 0], [1.2, 1, 1.4], int(0.5 * n), rng, skip=(FRONT,))
        door = box_surface([0, -0.04, 0.6], [1.2, -0.01, 1.4], int(0.25 * n), rng)
        drawer = box_surface([0.02, -0.04, 0.02], [1.18, 0.9, 0.6], int(0.25 * n), rng, skip=(5,))
        if open_:
            rot, trans = hinge_motion(hinge_axis, hinge_pivot, 60.0)
            door, drawer = door @ rot.T + trans, drawer + pull
        return np.concatenate([body, door, drawer])

    return state(False), state(True), hinge_axis, hinge_pivot, pull


def surfaces_of(points):
    """A SurfaceTest of a state seen completely: a point is on its surface when a centre lies
    within the tolerance, else seen through."""
    tree = cKDTree(points)

    def look(query, tolerance):
        on = tree.query(query)[0] < tolerance
        return on, ~on

    return OneView(look)


def coarse_init_seen(start, end, **kwargs):
    """coarse_init with both states' images (complete views of their centres)."""
    return coarse_init(start, end, surfaces={"start": surfaces_of(start),
                                             "end": surfaces_of(end)}, **kwargs)


def last_quarters(result, n):
    """The part labels of the canonical centres [2n, 3n) and [3n, 4n) (two moving pieces of
    the scenes here), and the movable part holding most of each."""
    owner = result.logits.argmax(1)
    groups = owner[2 * n:3 * n], owner[3 * n:]
    majority = tuple(int(np.bincount(g, minlength=result.num_parts)[1:].argmax()) + 1
                     for g in groups)
    return groups, majority


def test_touching_parts_with_different_motions_give_two_parts():
    start, end, axis, pivot, pull = door_over_drawer()
    # The premise: on the grid stage 2 uses, door and drawer are one dynamic component.
    size = Scale.of(np.concatenate([start, end])).voxel_size(single_part=False)
    split = split_static_dynamic(end, start, size)
    labels = split.grid.point_labels(end, split.labels[0])
    n = len(end) // 4
    door, drawer = labels[2 * n: 3 * n], labels[3 * n:]
    assert (door == 1).mean() > 0.3 and (drawer == 1).mean() > 0.3
    result = coarse_init_seen(start, end)
    assert result.num_parts == 3, result.notes
    joints = PartMotion.from_rt(result.motions, dtype=torch.float64).joints(pivot)
    by_type = {j["type"]: j for j in joints}
    assert set(by_type) == {"revolute", "prismatic"}
    hinge, slide = by_type["revolute"], by_type["prismatic"]
    assert angle_between(hinge["axis"], axis) < 2.0
    assert hinge["angle_deg"] == pytest.approx(60.0, abs=3.0)
    assert line_distance(hinge["origin"], pivot, axis) < 0.05
    travel = pull if result.canonical == "end" else -pull  # start -> end is never asked here
    assert angle_between(slide["axis"], travel / np.linalg.norm(travel)) < 3.0
    assert slide["distance"] == pytest.approx(0.35, abs=2 * result.voxel_size)


def test_the_door_and_the_drawer_each_get_their_own_gaussians():
    start, end, *_ = door_over_drawer(seed=1)
    result = coarse_init_seen(start, end)
    canon = start if result.canonical == "start" else end
    assert result.canonical == "end" and len(canon) == len(end)
    (door, drawer), (door_part, drawer_part) = last_quarters(result, len(end) // 4)
    assert door_part != drawer_part
    assert (door == door_part).mean() > 0.5 and (drawer == drawer_part).mean() > 0.4


def doors_stacked_on_one_hinge(upper_deg, lower_deg, n=24000, seed=0):
    """A cabinet with two doors one above the other on its left edge (axis +z), the upper
    turned by `upper_deg`, the lower by `lower_deg`: along their shared hinge line the open
    doors touch, so their dynamic voxels form one piece. Returns the states; the lower door's
    centres are the third quarter of each state, the upper door's the last."""
    rng = np.random.default_rng(seed)
    axis, pivot = np.array([0.0, 0.0, 1.0]), np.array([0.0, -0.025, 0.0])

    def state(open_):
        body = box_surface([0, 0, 0], [1.0, 0.8, 2.0], int(0.5 * n), rng, skip=(FRONT,))
        lower = box_surface([0, -0.04, 0.0], [1.0, -0.01, 0.99], int(0.25 * n), rng)
        upper = box_surface([0, -0.04, 1.01], [1.0, -0.01, 2.0], int(0.25 * n), rng)
        if open_:
            # Negative turns about +z swing the front doors out, away from the body.
            (rot_l, trans_l), (rot_u, trans_u) = (hinge_motion(axis, pivot, -deg)
                                                  for deg in (lower_deg, upper_deg))
            lower, upper = lower @ rot_l.T + trans_l, upper @ rot_u.T + trans_u
        return np.concatenate([body, lower, upper])

    return state(False), state(True)


@pytest.mark.parametrize(("upper_deg", "lower_deg", "seed"), [(57.0, 27.0, 1), (50.0, 20.0, 2)])
def test_doors_stacked_on_one_hinge_line_are_two_whole_parts(upper_deg, lower_deg, seed):
    """No single turn lands both doors: their far sides are cut off with turns of their own,
    and the strip along the shared hinge, which any turn about the line lands about as well,
    goes to the door beside it instead of staying a part mixing both (it had: K 4 with a
    third part holding a third of each door, or a door's strip joined to the other door)."""
    start, end = doors_stacked_on_one_hinge(upper_deg, lower_deg, seed=seed)
    size = Scale.of(np.concatenate([start, end])).voxel_size(single_part=False)
    split = split_static_dynamic(end, start, size)
    n = len(end) // 4
    labels = split.grid.point_labels(end, split.labels[0])
    assert (labels[2 * n:3 * n] == 1).mean() > 0.5 and (labels[3 * n:] == 1).mean() > 0.5
    result = coarse_init_seen(start, end)
    assert result.num_parts == 3, result.notes
    (lower, upper), (lower_part, upper_part) = last_quarters(result, n)
    assert lower_part != upper_part
    # The rest of each door is static-leaning matter along the hinge (the slab's 1.5 cm
    # next to the line moves under a voxel): about a tenth of its centres.
    assert (lower == lower_part).mean() > 0.85 and (upper == upper_part).mean() > 0.85
    assert (lower == upper_part).mean() < 0.02 and (upper == lower_part).mean() < 0.02


def slab_door_beside_panel(angle_deg, n=16000, seed=3):
    """A thick door (0.08) hinged on its right back edge beside a static panel of the same
    size on that side: the door mirrored about its hinge lands on the panel, the door on the
    wrong side of its own slab lands in the air."""
    rng = np.random.default_rng(seed)
    axis, pivot = np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])

    def state(open_):
        body = box_surface([0, 0.0, 0], [2.0, 1.0, 1.0], int(0.5 * n), rng, skip=(FRONT,))
        panel = box_surface([1.0, -0.08, 0], [2.0, 0.0, 1.0], int(0.2 * n), rng)
        door = box_surface([0.0, -0.08, 0], [1.0, 0.0, 1.0], int(0.3 * n), rng)
        if open_:
            rot, trans = hinge_motion(axis, pivot, angle_deg)
            door = door @ rot.T + trans
        return np.concatenate([body, panel, door])

    return state(False), state(True), axis, pivot


@pytest.mark.parametrize("angle_deg", [150.0, 25.0])
def test_door_pivot_side_is_chosen_by_where_it_lands(angle_deg):
    """150 degrees: the plane normals give 30 or 150 about either side's line; 25 degrees:
    the thick door's mid-planes cross far from its hinge. Both must end on the right edge."""
    start, end, axis, pivot = slab_door_beside_panel(angle_deg)
    result = coarse_init(start, end)
    assert result.num_parts == 2, result.notes
    joint = PartMotion.from_rt(result.motions, dtype=torch.float64).joints(pivot)[0]
    assert joint["type"] == "revolute"
    assert angle_between(joint["axis"], axis) < 2.0
    assert joint["angle_deg"] == pytest.approx(angle_deg, abs=3.0)
    # The other side of the door is 1.0 away; its thickness (0.08) and the plane fits of its
    # voxel-cut pieces blur where along that side.
    assert line_distance(joint["origin"], pivot, axis) < 0.15


def test_edge_hinges_turn_about_the_two_ends_of_the_slab():
    rng = np.random.default_rng(4)
    slab = box_surface([0, 0, 0], [1.0, 0.05, 2.0], 5000, rng)
    rot, _ = hinge_motion([0, 0, 1], [0, 0, 0], 40.0)
    candidates = edge_hinges(fit_plane(slab), rot)
    assert len(candidates) == 2
    fixed = []
    for r, t in candidates:
        np.testing.assert_allclose(r, rot)
        # Points of the turning line stay put: one candidate holds x = 0, the other x = 1.
        ends = np.array([[0.0, 0.025, 1.0], [1.0, 0.025, 1.0]])
        fixed.append(np.linalg.norm(ends @ r.T + t - ends, axis=1).argmin())
    assert sorted(fixed) == [0, 1]


def test_rod_hinges_contain_the_turn_of_a_lever():
    rng = np.random.default_rng(5)
    lever = box_surface([0, -0.02, -0.02], [0.4, 0.02, 0.02], 2000, rng)
    rot, trans = hinge_motion([0, 0, 1], [0.0, 0.0, 0.0], 55.0)
    candidates = rod_hinges(fit_plane(lever), fit_plane(lever @ rot.T + trans))
    probe = np.array([[0.4, 0.0, 0.0], [0.2, 0.02, 0.0]])
    errors = [np.abs(probe @ r.T + t - (probe @ rot.T + trans)).max() for r, t in candidates]
    assert len(candidates) == 2 and min(errors) < 0.02
    assert rod_hinges(fit_plane(lever), fit_plane(lever + np.array([0, 0.3, 0]))) == []


HINGE_OFFSET = np.array([0.025, 0.0, 0.0])  # a lever's axis from its base corner


def faucet(n=30000, seed=6):
    """A faucet-like body (a tall box and a spout) with two small levers on top, each 2 % of
    the points, turning about vertical axes through their own base by 50 and -40 degrees."""
    rng = np.random.default_rng(seed)
    bases = [np.array([0.3, 0.5, 1.0]), np.array([0.3, -0.5, 1.0])]
    angles = [50.0, -40.0]

    def lever(base):
        return box_surface(base + np.array([0.0, -0.025, 0.0]), base + np.array([0.3, 0.025, 0.05]),
                           int(0.02 * n), rng)

    def state(open_):
        body = box_surface([0, -0.7, 0], [0.6, 0.7, 1.0], int(0.8 * n), rng)
        spout = box_surface([0.6, -0.1, 0.7], [1.2, 0.1, 0.85], int(0.16 * n), rng)
        levers = []
        for base, angle in zip(bases, angles, strict=True):
            piece = lever(base)
            if open_:
                rot, trans = hinge_motion([0, 0, 1], base + HINGE_OFFSET, angle)
                piece = piece @ rot.T + trans
            levers.append(piece)
        return np.concatenate([body, spout, *levers])

    return state(False), state(True), bases, angles


def test_small_levers_are_found_and_turn():
    start, end, bases, _ = faucet()
    result = coarse_init(start, end)
    assert result.num_parts == 3, result.notes
    joints = PartMotion.from_rt(result.motions, dtype=torch.float64).joints(np.zeros(3))
    assert [j["type"] for j in joints] == ["revolute", "revolute"]
    got = sorted(round(j["angle_deg"]) for j in joints)
    assert abs(got[0] - 40) <= 7 and abs(got[1] - 50) <= 7  # the far side of a slide: 0
    for j in joints:
        assert angle_between(j["axis"], [0, 0, 1]) < 5.0
        nearest = min(line_distance(j["origin"], b + HINGE_OFFSET, np.array([0, 0, 1.0]))
                      for b in bases)
        assert nearest < 0.1  # the lever's other end is 0.3 away


TEMPLE_VOXEL = 0.02


def glasses_with_a_fragmented_temple(n=12000, seed=7, angle=25.0):
    """A glasses-like static frame and one long thin temple (1 x 0.02 x 0.01) hinged at its
    front end, turned by `angle` about the vertical axis. The turned state samples the temple
    only in short fragments (0.05 long, one eighth of the temple's cells each) with gaps of
    2.5 voxels between them, as a thin part few centres sample shows up; the other state
    samples it whole. Returns the states and the hinge (axis, pivot)."""
    rng = np.random.default_rng(seed)
    axis, pivot = np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 0.0])

    def state(turned):
        frame = box_surface([-1.2, -0.05, -0.2], [0.0, 0.0, 0.2], int(0.9 * n), rng)
        temple = box_surface([0.01, -0.02, -0.005], [1.0, 0.0, 0.005], int(0.1 * n), rng)
        if turned:
            period = 0.05 + 2.5 * TEMPLE_VOXEL
            temple = temple[(temple[:, 0] - 0.01) % period < 0.05]
            rot, trans = hinge_motion(axis, pivot, angle)
            temple = temple @ rot.T + trans
        return np.concatenate([frame, temple])

    return state(False), state(True), axis, pivot


def test_a_thin_part_fragmented_in_one_state_still_turns():
    start, end, axis, pivot = glasses_with_a_fragmented_temple()
    split = split_static_dynamic(start, end, TEMPLE_VOXEL)
    pieces = split.sizes[0 if len(split.sizes[0]) > len(split.sizes[1]) else 1]
    assert len(pieces) >= 8 and pieces[0] < 0.2 * pieces.sum()  # fragmented, as described
    result = coarse_init(start, end, voxel_size=TEMPLE_VOXEL)
    assert result.num_parts == 2, result.notes
    [joint] = PartMotion.from_rt(result.motions, dtype=torch.float64).joints(np.zeros(3))
    assert joint["type"] == "revolute", result.notes
    assert joint["angle_deg"] == pytest.approx(25.0, abs=2.0)
    assert angle_between(joint["axis"], axis) < 3.0
    assert line_distance(joint["origin"], pivot, axis) < 0.05  # the temple is 1 long


def test_a_piece_joins_the_part_whose_motion_agrees_with_its_own():
    """A piece's own best motion may land its few cells a little better than its part's
    (noise); when the two move its centres to within AGREE_VOXELS it still joins the part, and
    a motion that puts it elsewhere does not take it."""
    start, end, bases, angles = faucet()
    voxel = 0.02
    split = split_static_dynamic(start, end, voxel)
    lever = start[-int(0.02 * 30000) * 2 : -int(0.02 * 30000)]  # the first lever's centres
    cells = np.unique(split.grid.voxel_of(lever), axis=0)
    rot, trans = hinge_motion([0, 0, 1], bases[0] + HINGE_OFFSET, angles[0])
    own = split.score(cells, "hinge", rot, trans)
    assert own.landed > 0.9
    own.landed = 1.0  # a fit of the piece alone that lands every cell

    def shifted(by_voxels):
        # The same turn, then lifted by `by_voxels`: the lever lands that far off.
        lift = np.array([0.0, 0.0, by_voxels * voxel])
        return split.score(cells, "hinge", rot, trans + lift)

    near, far = shifted(1.9), shifted(6.0)
    assert near.trusted and near.landed < own.landed - 0.05  # not by landing alone
    assert _moves_along(split, cells, lever, near, [own])
    assert not _moves_along(split, cells, lever, far, [own])
    # A piece cut off as a region of its own motion joins only a motion that lands its
    # centres about as closely as its own: 1.9 voxels off is not that.
    assert not _moves_along(split, cells, lever, near, [own], region=True)
    assert _moves_along(split, cells, lever, own, [own], region=True)


def test_a_piece_joins_a_part_that_explains_more_of_its_change():
    """A piece's own fit may land a few more of its cells on matter that did not change; a
    part's motion landing it within TIE_MARGIN and explaining at least as much of the change
    takes it, one explaining less does not."""
    start, end, bases, angles = faucet()
    voxel = 0.02
    split = split_static_dynamic(start, end, voxel)
    lever = start[-int(0.02 * 30000) * 2 : -int(0.02 * 30000)]  # the first lever's centres
    cells = np.unique(split.grid.voxel_of(lever), axis=0)
    # The part's turn about an axis 3 voxels beside the lever's: 2.5 voxels apart on it.
    rot, trans = hinge_motion([0, 0, 1], bases[0] + HINGE_OFFSET + [0, 3 * voxel, 0], angles[0])
    shared = split.score(cells, "hinge", rot, trans)
    own = split.score(cells, "hinge", *hinge_motion([0, 0, 1], bases[0] + HINGE_OFFSET, angles[0]))
    own.landed = shared.landed + 0.08  # within TIE_MARGIN, not within 0.05
    own.explained = shared.explained - 0.1
    assert _moves_along(split, cells, lever, shared, [own])
    own.explained = shared.explained + 0.1
    assert not _moves_along(split, cells, lever, shared, [own])


def inner_face_scene(n=24000, seed=0):
    """A cabinet whose door (a slab 0.06 thick, hinged on its left edge, axis z) is closed in
    the target state and open 50 degrees in the canonical one. The door's inner face is seen
    only while the door is open: the target state holds the door's front and edges, not it.
    Returns the canonical and target centres, the inner face's canonical centres, the closing
    turn and the target images' test (on the surface within the tolerance; seen through in
    front of the closed cabinet; out of sight, hidden by the door, inside it)."""
    rng = np.random.default_rng(seed)
    lo, hi = np.array([0.0, -0.08, 0.0]), np.array([0.6, -0.02, 0.7])
    body = box_surface([0, 0, 0], [0.6, 0.5, 0.7], n // 2, rng, skip=(FRONT,))
    slab = box_surface(lo, hi, n // 2, rng)
    inner = np.isclose(slab[:, 1], hi[1])
    opening = hinge_motion([0, 0, 1], [0.0, -0.05, 0.0], -50.0)
    canon = np.concatenate([body, slab @ opening[0].T + opening[1]])
    target = np.concatenate([body, slab[~inner]])
    closing = hinge_motion([0, 0, 1], [0.0, -0.05, 0.0], 50.0)
    tree = cKDTree(target)

    def look(points, tolerance):
        on = tree.query(points)[0] < tolerance
        inside = np.all((points >= [0.0, lo[1], 0.0]) & (points <= [0.6, 0.5, 0.7]), axis=1)
        return on, ~on & ~inside

    return canon, target, canon[len(body):][inner], closing, OneView(look)


def test_a_face_the_target_hides_joins_the_door_whose_turn_hides_it():
    """The open door's inner face is a piece of its own (nothing of it in the target state):
    the door's closing turn puts it behind the closed door's front, where the voxel landing
    finds no matter but the target images see nothing contradict it (its rim on the door's
    edges, none of it seen through). It joins the door when its own motion is seen no better;
    not when its own motion shows it on the target's surfaces far more, and not under a turn
    that leaves it in front of the closed cabinet (seen through)."""
    canon, target, face, closing, surfaces = inner_face_scene()
    split = split_static_dynamic(canon, target, 0.02)
    split.on_surface, split.surface_tolerance = surfaces, 0.04
    cells = np.unique(split.grid.voxel_of(face), axis=0)
    door = split.score(cells, "hinge", *closing)
    assert door.trusted
    # Its own fit: pushed into the cabinet, landing more cells (on its walls) than the turn.
    pushed = split.score(cells, "slide", closing[0], closing[1] + [0.0, 0.3, 0.0])
    pushed.landed = door.landed + 0.2
    assert _moves_along(split, cells, face, door, [pushed])
    # Its own motion lays it on the closed door's front: seen there, it stays apart.
    on_front = split.score(cells, "slide", closing[0], closing[1] - [0.0, 0.06, 0.0])
    on_front.landed = door.landed + 0.2
    assert not _moves_along(split, cells, face, door, [on_front])
    # A turn 30 degrees short leaves it in front of the cabinet: seen through.
    short = split.score(cells, "hinge", *hinge_motion([0, 0, 1], [0.0, -0.05, 0.0], 20.0))
    assert not _moves_along(split, cells, face, short, [pushed])


def test_a_blob_that_is_neither_plane_nor_rod_turns_on_a_hinge():
    # A stapler-like head: a chunky box on a base (extents within a factor 1.5 of each other,
    # no plane, no long direction), raised 80 degrees about its back edge. Without planes or
    # lines to intersect, only a slide was tried, and the head came out sliding.
    rng = np.random.default_rng(3)
    axis, pivot = np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 0.3])
    rot, trans = hinge_motion(axis, pivot, 80.0)

    def state(open_):
        base = box_surface([0, 0, 0], [0.5, 1.5, 0.3], 12000, rng)
        head = box_surface([0.0, 0.0, 0.3], [0.5, 0.6, 0.7], 6000, rng)
        return np.concatenate([base, head @ rot.T + trans if open_ else head])

    init = coarse_init_seen(state(False), state(True))
    assert init.num_parts == 2
    got_rot, got_trans = init.motions[0]
    want_rot, want_trans = (rot, trans) if init.canonical == "start" else (rot.T, -rot.T @ trans)
    turn = np.degrees(np.arccos(np.clip((np.trace(got_rot.T @ want_rot) - 1) / 2, -1, 1)))
    assert turn < 5.0
    corner = np.array([0.5, 0.6, 0.7])
    assert np.linalg.norm(got_rot @ corner + got_trans - (want_rot @ corner + want_trans)) < 0.08


PADDLE_PIVOT = np.array([0.05, 0.0, 0.0])


def paddle_on_a_plate(deg: float, n: int = 40000, seed: int = 0):
    """A flat paddle (an L of two slabs, 8 mm thick) beside a flat plate, turned by `deg`
    within their common plane about a vertical axis through PADDLE_PIVOT: a blade of scissors
    opening. Sampled densely, as a long run's centres are (their spacing far below a voxel)."""
    rng = np.random.default_rng(seed)

    def state(turned: bool) -> np.ndarray:
        plate = box_surface([-0.3, -0.3, 0.0], [0.0, 0.3, 0.008], n // 2, rng)
        paddle = np.concatenate([box_surface([0.0, -0.12, 0.0], [0.3, 0.12, 0.008], n // 4, rng),
                                 box_surface([0.3, -0.12, 0.0], [0.4, 0.0, 0.008], n // 8, rng)])
        if turned:
            rot, trans = hinge_motion([0, 0, 1], PADDLE_PIVOT, deg)
            paddle = paddle @ rot.T + trans
        return np.concatenate([plate, paddle])

    return state(False), state(True)


@pytest.mark.parametrize("seed", [0, 1])
def test_a_flat_part_turned_within_its_plane_is_a_hinge_about_its_normal(seed):
    """No two planes intersect to give the axis of a slab turned within its own plane, and the
    slab is no rod: only the turns about its normal (voxels.in_plane_turns) find it."""
    start, end = paddle_on_a_plate(60.0, seed=seed)
    result = coarse_init(start, end)
    assert result.num_parts == 2, result.notes
    (joint,) = PartMotion.from_rt(result.motions, dtype=torch.float64).joints(np.zeros(3))
    assert joint["type"] == "revolute"
    assert abs(joint["angle_deg"] - 60.0) <= 3.0
    assert angle_between(joint["axis"], [0, 0, 1]) < 3.0
    assert line_distance(joint["origin"], PADDLE_PIVOT, np.array([0, 0, 1.0])) < 0.03


def test_without_turns_about_the_normal_a_flat_turn_is_missed(monkeypatch):
    start, end = paddle_on_a_plate(60.0)
    monkeypatch.setattr(voxels, "in_plane_turns", lambda *args: [])
    assert coarse_init(start, end).num_parts == 1


def test_surface_fit_tolerates_a_voxel_of_disagreement_between_dense_states():
    """The two states' reconstructions agree to about a voxel, however densely sampled: a
    piece half a voxel off its target still fits, three voxels off it does not. (Twice the
    centres' spacing, a sixteenth of a voxel here, would score both 0.)"""
    rng = np.random.default_rng(4)
    plate = box_surface([0.0, 0.0, 0.0], [1.0, 1.0, 0.01], 200_000, rng)
    split = split_static_dynamic(plate, plate, 0.05)
    assert 2 * split.spacing < 0.1 * split.grid.voxel_size
    piece = plate[:2000]
    lift = np.array([0.0, 0.0, 1.0]) * split.grid.voxel_size
    assert split.surface_fit(piece, np.eye(3), 0.5 * lift) > 0.7
    assert split.surface_fit(piece, np.eye(3), 3.0 * lift) < 0.01
