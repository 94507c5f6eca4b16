"""`gear bench raster`: the wgpu blend's counting variant through the binding (same images as
the normal kernels, counts that relate to the CPU executor's as documented), and timing a
trained model with --checkpoint (a finished run and a stage-1 checkpoint)."""

from pathlib import Path

import numpy as np
import pytest

from gear import _core, checkpoint
from gear.cli import main
from gear.synth import generate
from splat_scenes import camera, random_scene
from twin_outdir import make_out_dir, toy_gaussians

BACKGROUND = np.array([0.1, 0.3, 0.6], dtype=np.float32)


def forward(render, seed: int) -> tuple[list[np.ndarray], dict]:
    scene = random_scene(3000, 3, seed, 1.0, (-4.0, -2.5))
    cam = camera(70, 53)
    out = render(*[a.detach().numpy() for a in scene.arrays()],
                 cam.world_to_cam.astype(np.float32), (cam.fx, cam.fy, cam.cx, cam.cy),
                 cam.width, cam.height, BACKGROUND, True)
    *images, state = out
    return images, state.stats()


@pytest.mark.parametrize("seed", [1, 2])
def test_counted_wgpu_forward_renders_the_same_and_counts_like_the_cpu_executor(seed):
    plain, plain_stats = forward(_core.rasterize_forward, seed)
    counted, stats = forward(_core.rasterize_forward_counted, seed)
    _, cpu = forward(_core.rasterize_forward_cpu, seed)
    for a, b in zip(plain, counted, strict=True):
        np.testing.assert_array_equal(a, b)
    assert "evaluations" not in plain_stats  # the normal pass counts nothing
    assert stats["pairs"] == plain_stats["pairs"]
    assert cpu["contributions"] > 1000
    assert 0 < stats["contributions"] <= stats["evaluations"]
    # The CPU executor's rule applied to the wgpu walk, and the blended pairs: the same up to
    # pixels where the two executors' f32 arithmetic decides apart (docs/raster-contract.md).
    for wgpu_key, cpu_key in [("row_evaluations", "evaluations"),
                              ("contributions", "contributions")]:
        assert abs(stats[wgpu_key] - cpu[cpu_key]) <= 1e-3 * cpu[cpu_key], (stats, cpu)


@pytest.fixture(scope="module")
def scene_and_runs(tmp_path_factory) -> tuple[Path, Path, Path, Path]:
    root = tmp_path_factory.mktemp("bench_raster")
    scene = generate("fridge", root / "scene", res=24, views=3, test_views=1)
    finished = make_out_dir(root / "finished")
    stage1 = root / "stage1"  # interrupted in stage 1, both states in training
    payload = {"stage": "stage1", "iteration": 7, "models": {},
               "current": {s: checkpoint.gaussians_state(toy_gaussians(s))
                           for s in ("start", "end")},
               "iterations": {"start": 7, "end": 7}}
    checkpoint.save(stage1 / "checkpoints", payload)
    # ...and as a run that trained the states one after the other left it, in the end state
    payload = {"stage": "stage1-end", "iteration": 5, "models": {},
               "current": checkpoint.gaussians_state(toy_gaussians("end"))}
    checkpoint.save(root / "stage1_one_by_one" / "checkpoints", payload)
    stage3 = root / "stage3"  # stage 3 done, outputs not yet written
    payload = {"stage": "stage3-done", "iteration": 9, "models": {},
               "coarse": {"canonical": "start"},
               "refined": {"gaussians": checkpoint.gaussians_state(toy_gaussians("start"))}}
    checkpoint.save(stage3 / "checkpoints", payload)
    return scene, finished, stage1, stage3


def bench_lines(capsys, *argv: str) -> list[str]:
    assert main(["bench", "raster", "--repeats", "1", *argv]) == 0
    return capsys.readouterr().out.splitlines()


def test_checkpoint_runs_time_the_trained_model_from_the_scene_cameras(scene_and_runs, capsys):
    scene, finished, stage1, stage3 = scene_and_runs
    n = len(toy_gaussians().params["means"])
    for run, what, state in [(finished, "finished run", "start"),
                             (stage1, "stage1-end model at iteration 7", "end"),
                             (stage1 / "checkpoints" / checkpoint.LAST, "stage1-end", "end"),
                             (stage1.parent / "stage1_one_by_one",
                              "stage1-end model at iteration 5", "end"),
                             (stage3, "stage-3 model", "start")]:
        lines = bench_lines(capsys, "--checkpoint", str(run), "--scene", str(scene),
                            "--views", "2")
        assert any(what in line and f"{n} Gaussians, state {state}" in line for line in lines)
        rows = [line.split() for line in lines if line.strip().startswith(f"{state}/train/")]
        assert [row[:3] for row in rows] == [[f"{state}/train/{i:04d}", str(n), "24x24"]
                                             for i in range(2)]


@pytest.mark.parametrize(("which", "argv", "expected"), [
    ("finished", [], "--checkpoint needs --scene"),
    ("empty", ["--scene"], "not a run folder"),
])
def test_checkpoint_errors_are_one_line(scene_and_runs, tmp_path, capsys, which, argv, expected):
    scene, finished, *_ = scene_and_runs
    run = finished if which == "finished" else tmp_path
    extra = [str(scene)] if argv else []
    code = main(["bench", "raster", "--checkpoint", str(run), *argv, *extra])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and len(err) == 1 and expected in err[0], err
