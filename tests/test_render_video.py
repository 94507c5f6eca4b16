"""`gear render --video`: the file decodes to the asked frame count, size and rate, and each
frame is the twin at the loop's state and orbit camera (rendered again here, directly)."""

from __future__ import annotations

import imageio.v2 as imageio
import numpy as np
import pytest
import torch

from gear.cli import main
from gear.commands.render import PART_PALETTE, orbit_cameras, up_vector, video_path
from gear.twin import Twin
from twin_outdir import make_out_dir

FPS, SECONDS, SIZE = 10, 1.2, (64, 48)
FRAMES = 12
CODEC_TOL = 6.0  # mean |difference| per channel (of 255) that H.264 at this size stays under


@pytest.fixture(scope="module")
def out_dir(tmp_path_factory):
    return make_out_dir(tmp_path_factory.mktemp("run"))


def _decode(path) -> tuple[np.ndarray, dict]:
    with imageio.get_reader(path, format="FFMPEG") as reader:
        return np.stack([np.asarray(f) for f in reader]), reader.get_meta_data()


def _render(twin: Twin, path_index: int, colors: torch.Tensor | None = None) -> np.ndarray:
    """Frame `path_index` of the loop, rendered directly (the command's framing: the bounds
    over every state it shows)."""
    states, azimuths = video_path(FRAMES)
    sweep = np.linspace(0.0, 1.0, 2)
    center, radius = twin.bounds(sorted(set(sweep.tolist()) | set(states.tolist())))
    cam = orbit_cameras(center, radius, azimuths[path_index:path_index + 1], 25.0,
                        up_vector("z"), *SIZE)[0]
    out = twin.render(float(states[path_index]), cam, torch.ones(3), colors=colors)
    return np.round(np.clip(out.features.numpy(), 0, 1) * 255)


def test_video_path_loops_start_end_start():
    states, azimuths = video_path(8)
    np.testing.assert_allclose(states, [0, 0.25, 0.5, 0.75, 1, 0.75, 0.5, 0.25])
    np.testing.assert_allclose(azimuths, np.arange(8) * 45.0)


def test_video_decodes_to_the_twin_at_each_state(out_dir, tmp_path, capsys):
    video = tmp_path / "clips" / "twin.mp4"
    assert main(["render", str(out_dir), "--video", str(video), "--fps", str(FPS),
                 "--duration", str(SECONDS), "--size", *map(str, SIZE)]) == 0
    assert f"video: {FRAMES} frame(s) at {FPS} fps, 64x48" in capsys.readouterr().out
    assert not (out_dir / "twin_renders").exists()  # only the video was asked for
    frames, meta = _decode(video)
    assert frames.shape == (FRAMES, SIZE[1], SIZE[0], 3)
    assert meta["fps"] == pytest.approx(FPS)
    twin = Twin.load(out_dir)
    for k in (0, FRAMES // 4, FRAMES // 2, FRAMES - 1):
        want = _render(twin, k)
        err = np.abs(frames[k].astype(float) - want).mean()
        assert err < CODEC_TOL, f"frame {k}: mean error {err:.2f}"
        # ... and it is not just any frame: the neighbouring state/view is much farther off.
        other = _render(twin, (k + FRAMES // 2) % FRAMES)
        assert np.abs(frames[k].astype(float) - other).mean() > 3 * err
    assert np.abs(frames[0].astype(float) - frames[FRAMES // 2]).mean() > 10


def test_video_in_part_colours(out_dir, tmp_path):
    video = tmp_path / "parts.mkv"
    assert main(["render", str(out_dir), "--video", str(video), "--fps", "4", "--duration",
                 "0.5", "--size", "32", "32", "--color", "parts", "--t", "0"]) == 0
    frames, _ = _decode(video)
    assert frames.shape == (2, 32, 32, 3)
    assert (out_dir / "twin_renders" / "s0.000" / "000.png").is_file()  # --t still renders
    twin = Twin.load(out_dir)
    colors = torch.as_tensor(PART_PALETTE[twin.parts.numpy()])  # the fixture has 3 parts
    # Frame 0 is the start state; compare against a direct part-colour render at this size.
    _, azimuths = video_path(2)
    center, radius = twin.bounds([0.0, 1.0])
    cam = orbit_cameras(center, radius, azimuths[:1], 25.0, up_vector("z"), 32, 32)[0]
    want = np.round(np.clip(twin.render(0.0, cam, torch.ones(3), colors=colors)
                            .features.numpy(), 0, 1) * 255)
    assert np.abs(frames[0].astype(float) - want).mean() < CODEC_TOL


@pytest.mark.parametrize("argv, message", [
    (["--video", "x.gif"], "must end in one of .mp4, .mkv, .mov"),
    (["--video", "x.mp4", "--size", "63", "48"], "--size: width and height must be even"),
    (["--video", "x.mp4", "--fps", "0"], "--fps must be at least 1"),
    (["--video", "x.mp4", "--fps", "2", "--duration", "0.4"], "fewer than 2 frames"),
])
def test_video_rejects_bad_options(out_dir, tmp_path, capsys, argv, message):
    argv = [a if a != "x.gif" and a != "x.mp4" else str(tmp_path / a) for a in argv]
    assert main(["render", str(out_dir), *argv]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("gear: error:") and message in err and "\n" not in err


def test_video_of_a_twin_with_sh_has_its_view_dependent_colour(tmp_path):
    run = make_out_dir(tmp_path / "run", sh_degree=3)
    video = tmp_path / "sh.mp4"
    assert main(["render", str(run), "--video", str(video), "--fps", str(FPS),
                 "--duration", str(SECONDS), "--size", *map(str, SIZE)]) == 0
    frames, _ = _decode(video)
    twin = Twin.load(run)
    dc_only = Twin.load(run)
    dc_only.sh = None
    for k in (0, FRAMES // 4, 3 * FRAMES // 4):
        err = np.abs(frames[k].astype(float) - _render(twin, k)).mean()
        assert err < CODEC_TOL, f"frame {k}: mean error {err:.2f}"
        # The degree-0 colour alone would be clearly farther from what the video shows.
        assert np.abs(frames[k].astype(float) - _render(dc_only, k)).mean() > 2 * err
