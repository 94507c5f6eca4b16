"""Checkpoints: one file (checkpoints/last.pt) rewritten atomically, holding everything a run
needs to continue exactly where it stopped (parameters, Adam moments, RNG states, stage)."""

from __future__ import annotations

import os
from pathlib import Path

import torch

from gear.splats import Gaussians

LAST = "last.pt"


def gaussians_state(g: Gaussians) -> dict:
    return {
        "params": {name: t.detach().clone() for name, t in g.params.items()},
        "optimizer": None if g.optimizer is None else g.optimizer.state_dict(),
        "lrs": None
        if g.optimizer is None
        else {group["name"]: group["lr"] for group in g.optimizer.param_groups},
    }


def gaussians_from_state(state: dict) -> Gaussians:
    g = Gaussians(state["params"])
    if state["optimizer"] is not None:
        g.setup_optimizer(state["lrs"])
        g.optimizer.load_state_dict(state["optimizer"])
    return g


def save(directory: Path, payload: dict) -> Path:
    """Writes to a temporary file then renames: a crash never leaves a half-written checkpoint."""
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / LAST
    tmp = directory / (LAST + ".tmp")
    torch.save(payload, tmp)
    os.replace(tmp, path)
    return path


def load(directory: Path) -> dict | None:
    path = directory / LAST
    if not path.exists():
        return None
    try:
        return torch.load(path, weights_only=False)
    except Exception as err:  # a truncated or foreign file: say which, never a deep traceback
        raise ValueError(f"{path}: cannot read the checkpoint ({err})") from err
