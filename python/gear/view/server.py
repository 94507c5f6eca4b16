"""The viser scene of a twin and its controls.

Each part is a scene node `/part_<k>` holding its Gaussians (and, when the run has them, its
TSDF mesh) in the start state; a joint slider only sets that node's rigid transform, so moving
a joint sends one small message, never the Gaussians again. The "state" slider sets every joint
to the same fraction of its motion, exactly the interpolation `gear render` uses.
"""

from __future__ import annotations

import contextlib
import errno
import io
import socket
from collections.abc import Iterable
from pathlib import Path

import numpy as np
import viser

from gear.commands.render import ELEVATION_DEG, fit_distance, orbit_direction, part_colors
from gear.twin import Twin, TwinJoint
from gear.view.scene import (
    PartSplats,
    axis_segment,
    joint_fraction,
    part_meshes,
    part_pose,
    part_splats,
)

COLOR_MODES = ("rgb", "parts")  # the same names as `gear render --color`
SLIDER_STEPS = 200  # resolution of a joint slider between its start and end value
AXIS_THICKNESS = 0.01  # of the object's radius
START_AZIMUTH_DEG = -135.0  # first view: obliquely from between +x and -y (for z up)


def port_is_free(host: str, port: int) -> bool:
    """Whether a server could listen on host:port now (viser itself would silently move to the
    next free port, leaving the printed URL wrong). SO_REUSEADDR as the server sets it: a port
    whose last connections linger in TIME_WAIT is free, one with a listener is not. An address
    that names no interface of this machine is a ValueError."""
    try:
        family, kind, _, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
    except socket.gaierror:
        raise ValueError(f"--host {host}: not an address of this machine") from None
    with socket.socket(family, kind) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind(address)
        except OSError as err:
            if err.errno == errno.EADDRNOTAVAIL:
                raise ValueError(f"--host {host}: not an address of this machine") from None
            return False
    return True


def joint_label(index: int, joint: TwinJoint) -> str:
    """Slider label: the joint's index in joints.json, its type and the slider's unit."""
    return f"joint {index}: " + ("angle °" if joint.type == "revolute" else "travel")


class TwinViewer:
    """A running viser server showing `twin`. Its handles (sliders, checkboxes, part nodes) are
    public: a script or a test drives the same controls a person drags in the page."""

    def __init__(self, twin: Twin, out_dir: Path, host: str = "127.0.0.1", port: int = 8080,
                 up: np.ndarray | None = None) -> None:
        self.twin = twin
        up = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, dtype=np.float64)
        with contextlib.redirect_stdout(io.StringIO()):  # viser's own banner: we print the URL
            self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.url = f"http://{'localhost' if host in ('0.0.0.0', '::') else host}:" \
                   f"{self.server.get_port()}"
        self.server.scene.set_up_direction(tuple(float(v) for v in up))
        self.server.gui.configure_theme(show_share_button=False, control_width="medium")
        center, radius = twin.bounds([0.0, 1.0])
        cam = self.server.initial_camera
        cam.look_at = center
        cam.up = up
        cam.position = center + fit_distance(radius, cam.fov) * orbit_direction(
            START_AZIMUTH_DEG, ELEVATION_DEG, up)

        self.splats: dict[int, PartSplats] = {p.part: p for p in part_splats(twin)}
        self.part_nodes = {k: self.server.scene.add_frame(f"/part_{k}", show_axes=False)
                       for k in range(twin.num_parts)}
        self.splat_handles = {
            k: self.server.scene.add_gaussian_splats(
                f"/part_{k}/gaussians", centers=p.centers, covariances=p.covariances,
                rgbs=p.rgb, opacities=p.opacities)
            for k, p in self.splats.items()}
        flat = part_colors(np.arange(twin.num_parts))
        self.mesh_handles = {
            k: self.server.scene.add_mesh_simple(
                f"/part_{k}/mesh", mesh.vertices.astype(np.float32),
                mesh.faces.astype(np.uint32), color=tuple(flat[k]), visible=False)
            for k, mesh in part_meshes(out_dir, twin.num_parts).items()}
        self.axis_handles = [self._add_axis(i, j, center, radius)
                             for i, j in enumerate(twin.joints)]
        self._add_controls()

    def _add_axis(self, index: int, joint: TwinJoint, center: np.ndarray,
                  radius: float) -> viser.LineSegmentsHandle:
        part = self.splats.get(joint.part)
        part_center = part.centers.mean(axis=0) if part is not None else center
        ends = axis_segment(joint, part_center, center, radius)
        return self.server.scene.add_line_segments(
            f"/axes/joint_{index}", ends[None].astype(np.float32),
            colors=tuple(part_colors(np.array([joint.part]))[0]),
            thickness=AXIS_THICKNESS * radius)

    def _add_controls(self) -> None:
        gui = self.server.gui
        self.state_slider = gui.add_slider("state", min=0.0, max=1.0, step=0.01,
                                           initial_value=0.0,
                                           hint="0 = start, 1 = end: moves every joint")
        self.joint_sliders = []
        with gui.add_folder("joints"):
            for i, joint in enumerate(self.twin.joints):
                low, high = sorted((0.0, joint.amount))
                slider = gui.add_slider(
                    joint_label(i, joint), min=low, max=high if high > low else 1.0,
                    step=(high - low) / SLIDER_STEPS if high > low else 1.0, initial_value=0.0,
                    disabled=high <= low,
                    hint=f"part {joint.part}: from the start state (0) to the end state "
                         f"({joint.amount:g})")
                slider.on_update(lambda _, i=i: self._move_joint(i))
                self.joint_sliders.append(slider)
        self.color_mode = gui.add_dropdown("colour", COLOR_MODES, initial_value="rgb",
                                           hint="trained colours (their view-independent "
                                                "part), or a flat colour per part")
        self.show_gaussians = gui.add_checkbox("Gaussians", True)
        self.show_meshes = gui.add_checkbox("meshes", False, disabled=not self.mesh_handles)
        self.show_axes = gui.add_checkbox("joint axes", True)

        self.state_slider.on_update(lambda _: self._set_state(self.state_slider.value))
        self.color_mode.on_update(lambda _: self._recolor())
        self.show_gaussians.on_update(lambda _: self._show(self.splat_handles.values(),
                                                           self.show_gaussians.value))
        self.show_meshes.on_update(lambda _: self._show(self.mesh_handles.values(),
                                                        self.show_meshes.value))
        self.show_axes.on_update(lambda _: self._show(self.axis_handles, self.show_axes.value))

    def _set_state(self, s: float) -> None:
        for joint, slider in zip(self.twin.joints, self.joint_sliders, strict=True):
            slider.value = s * joint.amount  # each slider's callback moves its part

    def _move_joint(self, index: int) -> None:
        joint = self.twin.joints[index]
        wxyz, position = part_pose(joint, joint_fraction(joint, self.joint_sliders[index].value))
        node = self.part_nodes[joint.part]
        with self.server.atomic():  # rotation and translation land in the same frame
            node.wxyz, node.position = wxyz, position

    def _recolor(self) -> None:
        use_parts = self.color_mode.value == "parts"
        for k, handle in self.splat_handles.items():
            p = self.splats[k]
            handle.set_gaussians(p.centers, p.covariances, p.part_rgb if use_parts else p.rgb,
                                 p.opacities)

    @staticmethod
    def _show(handles: Iterable[viser.SceneNodeHandle], visible: bool) -> None:
        for handle in handles:
            handle.visible = visible

    def stop(self) -> None:
        with contextlib.redirect_stdout(io.StringIO()):  # viser's "server stopped" line
            self.server.stop()
