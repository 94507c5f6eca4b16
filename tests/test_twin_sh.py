"""A twin with spherical-harmonic colour: what training writes (`f_rest_*`) is what the twin
loads, renders, poses and exports; a twin without it is unchanged; a bad band count is refused."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image
from scipy.spatial.transform import Rotation

from gear.cli import main
from gear.commands.render import ELEVATION_DEG, orbit_cameras, up_vector
from gear.export.bundle import export_twin
from gear.sh import SH_C0, sh_to_rgb
from gear.sh_rotation import rotate_sh
from gear.splats import render
from gear.splats.rendering import rasterizer
from gear.splats.sh import SH_PARAM, view_rgb
from gear.twin import PLY_NAME, Twin, TwinError, read_ply_vertices
from gear.view.scene import part_splats
from twin_outdir import front_camera, make_out_dir, toy_gaussians

# Twin vs training render: the DC colour goes through float32 f_dc = (rgb - 0.5) / SH_C0 and
# back (~1e-7 per colour), everything else is the same op on the same numbers.
RENDER_TOL = 1e-5
# SH turned by least squares in float64, then stored as float32.
ROTATED_TOL = 1e-5


@pytest.fixture(scope="module")
def sh_run(tmp_path_factory):
    return make_out_dir(tmp_path_factory.mktemp("sh_run"), sh_degree=3)


def test_a_degree_3_twin_reloads_with_the_coefficients_training_wrote(sh_run):
    g = toy_gaussians(sh_degree=3)
    twin = Twin.load(sh_run)
    assert twin.sh_degree == 3 and twin.sh.shape == (len(g), 15, 3)
    assert torch.equal(twin.sh, g.params[SH_PARAM].detach())


@pytest.mark.parametrize("s", [0.0, 0.6, 1.0])
def test_a_degree_3_twin_renders_as_training_does(sh_run, s):
    g, twin, cam = toy_gaussians(sh_degree=3), Twin.load(sh_run), front_camera()
    pose = twin.pose(s)
    with torch.no_grad():
        want = render(g, cam, pose=pose).features  # the training-time render of this pose
    got = twin.render(s, cam).features
    np.testing.assert_allclose(got.numpy(), want.numpy(), atol=RENDER_TOL)
    # The bands matter: the same twin without them (DC colour only) looks clearly different.
    twin.sh = None
    assert float((twin.render(s, cam).features - got).abs().max()) > 0.05


def test_a_twin_without_f_rest_renders_exactly_as_before(tmp_path):
    twin = Twin.load(make_out_dir(tmp_path / "run"))
    assert twin.sh is None and "f_rest_0" not in read_ply_vertices(tmp_path / "run" / PLY_NAME)
    cam = front_camera()
    means, quats = twin.pose(1.0)
    dc_only = rasterizer()(means, quats, twin.log_scales, twin.opacity, twin.rgb, cam,
                           background=torch.zeros(3))
    assert torch.equal(twin.render(1.0, cam).features, dc_only.features)


def test_posed_bands_give_the_colour_of_the_canonical_frame(tmp_path):
    twin = Twin.load(make_out_dir(tmp_path / "run", canonical="end", sh_degree=3))
    cam = front_camera()
    means, quats = twin.pose(0.0)  # every movable part moved away from its canonical pose
    want = view_rgb(twin, twin.rgb, cam, means, quats, twin.quats)
    dc = ((twin.rgb - 0.5) / SH_C0)[:, None, :]
    dirs = (torch.as_tensor(cam.center, dtype=torch.float32) - means).contiguous()
    got = sh_to_rgb(dirs, torch.cat([dc, twin.posed_sh(0.0)], dim=1))
    np.testing.assert_allclose(got.numpy(), want.numpy(), atol=ROTATED_TOL)
    assert torch.equal(twin.posed_sh(1.0), twin.sh)  # the canonical state needs no turning


def test_rotation_of_bands_is_exact_and_composes():
    rng = np.random.default_rng(0)
    rest = torch.tensor(rng.normal(size=(20, 15, 3)))
    a, b = (torch.tensor(Rotation.random(random_state=k).as_matrix()) for k in (1, 2))
    np.testing.assert_allclose(rotate_sh(rotate_sh(rest, a), b), rotate_sh(rest, b @ a),
                               atol=1e-12)
    np.testing.assert_allclose(rotate_sh(rest, torch.eye(3, dtype=torch.float64)), rest,
                               atol=1e-12)


def test_part_plys_keep_the_bands_turned_to_the_start_state(tmp_path):
    run = make_out_dir(tmp_path / "run", canonical="end", sh_degree=2)
    export_twin(run, tmp_path / "u", quiet=True)
    twin = Twin.load(run)
    want = twin.posed_sh(0.0)[twin.parts == 1]  # the door, turned back by its 70 degrees
    props = read_ply_vertices(tmp_path / "u" / "splats" / "start" / "part_0.ply")
    got = np.stack([props[f"f_rest_{i}"] for i in range(24)], 1).reshape(-1, 3, 8)
    np.testing.assert_allclose(got.transpose(0, 2, 1), want.numpy(), atol=1e-6)


def test_a_bad_f_rest_count_is_a_one_line_error(tmp_path, capsys):
    run = make_out_dir(tmp_path / "run", sh_degree=1)
    ply = run / PLY_NAME
    raw = ply.read_bytes()
    # Rename the last band (f_rest_8) so 8 remain: no degree has 8 / 3 coefficients a channel.
    ply.write_bytes(raw.replace(b"property float f_rest_8\n", b"property float extra_8\n", 1))
    with pytest.raises(TwinError, match=r"8 f_rest_\* properties, expected .*9, 24, 45"):
        Twin.load(run)
    assert main(["render", str(run), "--views", "1", "--res", "16"]) == 1
    err = capsys.readouterr().err.strip()
    assert "8 f_rest_* properties" in err and len(err.splitlines()) == 1


def test_render_command_images_show_the_view_dependent_colour(sh_run, tmp_path):
    dest = tmp_path / "renders"
    assert main(["render", str(sh_run), "--t", "0.5", "--views", "2", "--res", "32",
                 "--background", "0", "0", "0", "--out", str(dest)]) == 0
    twin = Twin.load(sh_run)
    center, radius = twin.bounds([0.0, 0.5, 1.0])  # the command frames every state it shows
    cams = orbit_cameras(center, radius, np.array([0.0, 180.0]), ELEVATION_DEG,
                         up_vector("z"), 32)
    for v, cam in enumerate(cams):
        got = np.asarray(Image.open(dest / "s0.500" / f"{v:03d}.png")).astype(float)
        want = np.round(np.clip(twin.render(0.5, cam).features.numpy(), 0, 1) * 255)
        assert np.abs(got - want).max() <= 1.0  # uint8 rounding


def test_the_viewer_shows_the_degree_0_colour_of_an_sh_twin(sh_run):
    twin = Twin.load(sh_run)
    shown = np.concatenate([p.rgb for p in part_splats(twin)])
    order = np.argsort(twin.parts.numpy(), kind="stable")  # part_splats groups by part
    np.testing.assert_array_equal(shown, twin.rgb.numpy()[order])
