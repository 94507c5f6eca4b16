"""One Gaussian PLY per part (the standard 3D Gaussian Splatting layout, via the trainer's own
writer), posed in the export's state, so splat viewers can show or hide the parts apart. A twin
with spherical-harmonic colour keeps its `f_rest_*` bands, turned with each part's pose."""

from __future__ import annotations

from pathlib import Path

import torch

from gear.export.assembly import Assembly
from gear.export.source import RunSource
from gear.outputs import write_ply
from gear.splats import Gaussians
from gear.splats.sh import SH_PARAM

SPLAT_FOLDER = "splats"
RGB_LIMIT = 1e-4  # write_ply stores colours through a logit: keep them off 0 and 1


def write_part_splats(run: RunSource, assembly: Assembly, folder: Path) -> list[str]:
    """splats/<state>/<link>.ply for every link with Gaussians; their paths, relative."""
    twin = run.twin
    state_value = 0.0 if assembly.state == "start" else 1.0
    means, quats = twin.pose(state_value)
    sh = twin.posed_sh(state_value)
    rgb = twin.rgb.clamp(RGB_LIMIT, 1 - RGB_LIMIT)
    logits = torch.nn.functional.one_hot(twin.parts, twin.num_parts).float() * 10.0
    out = folder / SPLAT_FOLDER / assembly.state
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for link, part in zip(assembly.links, run.parts, strict=True):
        rows = torch.as_tensor(part.index, dtype=torch.int64)
        if len(rows) == 0:
            continue
        params = {
            "means": means[rows], "quats": quats[rows], "log_scales": twin.log_scales[rows],
            "opacity": twin.opacity[rows], "colors": torch.logit(rgb[rows]),
            "logits": logits[rows],
        }
        if sh is not None:
            params[SH_PARAM] = sh[rows]
        g = Gaussians(params)
        rel = f"{SPLAT_FOLDER}/{assembly.state}/{link.name}.ply"
        write_ply(folder / rel, g)
        written.append(rel)
    return written
