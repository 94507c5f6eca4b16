"""`gear view`: the scene arrays, the viewer's controls, the command, and the page in a browser.

The browser test does what a person does: opens the page in headless Chromium, looks at it
(screenshot), moves the door's slider with the keyboard, and looks again. Where the door must be
on screen is computed independently, by projecting the fixture's reference door points through
the camera the page reports back to the server.
"""

from __future__ import annotations

import io
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request

import numpy as np
import pytest
import torch
from PIL import Image
from scipy.spatial.transform import Rotation

from gear.cli import main
from gear.commands.render import PART_PALETTE
from gear.twin import Twin
from gear.view.scene import axis_segment, covariances, part_meshes, part_pose, part_splats
from gear.view.server import TwinViewer, port_is_free
from twin_outdir import HINGE, SLIDE, make_out_dir, moved, start_points

POS_TOL = 1e-5  # float32 storage of ~0.5-sized coordinates
CHROMIUM = shutil.which("chromium")
CHROMEDRIVER = shutil.which("chromedriver")


@pytest.fixture(scope="module", params=["start", "end"])
def out_dir(request, tmp_path_factory):
    return make_out_dir(tmp_path_factory.mktemp(f"run_{request.param}"), request.param)


@pytest.fixture(scope="module")
def twin(out_dir):
    return Twin.load(out_dir)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _apply(wxyz: np.ndarray, position: np.ndarray, points: np.ndarray) -> np.ndarray:
    rot = Rotation.from_quat(np.asarray(wxyz)[[1, 2, 3, 0]]).as_matrix()  # scipy: x, y, z, w
    return points @ rot.T + position


# ---------------------------------------------------------------- scene arrays


def test_part_splats_are_the_start_state(twin):
    points, parts = start_points()
    splats = part_splats(twin)
    assert [p.part for p in splats] == [0, 1, 2]
    for p in splats:
        np.testing.assert_allclose(p.centers, points[parts == p.part], atol=POS_TOL)
        np.testing.assert_allclose(p.rgb, twin.rgb.numpy()[parts == p.part])
        np.testing.assert_allclose(p.part_rgb, np.broadcast_to(PART_PALETTE[p.part],
                                                               p.centers.shape))
        np.testing.assert_allclose(p.opacities[:, 0], 1 / (1 + np.exp(-4.0)), rtol=1e-6)


@pytest.mark.parametrize("fraction", [0.0, 0.3, 1.0])
def test_part_pose_moves_parts_as_the_reference_motion(twin, fraction):
    """The scene-node transform of each part = the fixture's Rodrigues motion (scipy)."""
    points, parts = start_points()
    expected = moved(points, parts, fraction)
    for joint in twin.joints:
        wxyz, position = part_pose(joint, fraction)
        sel = parts == joint.part
        np.testing.assert_allclose(_apply(wxyz, position, points[sel]), expected[sel],
                                   atol=POS_TOL)


def test_covariances_from_quaternion_and_scales():
    rng = np.random.default_rng(1)
    quats = rng.normal(size=(6, 4)) * 3.0  # not normalised: the rasterizer normalises too
    log_scales = rng.normal(size=(6, 3))
    got = covariances(torch.tensor(quats), torch.tensor(log_scales)).numpy()
    rot = Rotation.from_quat(quats[:, [1, 2, 3, 0]]).as_matrix()
    want = np.einsum("nij,nj,nkj->nik", rot, np.exp(2 * log_scales), rot)
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-12)


def test_axis_segments(twin):
    center, radius = np.array([0.1, 0.0, 0.0]), 0.5
    hinge = axis_segment(twin.joints[0], np.zeros(3), center, radius)
    # On the hinge line (vertical through x=0.25, y=-0.25), centred level with the object.
    np.testing.assert_allclose(hinge[:, :2], [[0.25, -0.25]] * 2, atol=1e-12)
    np.testing.assert_allclose(hinge[:, 2], [-0.4, 0.4], atol=1e-12)
    start = np.array([0.0, 0.0, -0.3])
    slide = axis_segment(twin.joints[1], start, center, radius)
    # From the drawer's centre along its travel (0.2: longer than the 0.3-radius minimum).
    np.testing.assert_allclose(slide, [start, start + 0.2 * np.array(SLIDE["axis"])],
                               atol=1e-12)


def test_part_meshes_by_part_id(out_dir, tmp_path):
    meshes = part_meshes(out_dir, 3)
    assert sorted(meshes) == [0, 1, 2]
    # The hinge-side door mesh is the door box (part 1), not the drawer.
    assert meshes[1].bounds[0][2] == pytest.approx(0.1)
    assert part_meshes(tmp_path, 3) == {}


# ---------------------------------------------------------------- the viewer's controls


@pytest.fixture()
def viewer(twin, out_dir):
    v = TwinViewer(twin, out_dir, port=free_port())
    yield v
    v.stop()


def _node_points(viewer: TwinViewer, part: int) -> np.ndarray:
    node = viewer.part_nodes[part]
    return _apply(node.wxyz, node.position, viewer.splats[part].centers)


@pytest.mark.parametrize("s", [1.0, 0.5])
def test_state_slider_poses_parts_as_twin_pose(viewer, twin, s):
    viewer.state_slider.value = s
    assert [sl.value for sl in viewer.joint_sliders] == pytest.approx(
        [s * HINGE["angle_deg"], s * SLIDE["distance"]])
    means = twin.pose(s)[0].numpy()
    for k in range(twin.num_parts):
        np.testing.assert_allclose(_node_points(viewer, k), means[twin.parts.numpy() == k],
                                   atol=POS_TOL)


def test_joint_slider_moves_only_its_part(viewer):
    before = {k: _node_points(viewer, k) for k in (0, 1, 2)}
    viewer.joint_sliders[1].value = 0.1  # the drawer half way
    points, parts = start_points()
    np.testing.assert_allclose(_node_points(viewer, 2), moved(points, parts, 0.5)[parts == 2],
                               atol=POS_TOL)
    for k in (0, 1):
        np.testing.assert_array_equal(_node_points(viewer, k), before[k])


def test_colour_toggle_and_visibility(viewer):
    door = viewer.splat_handles[1]
    assert np.all(door.rgbs[:, 0] > 200)  # the trained red door
    viewer.color_mode.value = "parts"
    # viser stores 8-bit colours (truncated): within one step of the palette colour.
    assert np.abs(door.rgbs.astype(float) - PART_PALETTE[1] * 255).max() <= 1.0
    viewer.color_mode.value = "rgb"
    assert np.all(door.rgbs[:, 0] > 200)
    assert not any(h.visible for h in viewer.mesh_handles.values())
    viewer.show_meshes.value = True
    viewer.show_gaussians.value = False
    assert all(h.visible for h in viewer.mesh_handles.values()) and len(viewer.mesh_handles) == 3
    assert not any(h.visible for h in viewer.splat_handles.values())


# ---------------------------------------------------------------- the command


def test_view_refuses_a_bad_run_folder(tmp_path, capsys):
    assert main(["view", str(tmp_path / "nope")]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("gear: error:") and "no such output folder" in err and "\n" not in err


def test_view_refuses_a_busy_port(out_dir, capsys):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        assert not port_is_free("127.0.0.1", port)
        assert main(["view", str(out_dir), "--port", str(port)]) == 1
    err = capsys.readouterr().err.strip()
    assert err == (f"gear: error: port {port} on 127.0.0.1 is busy (another server?): pass a "
                   "free one with --port")


def test_view_refuses_an_unknown_host(out_dir, capsys):
    assert main(["view", str(out_dir), "--host", "192.0.2.1", "--port", str(free_port())]) == 1
    assert capsys.readouterr().err.strip() == (
        "gear: error: --host 192.0.2.1: not an address of this machine")


def _sigint_as_in_a_terminal() -> None:
    """A shell that starts the test suite in the background makes its children ignore SIGINT,
    and Python keeps an ignored SIGINT ignored: give the viewer a terminal's default."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_view_command_prints_the_url_and_stops_on_ctrl_c(out_dir):
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "gear", "view", str(out_dir), "--port",
                             str(port)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, preexec_fn=_sigint_as_in_a_terminal)
    try:
        line = proc.stdout.readline()
        assert f"http://127.0.0.1:{port}" in line and "Ctrl-C" in line
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=30) as page:
            assert page.status == 200 and b"<html" in page.read().lower()
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    assert out.strip() == "gear view: stopped"
    assert "Traceback" not in err
    assert port_is_free("127.0.0.1", port)


# ---------------------------------------------------------------- in the browser

WINDOW = (1200, 800)
DIFF = 60  # a pixel "changed" when a channel moved by more than this (of 255)


def _browser():
    webdriver = pytest.importorskip("selenium.webdriver", reason="selenium not installed")
    from selenium.webdriver.chrome.service import Service

    if CHROMIUM is None or CHROMEDRIVER is None:
        pytest.skip("no headless browser: install Debian's chromium and chromium-driver "
                    "(scripts/setup.sh does)")
    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage",
                f"--window-size={WINDOW[0]},{WINDOW[1]}",
                # Software WebGL (SwiftShader): no GPU here.
                "--use-angle=swiftshader", "--enable-unsafe-swiftshader"):
        options.add_argument(arg)
    return webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)


def _screenshot(driver) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(driver.get_screenshot_as_png())).convert("RGB"),
                      dtype=np.int16)


def _overlay_mask(driver, shape: tuple[int, ...]) -> np.ndarray:
    """True where the page draws controls or notices over the 3D view (the slider itself
    changes when it moves, so it must not count as the object changing)."""
    rects = driver.execute_script(
        "return [...document.querySelectorAll('.mantine-Paper-root, .mantine-Notification-root')]"
        ".map(e => { const r = e.getBoundingClientRect(); return [r.left, r.top, r.right,"
        " r.bottom]; });")
    mask = np.zeros(shape[:2], dtype=bool)
    for left, top, right, bottom in rects:
        mask[max(int(top), 0):int(np.ceil(bottom)), max(int(left), 0):int(np.ceil(right))] = True
    return mask


def _project(camera, points: np.ndarray, width: int, height: int) -> np.ndarray:
    """[N,2] pixel (x, y) of world points through the page's camera (viser reports it in the
    OpenCV convention: +z forward, +y down; fov is vertical)."""
    rot = Rotation.from_quat(np.asarray(camera.wxyz)[[1, 2, 3, 0]]).as_matrix()
    local = (points - camera.position) @ rot  # R^T (p - t)
    focal = 0.5 * height / np.tan(0.5 * camera.fov)
    return np.stack([focal * local[:, 0] / local[:, 2] + width / 2,
                     focal * local[:, 1] / local[:, 2] + height / 2], axis=1)


def _box(pixels: np.ndarray, pad: float) -> tuple[float, float, float, float]:
    return (*(pixels.min(axis=0) - pad), *(pixels.max(axis=0) + pad))


def _inside(box: tuple[float, float, float, float], shape: tuple[int, ...]) -> np.ndarray:
    ys, xs = np.mgrid[: shape[0], : shape[1]]
    return (xs >= box[0]) & (xs <= box[2]) & (ys >= box[1]) & (ys <= box[3])


def _wait_for(condition, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = condition()
        if value is not None and value is not False:
            return value
        time.sleep(0.5)
    pytest.fail(f"timed out after {timeout:.0f} s waiting for {what}")


def _steady_screenshot(driver, timeout: float) -> np.ndarray:
    """A screenshot once two in a row agree (splats are sorted and drawn asynchronously)."""
    last = [_screenshot(driver)]

    def settled() -> np.ndarray | None:
        shot = _screenshot(driver)
        same = np.abs(shot - last[0]).max() <= 2
        last[0] = shot
        return shot if same else None

    return _wait_for(settled, timeout, "the page to stop changing")


def _changed(before: np.ndarray, after: np.ndarray, mask: np.ndarray) -> np.ndarray:
    return (np.abs(after - before).max(axis=-1) > DIFF) & ~mask


def _red(image: np.ndarray) -> np.ndarray:
    return (image[..., 0] > 150) & (image[..., 1] < 110) & (image[..., 2] < 110)


def test_browser_shows_the_twin_and_the_door_slider_moves_it(tmp_path):
    driver = _browser()
    out_dir = make_out_dir(tmp_path / "run")
    viewer = TwinViewer(Twin.load(out_dir), out_dir, port=free_port())
    viewer.show_axes.value = False  # the door's axis is drawn red like the door: keep it apart
    try:
        driver.get(viewer.url)
        client = _wait_for(lambda: next(iter(viewer.server.get_clients().values()), None), 60,
                           "the page to connect")
        camera = client.camera
        # The page reports its camera once it has applied the viewer's initial one.
        _wait_for(lambda: camera.image_width > 0 and np.allclose(
            camera.position, viewer.server.initial_camera.position, atol=1e-4), 60,
            "the page to take the viewer's initial camera")
        width, height = camera.image_width, camera.image_height
        points, parts = start_points()
        pad = 3 * 0.04 * 0.5 * height / np.tan(0.5 * camera.fov) / np.linalg.norm(
            points - camera.position, axis=1).min()  # 3 sigma of the nearest Gaussian
        whole = _box(_project(camera, points, width, height), pad)
        door = parts == 1
        door_start = _box(_project(camera, points[door], width, height), pad)
        door_end = _box(_project(camera, moved(points, parts, 1.0)[door], width, height), pad)

        def object_drawn() -> np.ndarray | None:
            shot = _screenshot(driver)
            inside = _inside(whole, shot.shape) & ~_overlay_mask(driver, shot.shape)
            drawn = (np.abs(shot - 255).max(axis=-1) > DIFF) & inside
            return shot if drawn.sum() > 0.15 * inside.sum() else None

        _wait_for(object_drawn, 120, "the twin to appear on the page")
        before = _steady_screenshot(driver, 60)
        Image.fromarray(before.astype(np.uint8)).save(tmp_path / "before.png")
        assert before.shape[:2] == (height, width)
        mask = _overlay_mask(driver, before.shape)
        # Not blank: the object's red door, blue body and green drawer are all on screen.
        inside = _inside(whole, before.shape) & ~mask
        for channel in range(3):
            others = [c for c in range(3) if c != channel]
            hue = (before[..., channel] > 150) & (before[..., others].max(axis=-1) < 110)
            assert (hue & inside).sum() > 200, f"colour channel {channel} missing"
        red = _red(before) & ~mask
        assert red[_inside(door_start, before.shape)].sum() > 0.95 * red.sum()
        ys, xs = np.nonzero(red)
        assert door_start[0] <= xs.mean() <= door_start[2]
        assert door_start[1] <= ys.mean() <= door_start[3]

        # Move the door's slider as a person would: focus its thumb, press End (= its maximum).
        from selenium.webdriver.common.action_chains import ActionChains
        from selenium.webdriver.common.keys import Keys

        thumbs = driver.find_elements("css selector", ".mantine-Slider-thumb")
        assert len(thumbs) == 3  # state, joint 0 (door), joint 1 (drawer)
        driver.execute_script("arguments[0].focus()", thumbs[1])
        ActionChains(driver).send_keys(Keys.END).perform()
        _wait_for(lambda: viewer.joint_sliders[0].value == HINGE["angle_deg"], 30,
                  "the door slider's value to reach the server")
        _wait_for(lambda: _changed(before, _screenshot(driver), mask).sum() > 300, 60,
                  "the door to move on the page")
        after = _steady_screenshot(driver, 60)
        Image.fromarray(after.astype(np.uint8)).save(tmp_path / "after.png")
        mask |= _overlay_mask(driver, after.shape)
        changed = _changed(before, after, mask)
        where_door = _inside(door_start, after.shape) | _inside(door_end, after.shape)
        assert changed.sum() > 300
        assert changed[where_door].sum() > 0.95 * changed.sum(), "pixels changed off the door"
        ys, xs = np.nonzero(_red(after) & ~mask)
        assert door_end[0] <= xs.mean() <= door_end[2]
        assert door_end[1] <= ys.mean() <= door_end[3]
    finally:
        driver.quit()
        viewer.stop()
