"""The articulated twin: loading a trained OUT_DIR, posing at any state, rendering it."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from PIL import Image
from scipy.spatial.transform import Rotation

from gear.cli import main
from gear.commands.render import PART_PALETTE, orbit_cameras
from gear.kinematics import dq_sclerp
from gear.twin import Twin, TwinError, read_ply_vertices
from twin_outdir import (
    COLORS,
    HINGE,
    SLIDE,
    front_camera,
    joint_matrix,
    make_out_dir,
    moved,
    start_points,
)

POS_TOL = 1e-5  # float32 storage of ~0.5-sized coordinates


@pytest.fixture(scope="module")
def out_dir(tmp_path_factory):
    return make_out_dir(tmp_path_factory.mktemp("run"))


@pytest.fixture(scope="module")
def twin(out_dir):
    return Twin.load(out_dir)


def _rot(quats: torch.Tensor) -> np.ndarray:
    q = quats.double().numpy()
    return Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()  # scipy wants (x, y, z, w)


def test_load_reads_what_training_writes(twin):
    points, parts = start_points()
    assert twin.num_parts == 3 and twin.canonical == "start"
    np.testing.assert_array_equal(twin.parts.numpy(), parts)
    np.testing.assert_allclose(twin.means.numpy(), points, atol=1e-6)
    # Colours survive the f_dc encoding within the fixture's jitter.
    assert np.abs(twin.rgb.numpy() - COLORS[parts]).max() < 0.06
    assert [j.type for j in twin.joints] == ["revolute", "prismatic"]
    np.testing.assert_allclose(twin.joints[1].axis, [0.6, 0.8, 0.0])


@pytest.mark.parametrize("s", [0.0, 0.5, 1.0, 0.3])
def test_pose_is_the_joint_motion_fraction(twin, s):
    means, quats = twin.pose(s)
    parts = twin.parts.numpy()
    want = moved(twin.means.double().numpy(), parts, s)
    np.testing.assert_allclose(means.numpy(), want, atol=POS_TOL)
    # Each Gaussian's orientation turns with its part: R' = R_joint R.
    before, after = _rot(twin.quats), _rot(quats)
    for k, joint in ((0, None), (1, HINGE), (2, SLIDE)):
        r = np.eye(3) if joint is None else joint_matrix(joint, s)[:3, :3]
        np.testing.assert_allclose(after[parts == k], r @ before[parts == k], atol=1e-5)


def test_start_leaves_gaussians_in_place_and_half_is_half(twin):
    means0, quats0 = twin.pose(0.0)
    np.testing.assert_allclose(means0.numpy(), twin.means.numpy(), atol=1e-7)
    np.testing.assert_allclose(_rot(quats0), _rot(twin.quats), atol=1e-6)
    door = twin.parts == 1
    # At s = 0.5 a door point has turned by exactly 35 degrees about the hinge line.
    origin, axis = np.array(HINGE["origin"]), np.array(HINGE["axis"])
    p0 = twin.means[door].double().numpy() - origin
    p_half = twin.pose(0.5)[0][door].double().numpy() - origin
    flat0, flat1 = p0 - np.outer(p0 @ axis, axis), p_half - np.outer(p_half @ axis, axis)
    off_axis = np.linalg.norm(flat0, axis=1) > 1e-3  # points on the hinge line do not turn
    flat0, flat1 = flat0[off_axis], flat1[off_axis]
    np.testing.assert_allclose(np.linalg.norm(flat1, axis=1), np.linalg.norm(flat0, axis=1),
                               atol=POS_TOL)
    angle = np.degrees(np.arctan2(np.cross(flat0, flat1) @ axis, (flat0 * flat1).sum(1)))
    np.testing.assert_allclose(angle, 35.0, atol=1e-3)
    drawer = twin.parts == 2
    travel = (twin.pose(0.5)[0] - twin.means)[drawer].double().numpy()
    np.testing.assert_allclose(travel, np.tile(0.1 * np.array(SLIDE["axis"]), (int(drawer.sum()),
                                                                                1)), atol=POS_TOL)


@pytest.mark.parametrize("s", [0.25, 0.5, 0.8])
def test_intermediate_states_match_training_screw_interpolation(twin, s):
    # Training interpolates a part's motion with kinematics.dq_sclerp; the twin's states
    # must be the same motions (angles below 180 degrees).
    qr1, qd1 = twin.part_motions(1.0)
    qr_s, qd_s = twin.part_motions(s)
    want_r, want_d = dq_sclerp(qr1, qd1, s)
    sign = torch.sign((want_r * qr_s).sum(-1, keepdim=True))  # q and -q are the same motion
    torch.testing.assert_close(qr_s, sign * want_r, atol=1e-12, rtol=0)
    torch.testing.assert_close(qd_s, sign * want_d, atol=1e-12, rtol=0)


def test_canonical_end_is_posed_back_to_start(tmp_path, twin):
    end_twin = Twin.load(make_out_dir(tmp_path / "end", canonical="end"))
    assert end_twin.canonical == "end"
    np.testing.assert_allclose(end_twin.pose(1.0)[0].numpy(), end_twin.means.numpy(), atol=1e-7)
    for s in (0.0, 0.4):
        np.testing.assert_allclose(end_twin.pose(s)[0].numpy(), twin.pose(s)[0].numpy(),
                                   atol=POS_TOL)


def test_states_outside_the_motion_are_refused(twin):
    for s in (-0.1, 1.5, float("nan")):
        with pytest.raises(ValueError, match="state s must be in"):
            twin.pose(s)


def test_ascii_ply_with_standard_layout(tmp_path):
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
             "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    rows = [[0.1 * i, 0.2, -0.3, 0, 0, 0, 1.0, 0.0, -1.0, 2.0, -3, -3, -3, 1, 0, 0, 0]
            for i in range(3)]
    text = "ply\nformat ascii 1.0\nelement vertex 3\n"
    text += "".join(f"property float {n}\n" for n in names) + "property uchar part\nend_header\n"
    text += "".join(" ".join(str(v) for v in r) + f" {i % 2}\n" for i, r in enumerate(rows))
    path = tmp_path / "g.ply"
    path.write_text(text)
    props = read_ply_vertices(path)
    np.testing.assert_allclose(props["x"], [0.0, 0.1, 0.2], atol=1e-7)
    np.testing.assert_array_equal(props["part"], [0, 1, 0])
    assert props["part"].dtype == np.uint8


def _broken(out_dir, tmp_path, edit):
    """A copy of the fabricated OUT_DIR with one file edited by `edit(folder)`."""
    import shutil

    copy = tmp_path / "broken"
    shutil.copytree(out_dir, copy)
    edit(copy)
    return copy


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda d: (d / "joints.json").unlink(), r"joints\.json: missing"),
        (lambda d: (d / "joints.json").write_text("{not json"), r"joints\.json: not valid JSON"),
        (lambda d: (d / "joints.json").write_text(json.dumps(
            {"canonical": "start", "joints": [{**HINGE, "axis": [0, 0, 0]}, SLIDE]})),
         r"joints\.json: joints\[0\]: axis is the zero vector"),
        (lambda d: (d / "joints.json").write_text(json.dumps(
            {"canonical": "start", "joints": [{**HINGE, "angle_deg": None}, SLIDE]})),
         r"joints\[0\]: angle_deg must be a finite number"),
        (lambda d: (d / "joints.json").write_text(json.dumps(
            {"canonical": "start", "joints": [HINGE, {**SLIDE, "origin": None}]})),
         r"joints\[1\] origin: expected 3 finite numbers"),
        (lambda d: (d / "joints.json").write_text(json.dumps(
            {"canonical": "middle", "joints": []})), r"canonical must be 'start' or 'end'"),
        (lambda d: (d / "gaussians_canonical.ply").unlink(), r"gaussians_canonical\.ply: missing"),
        (lambda d: (d / "gaussians_canonical.ply").write_bytes(
            (d / "gaussians_canonical.ply").read_bytes()[:-40]), r"ply: truncated"),
        (lambda d: (d / "gaussians_canonical.ply").write_bytes(b"PK\x03\x04 zip"),
         r"ply: not a PLY file"),
        (lambda d: np.save(d / "parts.npy", np.zeros(5, np.int64)),
         r"parts\.npy: expected \d+ part ids"),
        (lambda d: np.save(d / "parts.npy", np.roll(np.load(d / "parts.npy"), 1)),
         r"parts\.npy disagree"),
        (lambda d: (d / "joints.json").write_text(json.dumps(
            {"canonical": "start", "joints": [HINGE]})), r"part ids must be in 0\.\.1"),
    ],
)
def test_broken_out_dir_names_the_file(out_dir, tmp_path, edit, message):
    with pytest.raises(TwinError, match=message):
        Twin.load(_broken(out_dir, tmp_path, edit))


def test_nonfinite_gaussian_is_reported(out_dir, tmp_path):
    def poison(d):
        path = d / "gaussians_canonical.ply"
        raw = bytearray(path.read_bytes())
        body = raw.index(b"end_header\n") + len(b"end_header\n")
        raw[body:body + 4] = np.float32(np.nan).tobytes()  # x of vertex 0
        path.write_bytes(bytes(raw))

    with pytest.raises(TwinError, match=r"1 Gaussian\(s\) with non-finite values"):
        Twin.load(_broken(out_dir, tmp_path, poison))


def _red_centroid(rgb: np.ndarray) -> np.ndarray:
    red = (rgb[..., 0] > 0.5) & (rgb[..., 1] < 0.4) & (rgb[..., 2] < 0.4)
    assert red.sum() > 10, "the door is not visible"
    rows, cols = np.nonzero(red)
    return np.array([cols.mean() + 0.5, rows.mean() + 0.5])


def test_render_moves_the_door_pixels(twin):
    cam = front_camera(48)
    images = {s: twin.render(s, cam).features.numpy() for s in (0.0, 1.0)}
    assert twin.render(0.5, cam, depth=True).depth is not None
    for img in images.values():
        assert np.all(np.isfinite(img))
    # The door's red pixels follow the door: their centroid lands near the projection of the
    # door's moved centre (tolerance: a few pixels, occlusion by the body shifts centroids).
    door = twin.parts == 1
    for s, img in images.items():
        centre = twin.pose(s)[0][door].double().numpy().mean(0)
        uv, _ = cam.project(centre[None])
        assert np.linalg.norm(_red_centroid(img) - uv[0]) < 4.0
    shift = np.linalg.norm(_red_centroid(images[1.0]) - _red_centroid(images[0.0]))
    assert shift > 5.0
    # The static body's blue pixels far from the door and drawer do not change.
    blue0 = images[0.0][..., 2] > 0.6
    blue1 = images[1.0][..., 2] > 0.6
    assert (blue0 & blue1).sum() > 0.8 * blue0.sum()


def test_render_command_writes_states_and_animation(out_dir, tmp_path):
    dest = tmp_path / "renders"
    code = main(["render", str(out_dir), "--t", "0", "1", "--views", "2", "--res", "32",
                 "--frames", "3", "--out", str(dest)])
    assert code == 0
    start = [np.asarray(Image.open(dest / "s0.000" / f"{v:03d}.png")) for v in range(2)]
    end = [np.asarray(Image.open(dest / "s1.000" / f"{v:03d}.png")) for v in range(2)]
    assert start[0].shape == (32, 32, 3)
    # Something moved in every view, and the white background is there.
    assert all(np.abs(a.astype(int) - b).max() > 50 for a, b in zip(start, end, strict=True))
    assert (start[0] == 255).all(axis=-1).sum() > 50
    strip = Image.open(dest / "animation" / "strip.png")
    assert strip.size == (96, 32)
    assert Image.open(dest / "animation" / "animation.gif").n_frames == 3


def test_part_colours_and_framing(out_dir, tmp_path, twin):
    dest = tmp_path / "parts"
    assert main(["render", str(out_dir), "--t", "1", "--views", "3", "--res", "40", "--color",
                 "parts", "--background", "0", "0", "0", "--out", str(dest)]) == 0
    pixels = np.concatenate([
        np.asarray(Image.open(dest / "s1.000" / f"{v:03d}.png")).reshape(-1, 3) / 255.0
        for v in range(3)])
    # Where one part covers a pixel fully, the pixel is that part's palette colour; every part
    # shows up in some view, and (nearly) every covered pixel is one of the three colours.
    covered = pixels[pixels.max(-1) > 0.55]
    near = np.stack([np.abs(covered - c).max(-1) < 0.06 for c in PART_PALETTE[:3]])
    assert np.all(near.sum(1) > 10)
    assert near.any(0).mean() > 0.8
    # The orbit frames the whole object at every state: every Gaussian projects into the image.
    center, radius = twin.bounds([0.0, 1.0])
    for cam in orbit_cameras(center, radius, np.array([0.0, 120.0, 240.0]), 25.0,
                             np.array([0.0, 0.0, 1.0]), 40):
        for s in (0.0, 1.0):
            uv, z = cam.project(twin.pose(s)[0].double().numpy())
            assert np.all(z > 0) and np.all((uv > 0) & (uv < 40))


def test_render_command_rejects_bad_state(out_dir, capsys):
    assert main(["render", str(out_dir), "--t", "1.2"]) == 1
    assert "--t: states must be in [0, 1]" in capsys.readouterr().err
