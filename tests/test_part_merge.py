"""Stage 3's merging of parts read twice (pipeline.stage3.merge): a part that another part's
motion, or staying put, explains about as well as its own joins it; distinct parts, and two
drawers pulled by the same travel, stay apart. Rendered with the deterministic torch
reference on tiny scenes: a static back wall (part 0) and planks in front of it."""

import json

import numpy as np
import pytest
import torch

from gear import geometry
from gear.articulation import PartMotion
from gear.config import make_config
from gear.outputs import drop_empty_parts
from gear.pipeline.runner import Runner
from gear.pipeline.stage2 import Stage2Result
from gear.pipeline.stage3 import Refine, merge, refine_parts
from gear.pipeline.stage3.joint_types import image_loss
from gear.pipeline.stage3.merge import FORGET_LOGIT, merge_parts, moved_like
from gear.splat_reference import rasterize_dense
from gear.splats import Gaussians, rendering
from stage3_scenes import OFFSET, grid_gaussians, plank, rot_z, views_of, wall

PULL = np.array([0.0, -0.25, 0.0])
HINGE = np.array([-0.3, -0.1, 0.0])  # the door's left edge (before OFFSET)
# Two doors above each other on one hinge line (a real cupboard's, cabinet_upper's).
STACKED = [(wall(), 0), (plank(-0.3, 0.0, z=0.15), 1), (plank(-0.3, 0.0, z=-0.15), 2)]


@pytest.fixture(autouse=True)
def torch_renderer(monkeypatch):
    monkeypatch.setattr(rendering, "rasterizer", lambda: rasterize_dense)


def hinge(deg: float) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of a turn by `deg` about the vertical line through the door's left edge."""
    rot, pivot = rot_z(deg), HINGE + OFFSET
    return rot, pivot - rot @ pivot


def stage(blocks, true_motions, trained_motions, **config) -> Refine:
    """A stage-3 state whose target views show the parts moved by `true_motions` and whose
    part motions are `trained_motions` (canonical -> target, one (R, t) per movable part)."""
    g = grid_gaussians(blocks)
    canonical = views_of(g, PartMotion(g.num_parts))
    target = views_of(g, PartMotion.from_rt(true_motions))
    cfg = make_config("quick", dict(em_interval=2, stage3_densify_until=0, **config))
    return Refine(g, PartMotion.from_rt(trained_motions), g.clone(), canonical, target, cfg,
                  seed=0)


def door_in_halves(second_half_deg: float) -> Refine:
    """A door turned 40° read as two parts: its larger left side (part 1) with the true turn,
    its right side (part 2, the smaller: it is judged first) with a turn of `second_half_deg`
    about the same hinge."""
    blocks = [(wall(), 0), (plank(-0.3, 0.0), 1), (plank(0.12, 0.3, columns=2), 2)]
    return stage(blocks, [hinge(40), hinge(40)], [hinge(40), hinge(second_half_deg)])


@pytest.mark.parametrize("second_half_deg", [40.0, 34.0])
def test_a_part_read_twice_joins_the_part(second_half_deg):
    s = door_in_halves(second_half_deg)
    right_half = s.gaussians.part_ids() == 2
    merges = merge_parts(s)
    assert [(m.part, m.into) for m in merges] == [(2, 1)]
    assert merges[0].cost <= merge.MERGE_SHARE * merges[0].gain
    ids = s.gaussians.part_ids()
    assert bool((ids[right_half] == 1).all()) and s.live_parts() == [1]
    logits = s.gaussians["logits"].detach()
    others = torch.cat([logits[:, :2], logits[:, 3:]], dim=1)
    assert bool((logits[:, 2] <= others.min(dim=1).values - FORGET_LOGIT + 1e-4).all())
    qr, qd = s.motion.motion()
    assert torch.allclose(qr[2], qr[1]) and torch.allclose(qd[2], qd[1])
    assert merge_parts(s) == []  # nothing left to merge


def test_distinct_parts_stay():
    """A door and a drawer: neither's motion explains the other, nor does staying put."""
    blocks = [(wall(), 0), (plank(-0.3, 0.0), 1), (plank(0.1, 0.3, z=-0.25), 2)]
    truth = [hinge(40), (np.eye(3), PULL)]
    s = stage(blocks, truth, truth)
    before = s.gaussians["logits"].detach().clone()
    assert merge_parts(s) == []
    assert torch.equal(s.gaussians["logits"].detach(), before)


@pytest.mark.parametrize("angles", [(40.7, 31.3), (22.6, 18.3)])
def test_doors_stacked_on_one_hinge_line_stay_two_parts(angles):
    """Two doors above each other on one hinge line, turned by different angles (a real
    cupboard's): neither's motion explains the other (stage 2 hands such a pair to stage 3
    cut in two, pipeline.stage2.stacked, and relies on this)."""
    truth = [hinge(angles[0]), hinge(angles[1])]
    s = stage(STACKED, truth, truth)
    assert merge_parts(s) == []
    assert s.live_parts() == [1, 2]


def test_stacked_doors_turned_alike_stay_two_parts_as_halves():
    """Two stacked doors turned 29.0 and 26.6 degrees (cabinet_upper's): one's motion costs
    the other less than MERGE_SHARE of its gain, so as parts read twice they would join; as
    the halves stage 2 cut from one part they are held to HALVES_MERGE_SHARE and stay two."""
    truth = [hinge(29.0), hinge(26.6)]
    s = stage(STACKED, truth, truth)
    assert merge_parts(s, halves=[(2, 1)]) == []
    assert s.live_parts() == [1, 2]
    merges = merge_parts(s)
    assert [(m.part, m.into) for m in merges] == [(1, 2)]
    assert merge.HALVES_MERGE_SHARE * merges[0].gain < merges[0].cost


def test_a_half_the_images_emptied_joins_its_partner(monkeypatch):
    """Halves of one door where the E-step has given all but two of one half's Gaussians to the
    other: the remnant (3 % of the pair's Gaussians), shown and trained 2.4 degrees off the
    door, so that the door's motion costs it more than HALVES_MERGE_SHARE of its gain, joins
    its partner all the same; with the emptied-half rule off it stays."""
    blocks = [(wall(), 0), (plank(-0.3, 0.0, columns=30), 1), (plank(0.0, 0.0, columns=1), 2)]
    turns = [hinge(29.0), hinge(26.6)]
    s = stage(blocks, turns, turns)
    monkeypatch.setattr(merge, "EMPTIED_HALF_SHARE", 0.0)
    assert merge_parts(s, halves=[(1, 2)]) == []
    monkeypatch.undo()
    merges = merge_parts(s, halves=[(1, 2)])
    assert [(m.part, m.into) for m in merges] == [(2, 1)]
    assert merges[0].cost > merge.HALVES_MERGE_SHARE * merges[0].gain
    assert s.live_parts() == [1]


def test_two_drawers_pulled_alike_stay_two_parts(monkeypatch):
    """Two drawers of a column (one above the other) pulled by the same travel: one motion
    explains both, but the lower one is not in line with the upper along the slide."""
    blocks = [(wall(), 0), (plank(-0.2, 0.2, z=0.15), 1), (plank(-0.2, 0.2, z=-0.15), 2)]
    slide = (np.eye(3), PULL)
    s = stage(blocks, [slide, slide], [slide, slide])
    base = image_loss(s, s.motion)
    assert image_loss(s, moved_like(s.motion, 2, 1)) - base == pytest.approx(0.0, abs=1e-6)
    assert merge_parts(s) == []
    monkeypatch.setattr(merge, "IN_LINE_SHARE", 0.0)  # the in-line test is what keeps them
    assert [(m.part, m.into) for m in merge_parts(s)] == [(1, 2)]


def test_two_drawers_stay_two_parts_when_one_has_strays_across_the_front(monkeypatch):
    """As above, with three opaque strays of the lower drawer scattered over the front, above
    and beside the upper one (a drawer hidden in the cabinet in one state gathers such strays
    in the E-step): the box of all its centres would hold the upper drawer, the box of its
    body does not."""
    strays = torch.tensor([[-0.4, -0.1, 0.3], [0.0, -0.1, 0.3], [0.4, -0.1, 0.3]])
    # Planks of 17 columns: centres as dense as a real model's, for the body test's voxel.
    lower = torch.cat([plank(-0.2, 0.2, z=-0.15, columns=17), strays])
    blocks = [(wall(), 0), (plank(-0.2, 0.2, z=0.15, columns=17), 1), (lower, 2)]
    slide = (np.eye(3), PULL)
    s = stage(blocks, [slide, slide], [slide, slide])
    assert merge_parts(s) == []
    assert s.live_parts() == [1, 2]
    monkeypatch.setattr(merge, "_body", lambda points, cell: points.numpy())  # every centre
    assert [(m.part, m.into) for m in merge_parts(s)] == [(1, 2)]


def test_a_part_its_own_motion_does_not_explain_joins_the_static_part():
    """A column of the wall read as a part with a small spurious shift: staying put explains
    its Gaussians better than its own motion does."""
    w = wall()
    blocks = [(w[:9], 0), (plank(-0.3, 0.3), 1), (w[9:], 2)]
    s = stage(blocks, [hinge(40), (np.eye(3), np.zeros(3))],
              [hinge(40), (np.eye(3), np.array([0.0, 0.0, 0.08]))])
    merges = merge_parts(s)
    assert [(m.part, m.into) for m in merges] == [(2, 0)] and merges[0].gain < 0
    assert s.live_parts() == [1]


def scored_by_table(monkeypatch, s: Refine, table: dict[tuple[int, int], float]) -> None:
    """Make merge's image loss a table: the sum over parts k moved by part j's motion (j = 0:
    staying put, j = k: its own) of table[k, j], 0 where absent, so that gains and costs are
    set exactly rather than rendered."""
    qr, qd = (x.detach().clone() for x in s.motion.motion())
    own = [(qr[j], qd[j]) for j in range(s.motion.num_parts)]

    def loss(state, motion):
        mr, md = motion.motion()
        total = 0.0
        for k in range(1, motion.num_parts):
            j = next(j for j, (r, d) in enumerate(own)
                     if torch.allclose(mr[k], r, atol=1e-6) and torch.allclose(md[k], d, atol=1e-6))
            total += table.get((k, j), 0.0)
        return total

    monkeypatch.setattr(merge, "image_loss", loss)


@pytest.mark.parametrize("gain, cost_like_door, into", [
    (0.02, 0.5, 0),    # not seen to move, the door's turn explains it worse: static
    (0.02, 0.01, 1),   # not seen to move, the door's turn explains it better: the door
    (0.04, 0.5, None),  # seen to move (4 % of the door's gain): a part of its own
])
def test_a_part_whose_motion_is_not_seen_joins_the_part_that_explains_it(
        monkeypatch, gain, cost_like_door, into):
    """A part whose own motion gains at most UNSEEN_GAIN_SHARE of the largest gain (a strip
    hidden inside a cabinet, turned onto itself) is not seen to move: it joins whichever
    explains it no worse than staying put, though that costs more than MERGE_SHARE of it."""
    blocks = [(wall(), 0), (plank(-0.3, 0.0), 1), (plank(0.15, 0.3, z=-0.2, columns=2), 2)]
    truth = [hinge(40), (np.eye(3), np.array([0.05, 0.0, 0.0]))]
    s = stage(blocks, truth, truth)
    assert merge.UNSEEN_GAIN_SHARE == 0.03
    scored_by_table(monkeypatch, s, {(1, 0): 1.0, (1, 2): 0.8, (2, 0): gain,
                                     (2, 1): cost_like_door})
    merges = merge_parts(s)
    if into is None:
        assert merges == [] and s.live_parts() == [1, 2]
    else:
        assert [(m.part, m.into) for m in merges] == [(2, into)]
        assert merges[0].gain == pytest.approx(gain)
        assert merges[0].cost > merge.MERGE_SHARE * merges[0].gain


# Four pairs of Gaussians (a pair: 0.05 apart along x) at the object's corners, or gathered
# in one place beside the door.
SCATTERED = [[-0.55, -0.1, -0.5], [0.5, -0.1, -0.5], [0.5, -0.1, 0.5], [-0.55, -0.1, 0.5]]
GATHERED = [[0.25, -0.1, 0.15], [0.35, -0.1, 0.15], [0.25, -0.1, 0.25], [0.35, -0.1, 0.25]]


@pytest.mark.parametrize("where, gain, stays", [
    ("scattered", 0.1, False),  # no body, its gain a tenth of the door's: joins the static part
    ("gathered", 0.1, True),    # one body: a part
    ("scattered", 0.45, True),  # no body, but seen to move (a door with few opaque centres)
])
def test_a_part_that_is_no_body_joins_the_static_part(monkeypatch, where, gain, stays):
    """Four pairs of Gaussians pulled by a motion of their own, scattered over the object's
    corners, are not one body: while their gain is under NO_BODY_GAIN_SHARE of the door's
    they are judged as a part not seen to move and join the static part (staying put
    explains them better than the door's turn). Gathered in one place, or gaining more, they
    are a part and stay. The image loss is a table, so that the gains are set exactly."""
    centres = torch.tensor(SCATTERED if where == "scattered" else GATHERED)
    pairs = torch.cat([centres, centres + torch.tensor([0.05, 0.0, 0.0])])
    blocks = [(wall(), 0), (plank(-0.3, 0.0, columns=7), 1), (pairs, 2)]
    truth = [hinge(40), (np.eye(3), PULL)]
    s = stage(blocks, truth, truth)
    assert merge.UNSEEN_GAIN_SHARE < gain and merge.NO_BODY_GAIN_SHARE == 0.25
    scored_by_table(monkeypatch, s, {(1, 0): 1.0, (1, 2): 0.8, (2, 0): gain,
                                     (2, 1): 2 * gain})
    merges = merge_parts(s)
    if stays:
        assert merges == [] and s.live_parts() == [1, 2]
    else:
        assert [(m.part, m.into) for m in merges] == [(2, 0)] and s.live_parts() == [1]


def test_merge_at_classification_then_dropped_from_the_outputs():
    s = door_in_halves(34.0)
    s.config.joint_classify_iteration = 2  # an M-step iteration (em_interval 2)
    terms = s.step(2)
    assert all(torch.isfinite(torch.as_tensor(v)).all() for v in terms.values())
    event = next(e for e in s.events if e.get("event") == "part_merge")
    assert [(m["part"], m["into"]) for m in event["merges"]] == [(2, 1)]
    assert any(e.get("event") == "joint_classification" for e in s.events)
    g, motion, dropped = drop_empty_parts(s.gaussians, s.motion)
    assert dropped == [2] and motion.num_parts == 2 and g.num_parts == 2


def test_halves_of_a_stacked_cut_join_only_at_the_end():
    """Two halves stage 2 cut from one part tall along its hinge are kept apart at the
    joint-type decision (each may still hold a slice of the other door) and join at the end
    when one motion explains both."""
    s = door_in_halves(34.0)
    s.halves = [(1, 2)]
    s.config.joint_classify_iteration = 2
    s.step(2)
    event = next(e for e in s.events if e.get("event") == "part_merge")
    assert event["merges"] == [] and s.live_parts() == [1, 2]
    s = door_in_halves(34.0)
    assert merge_parts(s, apart=[(2, 1)]) == [] and s.live_parts() == [1, 2]
    assert [(m.part, m.into) for m in merge_parts(s, halves=[(2, 1)])] == [(2, 1)]


@pytest.mark.parametrize("doors", ["one", "stacked"])
def test_parts_read_twice_merge_again_at_the_end_of_stage3(tmp_path, doors):
    """A fragment whose motion reaches its part's only after the joint-type decision (here
    never reached) still joins it: stage 3 merges once more before its result. Two stacked
    doors turned 29.0 and 26.6 degrees, cut in halves by stage 2, stay two parts there."""
    if doors == "one":
        blocks = [(wall(), 0), (plank(-0.3, 0.0), 1), (plank(0.12, 0.3, columns=2), 2)]
        truth = [hinge(40), hinge(40)]
    else:
        blocks, truth = STACKED, [hinge(29.0), hinge(26.6)]
    g = grid_gaussians(blocks)
    views = {"start": views_of(g, PartMotion(g.num_parts)),
             "end": views_of(g, PartMotion.from_rt(truth))}
    cfg = make_config("quick", dict(em_interval=2, stage3_densify_until=0, stage3_iterations=2,
                                    joint_classify_iteration=10))
    logits = g["logits"].detach().clone()
    model = Gaussians({k: v.detach() for k, v in g.params.items() if k != "logits"})
    # as if stage 2 had cut one part in halves: they may join at the end
    coarse = Stage2Result("start", 3, logits, [[m] for m in truth], 0.1, halves=[(1, 2)])
    runner = Runner(tmp_path, cfg, quiet=True)
    try:
        result = refine_parts({"start": model}, coarse, views, cfg, runner, None)
    finally:
        runner.log.close()
    assert result is not None
    records = [json.loads(line) for line in (tmp_path / "log.jsonl").read_text().splitlines()]
    merges = [r for r in records if r.get("event") == "part_merge"]
    assert len(merges) == 1 and merges[0]["when"] == "end"
    if doors == "one":
        assert set(result.gaussians.part_ids().tolist()) == {0, 1}
        assert [(m["part"], m["into"]) for m in merges[0]["merges"]] == [(2, 1)]
    else:
        assert set(result.gaussians.part_ids().tolist()) == {0, 1, 2}
        assert merges[0]["merges"] == []


def test_merging_can_be_turned_off():
    s = door_in_halves(34.0)
    s.config.joint_classify_iteration = 2
    s.config.merge_redundant_parts = False
    s.step(2)
    assert not any(e.get("event") == "part_merge" for e in s.events)
    assert s.live_parts() == [1, 2]


def test_share_in_line():
    other = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 1.0], [0.5, 5.0, 0.5]])
    along_y = np.array([0.0, 2.0, 0.0])
    inside = np.array([[0.5, -3.0, 0.5], [0.9, 9.0, 0.1]])  # anywhere along y
    outside = np.array([[1.5, 0.0, 0.5], [0.5, 0.0, -0.5]])
    assert geometry.share_in_line(inside, other, along_y, 0.0) == 1.0
    assert geometry.share_in_line(outside, other, along_y, 0.0) == 0.0
    assert geometry.share_in_line(np.vstack([inside, outside]), other, along_y, 0.0) == 0.5
    assert geometry.share_in_line(outside, other, along_y, 0.6) == 1.0  # grown by the margin
    assert geometry.share_in_line(outside[:0], other, along_y, 0.0) == 0.0
    # a stray point stretches the box unless trimmed
    strays = np.vstack([np.full((98, 3), 0.5), [[9.0, 0.0, 9.0]], [[0.0, 0.0, 0.0]]])
    far = np.array([[5.0, 0.0, 5.0]])
    assert geometry.share_in_line(far, strays, along_y, 0.0) == 1.0
    assert geometry.share_in_line(far, strays, along_y, 0.1, trim=0.02) == 0.0
