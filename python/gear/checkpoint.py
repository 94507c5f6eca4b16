"""Checkpoints: one file (checkpoints/last.pt) rewritten atomically, holding everything a run
needs to continue exactly where it stopped (parameters, Adam moments, RNG states, stage)."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np
import torch

from gear.data.scene import STATES, Scene
from gear.run_folder import RunFolderError
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


def scene_fingerprint(scene_dir: Path, scene: Scene) -> dict:
    """What a checkpoint was made from: the files of the scene folder (path -> size; `gt/` is
    left out, only evaluation reads it) and a digest of every view's camera (intrinsics, size,
    pose) of the loaded `scene`."""
    cameras = [v.camera for s in STATES for vs in scene.views[s].values() for v in vs]
    scene_dir = Path(scene_dir)
    files = {str(p.relative_to(scene_dir)): p.stat().st_size
             for p in sorted(scene_dir.rglob("*"))
             if p.is_file() and p.relative_to(scene_dir).parts[0] != "gt"}
    digest = hashlib.sha256()
    for cam in cameras:
        digest.update(np.asarray(cam.world_to_cam, dtype=np.float64).tobytes())
        digest.update(np.array([cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height],
                               dtype=np.float64).tobytes())
    return {"files": files, "cameras": digest.hexdigest()}


def _listed(names: list[str]) -> str:
    return ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")


def check_resumable(saved: dict, scene: dict, config: dict) -> None:
    """A one-line RunFolderError (a ValueError: the folder holds another run) naming what
    differs between the checkpoint `saved` and this run's scene fingerprint and resolved
    config (both as `scene_fingerprint` / JSON dicts)."""
    before = saved.get("scene")
    if before is not None:  # checkpoints written before fingerprints existed are not checked
        old, new = before["files"], scene["files"]
        differences = []
        if missing := sorted(set(old) - set(new)):
            differences.append(f"files gone: {_listed(missing)}")
        if added := sorted(set(new) - set(old)):
            differences.append(f"new files: {_listed(added)}")
        if changed := sorted(n for n in set(old) & set(new) if old[n] != new[n]):
            differences.append(f"files of another size: {_listed(changed)}")
        if before["cameras"] != scene["cameras"]:
            differences.append("the cameras differ")
        if differences:
            raise RunFolderError("--resume: the checkpoint was made from another scene ("
                             + "; ".join(differences) + ")")
    saved_config = saved["config"]
    changed = [f"{name} {saved_config.get(name)!r} -> {value!r}" for name, value in config.items()
               if name in saved_config and saved_config[name] != value]
    if changed:
        raise RunFolderError("--resume: the options differ from the saved run's ("
                         + ", ".join(changed) + "); resume without them or start over with "
                         "--overwrite")
