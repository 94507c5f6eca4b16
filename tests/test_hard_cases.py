"""Hard cases: the articulations the method is known to find hard, each with its
tolerance stated where it is asserted.

Stage-2 cases (a door turned by 2 degrees, a drawer pulled by 1 % of the object, two identical
states) run stage 2 on the depth of tiny renders, back-projected: a clean stand-in for the
stage-1 centres, fine enough to see such small motions. The other cases train on tiny scenes
(32-64 px, 8 views per state) with the GPU rasterizer in float32, on the quick profile's schedule
compressed about 4x (tests/hard_scenes.py; GEAR_HARD_QUICK=1 runs the uncompressed schedule).
Nothing reads ground truth before a result is final; the tests compare with it afterwards.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field

import numpy as np
import pytest
import torch

from gear import _core
from gear.articulation import PartMotion
from gear.metrics import match_parts
from gear.pipeline.stage2.parts import coarse_init
from gear.pipeline.stage3 import joint_types
from gear.pipeline.stage3.joint_types import classify_joints
from gear.pipeline.stage3.shared import RefineState
from gear.splats import Densifier, Gaussians
from hard_scenes import (
    STAGE1_QUICK,
    Run,
    axis_angle_deg,
    backprojected,
    hard_config,
    line_distance,
    make_scene,
    object_size,
    run_stages,
    variant,
)

GPU = pytest.mark.skipif(not hasattr(_core, "rasterize_forward"),
                         reason="needs the GPU rasterizer in gear._core")
STAGE2_RES, STAGE2_VIEWS = 64, 24
TRAIN_VIEWS = 8


def stage2_joints(result, center: np.ndarray) -> list[list[dict]]:
    """Every stage-2 reading (candidate) of every part, as canonical -> target joints."""
    return [PartMotion.from_rt(c, dtype=torch.float64).joints(center) for c in result.candidates]


def assert_finite_joint(joint: dict) -> None:
    for key in ("axis", "origin"):
        assert np.isfinite(joint[key]).all(), f"{key} is not finite: {joint}"
    assert abs(np.linalg.norm(joint["axis"]) - 1.0) < 1e-6, f"axis is not a unit vector: {joint}"
    assert math.isfinite(joint["angle_deg"]) and math.isfinite(joint["distance"])
    # The type and the motion agree: a slide does not turn, a hinge does not slide.
    if joint["type"] == "prismatic":
        assert joint["angle_deg"] == 0.0 and joint["distance"] > 0.0, joint
    else:
        assert joint["type"] == "revolute" and joint["distance"] == 0.0, joint


def assert_finite_model(run: Run) -> None:
    """Every logged loss term of every stage is finite and so is every trained parameter."""
    losses = run.losses()
    stages = {s for s, *_ in losses}
    assert "stage1" in stages
    assert {t.split("/")[0] for s, _, t, _ in losses if s == "stage1"} == {"start", "end"}
    bad = [entry for entry in losses if not math.isfinite(entry[3])]
    assert not bad, f"non-finite losses: {bad[:5]}"
    if run.refine is not None:
        assert "stage3" in stages
        for name, value in run.refine.gaussians.params.items():
            assert torch.isfinite(value).all(), f"stage-3 parameter {name} has NaN/Inf"
        for tensor in run.refine.motion.motion():
            assert torch.isfinite(tensor).all(), "part motion has NaN/Inf"
    for joint in run.joints:
        assert_finite_joint(joint)


# ------------------------------------------------------------------ stage 2 on back-projections


@pytest.fixture(scope="module")
def door_two_degrees(tmp_path_factory):
    """The built-in fridge with its door turned by 2 degrees (from 8.6 to 10.6): its free edge
    moves 2.4 cm on a 1.5 m object."""
    obj = variant("fridge", {"door": (0.15, 0.15 + math.radians(2.0))})
    scene = make_scene(tmp_path_factory.mktemp("door2"), obj, STAGE2_RES, STAGE2_VIEWS)
    return scene, backprojected(scene)


@pytest.mark.parametrize("num_parts", [None, 2])
def test_two_degree_door_gets_one_consistent_finite_joint(door_two_degrees, num_parts):
    """A 2-degree hinge is below the coarse grid (and below ε = 10 degrees): stage 2 must still
    see one moving part and give it a finite joint, a slide or a hinge, never NaN."""
    _, points = door_two_degrees
    result = coarse_init(points["start"], points["end"], num_parts)
    assert result.num_parts == 2, result.notes
    center = points["start"].mean(axis=0)
    for reading in stage2_joints(result, center)[0]:
        assert_finite_joint(reading)
    motion = PartMotion.from_rt(result.motions)
    joint = motion.joints(center)[0]
    # The door's free edge moves along -x-y (GT hinge axis -z); a slide must point that way
    # within 20 degrees, a hinge's axis must be within 20 degrees of the hinge's.
    if joint["type"] == "prismatic":
        edge_motion = np.array([-1.0, -1.0, 0.0]) / np.sqrt(2)
        assert axis_angle_deg(joint["axis"], edge_motion) < 20.0, joint
        assert 0.005 < joint["distance"] < 0.05, joint  # 2.4 cm of edge travel, +-2 voxels
    else:
        assert axis_angle_deg(joint["axis"], [0, 0, 1]) < 20.0, joint


def test_two_degree_hinge_is_classified_consistently():
    """Stage 3's ε rule on a 2-degree hinge: the paper's rule makes it prismatic, the image-scored
    rule keeps whichever reading scores lower; either way the joint is finite and typed as its
    motion is."""
    angle = math.radians(2.0)
    hinge = (np.array([[math.cos(angle), -math.sin(angle), 0.0],
                       [math.sin(angle), math.cos(angle), 0.0], [0.0, 0.0, 1.0]]),
             np.array([0.02, -0.01, 0.0]))
    center = np.array([0.3, 0.2, 0.5])
    paper = PartMotion.from_rt([hinge])
    assert classify_joints(paper, eps_deg=10.0) == [1]
    assert paper.joints(center)[0]["type"] == "prismatic"
    for prefer in ("revolute", "prismatic"):
        scored = PartMotion.from_rt([hinge])

        def score(candidate: PartMotion, prefer: str = prefer) -> float:
            j = candidate.joints(center)[0]
            return 0.0 if j["type"] == prefer else 1.0

        classify_joints(scored, eps_deg=10.0, score=score, init_motions=[[hinge]])
        joint = scored.joints(center)[0]
        assert joint["type"] == prefer
        assert_finite_joint(joint)
        for tensor in scored.motion():
            assert torch.isfinite(tensor).all()


def test_one_percent_drawer_is_a_slide_along_the_drawer(tmp_path):
    """The drawer cabinet's drawer pulled by 1 % of the cabinet's 0.9 m (9 mm, under a third of
    a pixel at 64 px): one prismatic part, direction within 5 degrees, travel within one voxel."""
    base = variant("drawer_cabinet")
    travel = 0.01 * object_size(base)
    obj = variant("drawer_cabinet", {"drawer_1": (0.05, 0.05 + travel)})
    scene = make_scene(tmp_path / "drawer", obj, STAGE2_RES, STAGE2_VIEWS)
    points = backprojected(scene)
    gt = obj.parts[0].joint
    for num_parts in (None, 2):
        result = coarse_init(points["start"], points["end"], num_parts)
        assert result.num_parts == 2, result.notes
        joint = PartMotion.from_rt(result.motions).joints(np.zeros(3))[0]
        assert joint["type"] == "prismatic", joint
        want = gt.axis if result.canonical == "start" else -gt.axis
        cos = float(np.dot(joint["axis"], want))
        assert math.degrees(math.acos(min(1.0, cos))) < 5.0, joint  # signed: not pushed in
        assert abs(joint["distance"] - travel) <= result.voxel_size, (joint, result.voxel_size)


def test_half_turn_door_keeps_fold_and_slide_in_stage2(tmp_path):
    """safe180's square door (0.6 x 0.6 m) opened by 180 degrees lies flat beside its closed
    place: the voxels cannot tell a half turn from a slide of the slab, so stage 2 must hand both
    readings to stage 3. The fold: 180 +- 1 degrees, axis within 3 degrees, line within 5 cm."""
    obj = variant("safe180")
    points = backprojected(make_scene(tmp_path / "safe", obj, STAGE2_RES, STAGE2_VIEWS))
    gt = obj.parts[0].joint
    result = coarse_init(points["start"], points["end"])
    center = points["start"].mean(axis=0)
    door = [r for r in stage2_joints(result, center) if any(j["type"] == "revolute" for j in r)]
    assert len(door) == 1, result.notes
    assert sorted(j["type"] for j in door[0]) == ["prismatic", "revolute"], result.notes
    fold = next(j for j in door[0] if j["type"] == "revolute")
    assert abs(fold["angle_deg"] - 180.0) <= 1.0, fold
    assert axis_angle_deg(fold["axis"], gt.axis) <= 3.0, fold
    assert line_distance(fold["origin"], gt.origin, gt.axis) <= 0.05, fold


def test_identical_states_have_no_moving_part_in_stage2(tmp_path):
    """Both states of the fridge with the door at the same angle, seen by different cameras:
    stage 2 finds no motion and one static part."""
    obj = variant("fridge", {"door": (0.6, 0.6)})
    points = backprojected(make_scene(tmp_path / "same", obj, STAGE2_RES, STAGE2_VIEWS))
    for num_parts in (None, 2):
        result = coarse_init(points["start"], points["end"], num_parts)
        assert result.num_parts == 1 and result.motions == [], result.notes
        assert np.isfinite(result.logits).all()


# ------------------------------------------------------------------ training runs (GPU, float32)


class Spies:
    """Records, during a run, every joint reading stage 3 scores (joint_types.motion_loss) and every
    stage-3 opacity reset (which Gaussians, their parts, opacities before and after)."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.scored: list[tuple[list[dict], float]] = []
        self.resets: list[dict] = []
        spies = self
        motion_loss, reset_opacity = joint_types.motion_loss, Densifier.reset_opacity

        def scored_loss(stage: RefineState, candidate: PartMotion) -> float:
            value = motion_loss(stage, candidate)
            center = stage.gaussians["means"].detach().mean(dim=0).numpy()
            spies.scored.append((candidate.joints(center), value))
            return value

        def spied_reset(strategy: Densifier, g: Gaussians,
                        protect: torch.Tensor | None = None) -> int:
            if g.num_parts == 1:  # stage 1
                return reset_opacity(strategy, g, protect)
            before = torch.sigmoid(g["opacity"].detach()).clone()
            n = reset_opacity(strategy, g, protect)
            spies.resets.append(dict(parts=g.part_ids(), before=before,
                                     after=torch.sigmoid(g["opacity"].detach()).clone(),
                                     protect=None if protect is None else protect.clone()))
            return n

        monkeypatch.setattr(joint_types, "motion_loss", scored_loss)
        monkeypatch.setattr(Densifier, "reset_opacity", spied_reset)


def matched(run: Run) -> tuple[list[tuple[dict, object, dict]], object]:
    """(predicted joint, GT joint, errors) per GT joint matched, and the Matching."""
    gt = run.scene.gt.joints
    matching = match_parts(run.joints, gt)
    return [(run.joints[p], gt[g], e) for (g, p), e in zip(matching.pairs, matching.errors,
                                                           strict=True)], matching


@dataclass(frozen=True)
class Case:
    """A training case: a built-in object (joint values changed by `values`, see
    hard_scenes.variant), its render settings and config overrides."""

    obj: str
    res: int = 32
    effects: tuple = ()
    depth: bool = True
    values: dict | None = None
    config: dict = field(default_factory=dict)


CASES: dict[str, Case] = {
    "fridge": Case("fridge"),
    "drawer_cabinet": Case("drawer_cabinet"),
    "laptop": Case("laptop"),
    "box_lid": Case("box_lid"),
    "oven": Case("oven"),
    "storage7": Case("storage7"),
    # Stage 1 on the quick profile's own schedule: in the compressed 70 iterations a door came
    # out a slide or was lost on 14 of 24 training seeds (measured), and 16 views instead of 8
    # made it worse (10 of 12): too few passes over each view. With 300: both right on 11 of 12.
    "double_door": Case("double_door", res=40, config=dict(STAGE1_QUICK)),
    "safe180": Case("safe180"),
    # The same scene trained from two more seeds: at 32 px the half turn and the in-plane
    # turns of the square door that land it in the same place differ by a dial of a pixel or
    # two and 6 cm of depth, so which reading the images prefer varies with the seed.
    "safe180_seed1": Case("safe180", config=dict(seed=1)),
    "safe180_seed2": Case("safe180", config=dict(seed=2)),
    # The lever is 1.8 cm thick: 64 px make it a few pixels wide. K = 2 is given (the test is
    # about keeping a small part through opacity resets, not about finding it), and stage 3
    # resets opacity at iterations 30 and 60, inside its densification window. Four training
    # seeds: whether stage 3 keeps the lever as a part at all varies with the seed (below).
    **{name: Case("handle", res=64, config=dict(num_parts=2, opacity_reset_interval=30,
                                                 stage3_densify_until=61, seed=seed))
       for seed, name in enumerate(("handle", "handle_seed1", "handle_seed2", "handle_seed3"))},
    "fridge_flawed_masks": Case("fridge", effects=("mask-over", "mask-under")),
    # Without depth, stage 1 learns the geometry from colour alone, starting from the surface of
    # the masks' visual hull: it runs the quick profile's own stage-1 schedule (300 iterations;
    # stages 2-3 stay compressed). In the compressed 70 the Gaussians barely leave the hull, which
    # cannot carve the hollow between the open door and the body: stage 2 then found no door
    # hinge with 8, 16 or 24 views (measured). With 300, the volume-sampled hull used before
    # still failed (Geo Dist 60 and 129 degrees on seeds 0 and 1).
    "fridge_no_depth": Case("fridge", depth=False, config=dict(STAGE1_QUICK)),
    # The door turned by 2 degrees: its edge moves 2.4 cm, under a pixel at 32 px. K = 2 given.
    "door_2deg": Case("fridge", values={"door": (0.15, 0.15 + math.radians(2.0))},
                      config=dict(num_parts=2)),
}


class Runs:
    """Training runs shared by the tests of this module (each made once, on first use)."""

    def __init__(self, tmp_path_factory: pytest.TempPathFactory) -> None:
        self.factory = tmp_path_factory
        self.done: dict[str, tuple[Run, Spies]] = {}

    def get(self, name: str) -> tuple[Run, Spies]:
        if name not in self.done:
            case = CASES[name]
            root = self.factory.mktemp(name)
            scene = make_scene(root / "scene", variant(case.obj, case.values), case.res,
                               TRAIN_VIEWS, case.effects, case.depth)
            with pytest.MonkeyPatch.context() as monkeypatch:
                spies = Spies(monkeypatch)
                run = run_stages(scene, root / "out", hard_config(**case.config))
            self.done[name] = (run, spies)
        return self.done[name]


BUILT_IN = ["fridge", "drawer_cabinet", "laptop", "box_lid", "oven", "storage7", "double_door",
            "safe180", "handle"]


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Runs:
    return Runs(tmp_path_factory)


def test_every_built_in_object_has_a_case():
    from gear.synth import describe

    assert sorted(BUILT_IN) == sorted(name for name, _ in describe())
    assert all(CASES[name].obj == name and CASES[name].values is None for name in BUILT_IN)


@GPU
@pytest.mark.parametrize("name", BUILT_IN)
def test_float32_losses_stay_finite_on_every_built_in_object(runs, name):
    """Every loss term logged at every iteration of stages 1 and 3, every trained parameter, the
    motions and the reported joints are finite (float32, GPU rasterizer)."""
    run, _ = runs.get(name)
    assert run.losses(), "nothing was logged"
    assert_finite_model(run)


@GPU
def test_half_turn_door_is_a_180_degree_hinge_chosen_by_the_images(runs):
    """safe180 (0 -> 180 degrees), the paper's documented failure, trained from three seeds. In
    every run stage 2 must keep a half-turn reading of the door, stage 3 must score it on the
    target images (photometric + depth, joint_types.motion_loss) beside the other readings and
    keep the lowest. The square door is the hard part: turned in its own plane by 90 or 180
    degrees about a point of its edge it lands where the half turn puts it, and at 32 px only a
    dial of a pixel or two and 6 cm of depth tell them apart, so the images pick the in-plane
    turn on some seeds (measured over seeds 0-5: 4 and 5 of 6 right, with two roundings of the
    optimiser). Required: the half turn kept and scored on every seed, and the right hinge
    (180 +- 5 degrees, axis within 5 degrees, line within 5 cm of a 0.6 m safe) on two of the
    three."""
    right = []
    for name in ("safe180", "safe180_seed1", "safe180_seed2"):
        run, spies = runs.get(name)
        pairs, matching = matched(run)
        assert len(pairs) == 1, (name, matching)
        pred, gt, errors = pairs[0]
        k = pred["part"]
        center = run.refine.gaussians["means"].detach().mean(dim=0).numpy()
        readings = PartMotion.from_rt(run.coarse["candidates"][k - 1], dtype=torch.float64)
        kinds = [(j["type"], round(j["angle_deg"], 1)) for j in readings.joints(center)]
        assert any(kind == "revolute" and angle > 170 for kind, angle in kinds), (
            name, f"stage 2 readings: {kinds}", run.notes)
        scored = [(joints[k - 1], loss) for joints, loss in spies.scored]
        assert len(scored) >= 2, (name, scored)
        assert any(j["type"] == "revolute" and j["angle_deg"] > 170 for j, _ in scored), (
            name, scored)
        best = min(scored, key=lambda entry: entry[1])[0]
        assert pred["type"] == best["type"], (name, pred, scored)
        assert abs(pred["angle_deg"] - best["angle_deg"]) <= 5.0, (name, pred, scored)
        right.append(pred["type"] == "revolute" and abs(pred["angle_deg"] - 180.0) <= 5.0
                     and errors["axis_ang"] <= 5.0
                     and line_distance(pred["origin"], gt.origin, gt.axis) <= 0.05)
    assert sum(right) >= 2, right


@GPU
def test_flush_double_doors_are_two_hinges(runs):
    """double_door: two doors flush against each other when closed. Two movable parts, both
    revolute, axes within 5 degrees, axis lines within 10 cm (of a 0.9 m cabinet), angles within
    10 degrees of 63 and 40. Stage 2 may cut a door in two (K = 4-6 on 7 of 12 seeds, measured);
    stage 3 must join the pieces, so that two movable parts hold Gaussians at the end."""
    run, _ = runs.get("double_door")
    pairs, matching = matched(run)
    counts = torch.bincount(run.refine.gaussians.part_ids()).tolist()
    assert sum(c > 0 for c in counts[1:]) == 2, (counts, run.notes)
    assert len(pairs) == 2 and not matching.type_mismatches, matching
    for pred, gt, errors in pairs:
        assert errors["axis_ang"] <= 5.0, (pred, errors)
        assert line_distance(pred["origin"], gt.origin, gt.axis) <= 0.1, (pred, gt.origin)
        assert abs(pred["angle_deg"] - gt.amount) <= 10.0, (pred, gt.amount)


@GPU
def test_thin_handle_survives_opacity_resets(runs):
    """handle: the lever (16 x 1.8 x 1.8 cm) is a part of far fewer than N_thresh = 2000
    Gaussians. At every stage-3 opacity reset where it holds Gaussians, they keep their opacity
    exactly while the static body's drop to <= 0.01. Where the lever is still a part through both
    resets, at the end it holds >= 80 % of the Gaussians it had at the first reset, and their
    mean opacity is at least 10x the 0.01 a reset leaves and >= 80 % of their mean just before
    the first reset (measured: 0.09 before, 0.25 at the end).

    Whether it is still a part is the joint-type decision's (iteration 40, between the resets):
    at this budget the lever's learnt motion sometimes explains the images worse than holding it
    still (gain < 0 on seed 0 with one rounding of the optimiser), and the part then joins the
    static body, rightly for what the images show. That happened on 2 to 4 of 6 training seeds
    depending on the rounding; the lever must be kept on at least one of the four seeds here."""
    kept = 0
    for name in ("handle", "handle_seed1", "handle_seed2", "handle_seed3"):
        run, spies = runs.get(name)
        assert run.refine is not None and run.num_parts == 2, name
        threshold = hard_config(**CASES[name].config).small_part_threshold
        assert len(spies.resets) == 2, "expected stage-3 resets at iterations 30 and 60"
        counts = [int((reset["parts"] == 1).sum()) for reset in spies.resets]
        for reset, count in zip(spies.resets, counts, strict=True):
            assert count < threshold, (name, count)
            lever = reset["parts"] == 1
            assert torch.equal(reset["after"][lever], reset["before"][lever]), name
            static = reset["parts"] == 0
            assert (reset["after"][static] <= 0.01 + 1e-6).all(), name
        if 0 in counts:
            continue
        kept += 1
        first = spies.resets[0]
        first_opacity = float(first["before"][first["parts"] == 1].mean())
        g = run.refine.gaussians
        lever = g.part_ids() == 1
        opacity = torch.sigmoid(g["opacity"].detach())[lever]
        assert int(lever.sum()) >= 0.8 * counts[0], (name, int(lever.sum()), counts[0])
        assert float(opacity.mean()) >= max(0.1, 0.8 * first_opacity), (
            name, opacity.mean(), first_opacity)
    assert kept >= 1


@GPU
def test_flawed_masks_still_give_the_fridge_door(runs):
    """The fridge with over-segmented (regions cut in 2-3) and under-segmented (touching regions
    of different parts merged) masks: the door hinge within 5 degrees of axis, 12 cm of axis
    line and 10 degrees of rotation (Geo Dist). The line distance at this tiny budget (8 views,
    70 + 80 iterations) measured 0.035-0.101 over training seeds 0-2 (0.047-0.095 with the
    paper's frozen anchor; seed 0 is the largest with both), hence 12 cm rather than 10."""
    run, _ = runs.get("fridge_flawed_masks")
    pairs, matching = matched(run)
    assert len(pairs) == 1 and not matching.type_mismatches, (matching, run.joints)
    pred, gt, errors = pairs[0]
    assert errors["axis_ang"] <= 5.0, errors
    assert line_distance(pred["origin"], gt.origin, gt.axis) <= 0.12, (pred, gt.origin)
    assert errors["geo_dist"] <= 10.0, errors


@GPU
def test_fridge_without_depth_trains_finite(runs):
    """No depth images at all: stage 1 starts on the surface of the masks' visual hull and trains
    on colour and silhouettes; every loss, parameter and joint stays finite and no depth term is
    ever computed.

    Finding the door itself (axis within 10 degrees, Geo Dist within 15) is not asserted: it
    held in 7 of 9 runs on this scene but in about one of ten on other renders of the fridge,
    and the same seed passes or fails from run to run (GPU atomics sum in no fixed order); a
    test of it could only be skipped or made unable to fail (docs/training.md, "Without
    depth")."""
    run, _ = runs.get("fridge_no_depth")
    assert not run.scene.has_depth
    assert not any(term == "depth" for _, _, term, _ in run.losses())
    assert_finite_model(run)
    assert run.joints, run.notes


@GPU
def test_identical_states_give_one_static_part_and_no_joint(tmp_path):
    """Both states with the door at the same angle: `train` says there is no motion, writes the
    canonical stage-1 model as one static part and an empty joint list, nothing NaN. Stage 1
    runs the quick profile's own 300 iterations on 16 views per state (the run stops after it):
    after the compressed 70, unpruned low-opacity floaters behind the fridge (86 centres, mean
    opacity 0.15) passed stage 2's tests as a part sliding 0.27 m, and with 8 views noise
    components still did in about one run in four (measured)."""
    from gear.train import train
    from gear.twin import read_ply_vertices

    obj = variant("fridge", {"door": (0.6, 0.6)})
    scene = make_scene(tmp_path / "scene", obj, 32, 2 * TRAIN_VIEWS)
    out = tmp_path / "out"
    result = train(scene, out, hard_config(**STAGE1_QUICK), quiet=True)
    assert result.joints == []
    saved = json.loads((out / "joints.json").read_text())
    assert saved["joints"] == []
    parts = np.load(out / "parts.npy")
    assert len(parts) > 0 and (parts == 0).all()
    ply = read_ply_vertices(out / "gaussians_canonical.ply")
    assert len(ply["x"]) == len(parts) and (ply["part"] == 0).all()
    assert all(np.isfinite(values).all() for values in ply.values())
    log = (out / "log.jsonl").read_text()
    assert "no motion detected" in log
    assert "stage3" not in {json.loads(line).get("stage") for line in log.splitlines()}


@GPU
def test_two_degree_door_trains_without_nan(runs):
    """The 2-degree door trained end to end with K = 2 given. Its edge moves 2.4 cm, under a pixel
    at 32 px and under the 5 cm fine voxel of a 1500-centre stage-1 model (measured), so stage 2
    may report no motion (one static part, no joint; the back-projection test above shows the
    part once the data resolve it). Otherwise it is one joint, typed as its motion is. Either
    way every loss, parameter and output is finite."""
    run, _ = runs.get("door_2deg")
    assert_finite_model(run)
    if run.num_parts == 1:
        assert run.joints == [] and any("no motion" in note for note in run.notes), run.notes
    else:
        assert run.num_parts == 2 and len(run.joints) == 1, run.joints
