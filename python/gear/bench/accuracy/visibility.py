"""How far each moving part travels in the training images: a fact of the data, not of the
method. A part whose motion moves its surface by a fraction of a pixel in every view leaves no
trace an image-based method could find, whatever its budget; the real-asset suite reports the
smallest such motion per scene so that its table tells those parts apart from failures."""

from __future__ import annotations

import numpy as np

from gear.data.scene import Scene
from gear.evaluate import load_mesh
from gear.metrics import sample_surface

SAMPLES = 2000
# The share of the part's surface that moves at least this far: the part's far end (a door's
# free edge, a drawer's front) and not a stray vertex.
QUANTILE = 0.95


def part_motion_pixels(scene: Scene, seed: int = 0) -> list[float] | None:
    """Per ground-truth joint (the part it moves), how many pixels the part's surface moves
    from the start to the end state in the start state's training views: the QUANTILE of its
    sampled surface points' image displacements, median over the views (points behind a
    camera left out). None without ground-truth joints, part meshes or training views."""
    gt = scene.gt
    cameras = [v.camera for v in scene.train("start")]
    if gt is None or not gt.joints or not cameras:
        return None
    files = gt.meshes.get("start", {})
    moved = []
    for i, joint in enumerate(gt.joints):
        key = f"part_{i}"  # gear.data.gt.gt_mesh_files' name for part i's mesh
        mesh = load_mesh(files[key]) if key in files else None
        if mesh is None or mesh.area <= 0:
            return None
        points = sample_surface(mesh, SAMPLES, seed)
        transform = joint.motion()
        moved.append((points, points @ transform[:3, :3].T + transform[:3, 3]))
    return [_median_over_views(before, after, cameras) for before, after in moved]


def _median_over_views(before: np.ndarray, after: np.ndarray, cameras: list) -> float:
    shifts = []
    for camera in cameras:
        (uv0, z0), (uv1, z1) = camera.project(before), camera.project(after)
        seen = (z0 > 0) & (z1 > 0)
        if seen.any():
            step = np.linalg.norm(uv1[seen] - uv0[seen], axis=1)
            shifts.append(float(np.quantile(step, QUANTILE)))
    return float(np.median(shifts)) if shifts else 0.0
