"""The scenes of a batch: SCENES is a folder whose sub-folders are scenes, or a text file
listing scene folders (one per line; blank lines and `#` comments skipped; relative paths are
taken from the file's folder). Each scene's runs go to RUNS/<folder name>."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path


class BatchError(ValueError):
    """The batch as a whole cannot start (one line, for the CLI)."""


@dataclass(frozen=True)
class BatchScene:
    name: str  # its run folder's name under RUNS
    path: Path


def list_scenes(spec: Path) -> list[BatchScene]:
    """The scenes named by `spec`. A listed path that is no scene is not an error here: its
    task reports it, so one bad scene never stops the batch."""
    spec = Path(spec)
    if spec.is_dir():
        paths = sorted(p for p in spec.iterdir() if p.is_dir() and not p.name.startswith("."))
        if not paths:
            raise BatchError(f"{spec}: holds no scene folders")
    elif spec.is_file():
        paths = []
        for line in spec.read_text().splitlines():
            line = line.strip()
            if line and not line.startswith("#"):
                path = Path(line).expanduser()
                paths.append(path if path.is_absolute() else spec.parent / path)
        if not paths:
            raise BatchError(f"{spec}: lists no scene folders")
    else:
        raise BatchError(f"{spec}: no such folder or scene list")
    scenes: dict[str, BatchScene] = {}
    for path in paths:
        path = path.absolute()  # workers may run in another folder (or on another machine)
        name = path.resolve().name
        if name in scenes:
            raise BatchError(f"two scenes would share the run folder {name!r} ({scenes[name].path}"
                             f" and {path}); rename one of them")
        scenes[name] = BatchScene(name, path)
    return list(scenes.values())


def files_fingerprint(folder: Path) -> dict[str, list[int]]:
    """Every file under `folder` with its size and modification time: a scene that failed
    validation is checked again by `--resume` only once this changes."""
    folder = Path(folder)
    if not folder.is_dir():
        return {}
    found = {}
    for root, _dirs, files in os.walk(folder):
        for name in files:
            path = Path(root) / name
            stat = path.stat()
            found[str(path.relative_to(folder))] = [stat.st_size, stat.st_mtime_ns]
    return dict(sorted(found.items()))
