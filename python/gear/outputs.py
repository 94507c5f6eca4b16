"""Everything a finished run writes to OUT_DIR (docs/training.md, "Outputs"): joints.json, the
canonical Gaussians (standard 3DGS PLY + `part`), parts.npy, per-view part-id and RGB renders,
TSDF meshes."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
import trimesh
from PIL import Image

from gear.articulation import PartMotion
from gear.camera import Camera
from gear.kinematics import pose_parts
from gear.sh import SH_C0
from gear.splats import Gaussians, render
from gear.splats.sh import SH_PARAM, view_rgb

BACKGROUND_PART = 255


def posed(g: Gaussians, motion: PartMotion | None, state: str,
          canonical: str) -> tuple[torch.Tensor, torch.Tensor]:
    """(means, quats) of the Gaussians in `state` with hard part assignment."""
    means, quats = g["means"].detach(), g["quats"].detach()
    if motion is None or state == canonical or motion.num_parts == 1:
        return means, quats
    with torch.no_grad():
        qr, qd = motion.motion(1.0)
        return pose_parts(means, quats, g.part_ids(), qr, qd)


def write_ply(path: Path, g: Gaussians) -> None:
    """Binary little-endian PLY in the layout 3D Gaussian Splatting viewers read (x y z,
    normals, f_dc_0..2, f_rest_* with spherical harmonics (channel-major), opacity logit,
    scale_0..2 as logs, rot_0..3 as w x y z) plus `part`."""
    n = len(g)
    rgb = g.rgb().detach().numpy()
    rest = g.params.get(SH_PARAM)
    # [N, K-1, 3] -> [N, 3 * (K-1)]: all of red's coefficients, then green's, then blue's.
    f_rest = None if rest is None else rest.detach().transpose(1, 2).reshape(n, -1).numpy()
    rest_fields = [] if f_rest is None else [(f"f_rest_{i}", "f4") for i in range(f_rest.shape[1])]
    fields = [
        ("x", "f4"), ("y", "f4"), ("z", "f4"), ("nx", "f4"), ("ny", "f4"), ("nz", "f4"),
        ("f_dc_0", "f4"), ("f_dc_1", "f4"), ("f_dc_2", "f4"), *rest_fields, ("opacity", "f4"),
        ("scale_0", "f4"), ("scale_1", "f4"), ("scale_2", "f4"),
        ("rot_0", "f4"), ("rot_1", "f4"), ("rot_2", "f4"), ("rot_3", "f4"), ("part", "i4"),
    ]
    data = np.zeros(n, dtype=[(name, "<" + t) for name, t in fields])
    means = g["means"].detach().numpy()
    data["x"], data["y"], data["z"] = means.T
    f_dc = (rgb - 0.5) / SH_C0
    data["f_dc_0"], data["f_dc_1"], data["f_dc_2"] = f_dc.T
    for i, (name, _) in enumerate(rest_fields):
        data[name] = f_rest[:, i]
    data["opacity"] = g["opacity"].detach().numpy()
    scales = g["log_scales"].detach().numpy()
    data["scale_0"], data["scale_1"], data["scale_2"] = scales.T
    quats = g["quats"].detach().numpy()
    data["rot_0"], data["rot_1"], data["rot_2"], data["rot_3"] = quats.T
    data["part"] = g.part_ids().numpy().astype(np.int32)
    header = "ply\nformat binary_little_endian 1.0\n" + f"element vertex {n}\n"
    header += "".join(
        f"property {'float' if t == 'f4' else 'int'} {name}\n" for name, t in fields
    )
    header += "end_header\n"
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(data.tobytes())


def _render_parts(g: Gaussians, means: torch.Tensor, quats: torch.Tensor, cam: Camera):
    """Rendered part id per pixel (255 where alpha < 0.5) and RGB over black."""
    k = g.num_parts
    onehot = F.one_hot(g.part_ids(), k).float()
    with torch.no_grad():
        rgb = view_rgb(g, g.rgb(), cam, means, quats, g["quats"])
        out = render(g, cam, pose=(means, quats), features=torch.cat([rgb, onehot], dim=1),
                     detach=True)
    ids = out.features[..., 3:].argmax(dim=-1).numpy().astype(np.uint8)
    ids[out.alpha.numpy() < 0.5] = BACKGROUND_PART
    rgb = out.features[..., :3].clamp(0, 1).numpy()
    return ids, rgb


def write_view_images(out_dir: Path, g: Gaussians, motion: PartMotion | None, canonical: str,
                      views: dict[str, dict[str, Sequence]]) -> None:
    """parts/{state}/{split}/NNNN.png for every view; renders/{state}/test/NNNN.png (RGB)."""
    for state, splits in views.items():
        means, quats = posed(g, motion, state, canonical)
        for split, vs in splits.items():
            for view in vs:
                ids, rgb = _render_parts(g, means, quats, view.camera)
                stem = view.name.rsplit("/", 1)[-1]  # the image's file stem, e.g. "0003"
                path = out_dir / "parts" / state / split / f"{stem}.png"
                path.parent.mkdir(parents=True, exist_ok=True)
                Image.fromarray(ids).save(path)
                if split == "test":
                    path = out_dir / "renders" / state / split / f"{stem}.png"
                    path.parent.mkdir(parents=True, exist_ok=True)
                    Image.fromarray(np.round(rgb * 255).astype(np.uint8)).save(path)


def write_meshes(out_dir: Path, g: Gaussians, motion: PartMotion | None, canonical: str,
                 train_views: dict[str, Sequence], voxel: float, trunc: float) -> None:
    """meshes/{state}/{whole,static,part_<i>}.ply: TSDF fusion of the rendered expected depth
    (normalised by alpha) of the whole model and of each part alone, over the training views."""
    from gear.mesh import tsdf_fuse

    ids = g.part_ids()
    subsets = {"whole": torch.ones(len(g), dtype=torch.bool), "static": ids == 0}
    for k in range(1, g.num_parts):
        subsets[f"part_{k - 1}"] = ids == k
    for state, vs in train_views.items():
        means, quats = posed(g, motion, state, canonical)
        folder = out_dir / "meshes" / state
        folder.mkdir(parents=True, exist_ok=True)
        for name, keep in subsets.items():
            if not bool(keep.any()):  # a part that lost all its Gaussians: an empty mesh
                trimesh.Trimesh().export(folder / f"{name}.ply")
                continue
            part = g.subset(keep)
            depths, alphas = [], []
            for view in vs:
                with torch.no_grad():
                    out = render(part, view.camera, pose=(means[keep], quats[keep]),
                                 features=torch.zeros(len(part), 1), depth=True)
                alpha = out.alpha.numpy()
                depth = out.depth.numpy() / np.maximum(alpha, 1e-6)
                depths.append(np.where(alpha > 1e-6, depth, 0.0))
                alphas.append(alpha)
            mesh = tsdf_fuse(depths, alphas, [v.camera for v in vs], voxel=voxel, trunc=trunc)
            mesh.export(folder / f"{name}.ply")


def write_joints(path: Path, canonical: str, joints: list[dict]) -> None:
    path.write_text(json.dumps({"canonical": canonical, "joints": joints}, indent=2) + "\n")


def drop_empty_parts(g: Gaussians, motion: PartMotion) -> tuple[Gaussians, PartMotion, list[int]]:
    """The model without the movable parts no Gaussian belongs to (more parts asked for than
    the data has): their logit columns and motions go, the others are renumbered in order.
    Returns the dropped part ids (empty when every part keeps Gaussians)."""
    counts = torch.bincount(g.part_ids(), minlength=g.num_parts)
    keep = [0] + [k for k in range(1, g.num_parts) if int(counts[k]) > 0]
    dropped = [k for k in range(1, g.num_parts) if int(counts[k]) == 0]
    if not dropped:
        return g, motion, []
    # Every Gaussian's argmax is a kept column, so the kept columns' argmax is the same part.
    kept = Gaussians({name: (t.detach()[:, keep] if name == "logits" else t.detach())
                      for name, t in g.params.items()})
    smaller = PartMotion(len(keep), dtype=motion.qr.dtype)
    movable = torch.tensor(keep[1:], dtype=torch.long) - 1  # long even when none is left
    with torch.no_grad():
        smaller.qr.copy_(motion.qr[movable])
        smaller.qd.copy_(motion.qd[movable])
        smaller.prismatic.copy_(motion.prismatic[keep])
    return kept, smaller, dropped
