"""initialise_parts hands stage 2 only the opaque Gaussians' centres: low-opacity floaters would
otherwise become parts of their own. The dropped Gaussians take their part logits from the
nearest opaque one."""

import numpy as np
import pytest
import torch

from gear.config import make_config
from gear.pipeline.runner import Runner
from gear.pipeline.stage2 import initialise as stage2
from gear.pipeline.stage2.initialise import STAGE2_MIN_OPACITY, stage2_selection
from gear.pipeline.stage2.parts import coarse_init
from gear.splats import Gaussians
from stage2_surfaces import OneView
from test_coarse import FRAMES, door_scene

FLOATERS = 300  # per state: a haze cluster in front of the cabinet, elsewhere in each state


def haze(centre, rng) -> np.ndarray:
    """A flat sheet of haze (0.2 x 0.03 x 0.2), as floaters often are."""
    return np.asarray(centre) + (rng.random((FLOATERS, 3)) - 0.5) * [0.2, 0.03, 0.2]


def model_of(points: np.ndarray, opacity: np.ndarray) -> Gaussians:
    n = len(points)
    p = torch.as_tensor(opacity, dtype=torch.float32)
    return Gaussians(dict(
        means=torch.as_tensor(points, dtype=torch.float32),
        quats=torch.tensor([1.0, 0, 0, 0]).repeat(n, 1),
        log_scales=torch.full((n, 3), -4.0),
        opacity=torch.log(p / (1 - p)),
        colors=torch.zeros(n, 3),
    ))


def hazy_door_scene():
    """The 60-degree door of test_coarse, opaque (0.9), plus a floater cluster (opacity 0.05)
    in front of the cabinet in each state, 0.35 apart from one state to the other."""
    rng = np.random.default_rng(3)
    start, end, *_ = door_scene(60.0, FRAMES["identity"], n=6000)
    floaters = {"start": haze([0.3, -0.8, 0.9], rng), "end": haze([0.65, -0.8, 0.9], rng)}
    points = {"start": np.concatenate([start, floaters["start"]]),
              "end": np.concatenate([end, floaters["end"]])}
    opacity = {s: np.r_[np.full(len(points[s]) - FLOATERS, 0.9), np.full(FLOATERS, 0.05)]
               for s in points}
    return points, opacity


def sees_everything(model, views):
    """A surface test that passes every point: the part count rests on the voxel tests."""
    return OneView(lambda pts, tol: (np.ones(len(pts), bool), np.ones(len(pts), bool)))


def stage2_runner(tmp_path) -> Runner:
    return Runner(tmp_path, make_config("quick"), quiet=True)


def test_floaters_make_no_part(tmp_path, monkeypatch):
    points, opacity = hazy_door_scene()
    # Every centre, floaters included: the haze moved between the states is a second part.
    everything = coarse_init(points["start"], points["end"],
                             surfaces={s: sees_everything(None, None) for s in points})
    assert everything.num_parts == 3, everything.notes

    monkeypatch.setattr(stage2, "SurfaceTest", sees_everything)
    runner = stage2_runner(tmp_path)
    models = {s: model_of(points[s], opacity[s]) for s in points}
    coarse = vars(stage2.initialise_parts(models, {"start": [], "end": []}, runner.config, runner))
    assert coarse["num_parts"] == 2, coarse["notes"]
    canonical = coarse["canonical"]
    logits = coarse["logits"].numpy()
    assert logits.shape == (len(points[canonical]), 2)
    # The part is the door: most door Gaussians are seeded to it, the body leans static.
    n_door = int(0.3 * 6000)
    n_body = len(points[canonical]) - FLOATERS - n_door
    assert (logits[n_body:n_body + n_door].argmax(1) == 1).mean() > 0.5
    assert (logits[:n_body].argmax(1) == 1).mean() < 0.02
    # A floater's logits are those of its nearest opaque Gaussian.
    pts = points[canonical]
    opaque = pts[:-FLOATERS]
    for i in range(len(pts) - FLOATERS, len(pts), 37):
        nearest = int(np.argmin(np.linalg.norm(opaque - pts[i], axis=1)))
        assert np.array_equal(logits[i], logits[nearest])
    runner.log.close()


def test_an_unbinarised_model_is_passed_whole():
    """A short run whose opacities have not separated (most below the threshold) keeps every
    centre: a few opaque ones would be a sparse, biased sample of the surface."""
    rng = np.random.default_rng(0)
    pts = rng.random((500, 3))
    faint = model_of(pts, np.full(500, 0.2))
    assert stage2_selection({"start": faint, "end": faint})["start"][0].all()
    mixed = model_of(pts, np.r_[np.full(400, 0.9), np.full(100, 0.1)])
    keep, opaque = stage2_selection({"start": mixed, "end": mixed})["end"]
    assert keep[:400].all() and not keep[400:].any() and opaque == 400
    assert STAGE2_MIN_OPACITY == pytest.approx(0.5)


def test_both_states_are_selected_by_one_rule():
    """One state past the opaque fraction and the other not: both keep every centre (stage 2
    reads motion off the difference of the two states, so haze kept in one state and dropped
    in the other would read as moving matter); the opaque counts are each state's own."""
    rng = np.random.default_rng(1)
    pts = rng.random((500, 3))
    binarised = model_of(pts, np.r_[np.full(300, 0.9), np.full(200, 0.1)])  # 60 % opaque
    hazy = model_of(pts, np.r_[np.full(200, 0.9), np.full(300, 0.1)])  # 40 % opaque
    chosen = stage2_selection({"start": hazy, "end": binarised})
    assert chosen["start"][0].all() and chosen["end"][0].all()
    assert (chosen["start"][1], chosen["end"][1]) == (200, 300)
    both = stage2_selection({"start": binarised, "end": binarised})
    assert not both["start"][0][300:].any() and both["start"][0][:300].all()
