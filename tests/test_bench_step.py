"""`gear bench step`: one iteration of stage 1 and of stage 3's E- and M-steps timed on a run's
own model, split by the profiler. Checked against what each step does (its rasterizer calls),
against a run it did not train on, and for leaving the run untouched."""

from __future__ import annotations

import hashlib

import pytest

from gear.bench.step import markdown_table, phases, time_phase
from gear.cli import main
from gear.config import make_config
from gear.run_folder import RunFolderError
from gear.synth import generate
from gear.train import train

CONFIG = dict(stage1_iterations=40, stage3_iterations=40, em_interval=5, densify_from=5,
              densify_until=30, densify_interval=10, stage3_densify_until=20,
              joint_classify_iteration=20, classify_tune_steps=2, init_max_points=400,
              max_gaussians=800, num_parts=2, mesh_voxel=0.08, mesh_trunc=0.24)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("step")
    scene = generate("fridge", root / "scene", res=24, views=4, test_views=1)
    other = generate("drawer_cabinet", root / "other", res=24, views=4, test_views=1)
    run = root / "run"
    train(scene, run, make_config("quick", CONFIG), quiet=True)
    return scene, other, run


def _digest(folder) -> str:
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            h.update(str(p.relative_to(folder)).encode() + p.read_bytes())
    return h.hexdigest()


def test_each_phase_is_timed_with_the_render_calls_its_step_makes(trained):
    scene, _, run = trained
    before = _digest(run)
    timings = [time_phase(name, stage, it, steps=2, warmup=1)
               for name, stage, it in phases(run, scene)]
    assert [t.phase for t in timings] == ["stage 1", "stage 3, E-step", "stage 3, M-step"]
    stage1, estep, mstep = timings
    assert stage1.raster_calls == 1  # the state's view
    # E-step: the posed view and the anchor (plus the logit image where region masks exist).
    assert estep.raster_calls in (2, 3)
    assert mstep.raster_calls == make_config("quick", CONFIG).m_step_views
    for t in timings:
        assert t.gaussians > 0
        assert 0 < t.raster_forward and 0 < t.raster_backward
        # The profiled parts are inside the iteration: they cannot add up to more than it.
        assert t.raster_forward + t.raster_backward + t.optimizer <= t.wall * 1.001
        assert t.wall > 0 and t.cpu > 0 and t.optimizer > 0
    table = markdown_table(timings)
    assert table.count("\n") == 8 and "| render backward |" in table
    assert _digest(run) == before  # the run is only read


def test_a_scene_the_run_was_not_trained_on_is_refused(trained):
    _, other, run = trained
    with pytest.raises(RunFolderError, match="not the scene"):
        next(phases(run, other))


def test_a_folder_without_a_stage3_checkpoint_is_one_line(trained, tmp_path, capsys):
    scene, _, _ = trained
    assert main(["bench", "step", str(tmp_path), "--scene", str(scene)]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "past stage 2" in err[0]
