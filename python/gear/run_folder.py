"""The output folder of one training run (docs/training.md, "One run per output folder").

A folder belongs to one run at a time: `RunFolder.open` takes a lock file held for the run's
life (an advisory `flock`, which the kernel releases when the process dies, so a lock left by a
crashed run is detected and taken over), refuses a folder that already holds a run unless the
caller resumes it or overwrites it, and never mixes two runs' files. Outputs are written under
a staging folder and renamed into place; a completion marker is written last, so a folder with
the marker holds one finished run and a folder without it an unfinished one.
"""

from __future__ import annotations

import fcntl
import json
import os
import shutil
import time
from pathlib import Path

LOCK = ".gear.lock"
COMPLETE = "complete.json"
STAGING = ".outputs.partial"
# Everything a run and the commands reading it write into its folder (besides the lock): what
# `--overwrite` removes, and what marks a folder as holding a run. `metrics.json` comes from
# `gear eval`, `twin_renders` from `gear render`, `batch.json` from `gear batch`; an export
# folder inside the run folder is recognised by its manifest (`is_export`).
RUN_ENTRIES = ("complete.json", "joints.json", "gaussians_canonical.ply", "parts.npy", "parts",
               "renders", "meshes", "log.jsonl", "config.json", "checkpoints", STAGING,
               "metrics.json", "twin_renders", "batch.json")
EXPORT_MANIFEST = "export.json"  # written last into every `gear export` folder


class RunFolderError(ValueError):
    """The output folder cannot be used for this run (one line, for the CLI)."""


def writable_folder(out_dir: Path) -> None:
    """Creates `out_dir` if needed; a one-line RunFolderError when it cannot hold outputs."""
    if out_dir.exists() and not out_dir.is_dir():
        raise RunFolderError(f"--out {out_dir}: is a file, not a folder")
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise RunFolderError(f"--out {out_dir}: cannot create the folder ({err.strerror})") from err
    if not os.access(out_dir, os.W_OK | os.X_OK):
        raise RunFolderError(f"--out {out_dir}: the folder is not writable")


def _describe_holder(text: str) -> str:
    try:
        holder = json.loads(text)
        return f"PID {holder['pid']}, started {holder['started']}"
    except (ValueError, KeyError, TypeError):
        return "an unknown process"


class RunFolder:
    """An output folder locked for this process; `close` releases it."""

    def __init__(self, path: Path, lock_fd: int, notes: list[str]) -> None:
        self.path, self._fd, self.notes = path, lock_fd, notes

    @classmethod
    def open(cls, out_dir: Path, *, resume: bool = False, overwrite: bool = False) -> RunFolder:
        """Locks `out_dir` and checks it suits a new run (`resume` False) or a continued one."""
        if resume and overwrite:
            raise RunFolderError("--resume and --overwrite exclude each other")
        out_dir = Path(out_dir)
        writable_folder(out_dir)
        fd, notes = cls._lock(out_dir)
        folder = cls(out_dir, fd, notes)
        try:
            folder._check_contents(resume, overwrite)
        except BaseException:
            folder.close()
            raise
        return folder

    @staticmethod
    def _lock(out_dir: Path) -> tuple[int, list[str]]:
        path = out_dir / LOCK
        notes: list[str] = []
        while True:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
            previous = os.read(fd, 4096).decode(errors="replace")
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(fd)
                raise RunFolderError(
                    f"--out {out_dir}: in use by another gear run ({_describe_holder(previous)}); "
                    "wait for it or choose another folder") from None
            # The holder may have removed the file between our open and our flock: then the
            # lock is on a deleted file and the next run would lock a new one. Retry.
            try:
                same = os.path.samestat(os.fstat(fd), os.stat(path))
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        if previous.strip():  # a clean run removes its lock file: this one's holder died
            notes.append(f"took over a stale lock in {out_dir} (left by "
                         f"{_describe_holder(previous)}, which no longer runs)")
        record = {"pid": os.getpid(), "started": time.strftime("%Y-%m-%d %H:%M:%S %Z")}
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(record).encode(), 0)
        os.fsync(fd)
        return fd, notes

    def _check_contents(self, resume: bool, overwrite: bool) -> None:
        entries = {p.name for p in self.path.iterdir()} - {LOCK}
        held = {name for name in entries if name in RUN_ENTRIES or is_export(self.path / name)}
        if resume:
            if COMPLETE in entries:
                raise RunFolderError(f"--resume: the run in {self.path} is finished; nothing to "
                                     "resume (use --overwrite to start it over)")
            return
        if held and not overwrite:
            if _predates_marker(self.path):
                raise RunFolderError(f"--out {_predates_message(self.path)}")
            state = "a finished" if COMPLETE in entries else "an unfinished"
            raise RunFolderError(
                f"--out {self.path}: holds {state} run; continue it with --resume, replace it "
                "with --overwrite, or choose another folder")
        foreign = entries - held
        if foreign and not held:
            raise RunFolderError(
                f"--out {self.path}: holds files that are not a gear run's "
                f"({', '.join(sorted(foreign)[:3])}); choose an empty or new folder")
        for name in held:  # --overwrite: the old run goes entirely before the new one starts
            _remove(self.path / name)
        if held:
            self.notes.append(f"--overwrite: removed the previous run's files from {self.path}")

    def staging(self) -> Path:
        """An empty folder the outputs are written to before `publish` moves them into place."""
        path = self.path / STAGING
        _remove(path)
        path.mkdir()
        return path

    def publish(self, summary: dict) -> None:
        """Moves the staged outputs into place, then writes the completion marker (last)."""
        staged = self.path / STAGING
        for entry in sorted(staged.iterdir()):
            target = self.path / entry.name
            _remove(target)  # an output folder of an earlier attempt of this run
            os.replace(entry, target)
        staged.rmdir()
        write_atomic(self.path / COMPLETE, json.dumps(summary, indent=2) + "\n")

    def close(self) -> None:
        """Releases the lock; the lock file goes with it (removed while still held)."""
        if self._fd < 0:
            return
        try:
            (self.path / LOCK).unlink(missing_ok=True)
        finally:
            os.close(self._fd)
            self._fd = -1

    def __enter__(self) -> RunFolder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def require_finished(out_dir: Path) -> Path:
    """`out_dir` when it holds a finished run (its completion marker is there); otherwise a
    one-line RunFolderError saying what it holds instead. Commands that read a run's outputs
    (eval, render, view, export) call this, so they never read half a run."""
    out_dir = Path(out_dir)
    if not out_dir.exists():
        raise RunFolderError(f"{out_dir}: no such output folder")
    if not out_dir.is_dir():
        raise RunFolderError(f"{out_dir}: is a file, not the output folder of `gear train`")
    if (out_dir / COMPLETE).is_file():
        return out_dir
    if _predates_marker(out_dir):
        raise RunFolderError(_predates_message(out_dir))
    if any((out_dir / name).exists() for name in RUN_ENTRIES):
        raise RunFolderError(
            f"{out_dir}: its run did not finish (no {COMPLETE}); continue it with "
            f"`gear train SCENE --out {out_dir} --resume`, or start it over with --overwrite")
    raise RunFolderError(f"{out_dir}: not the output folder of `gear train` (no {COMPLETE})")


def is_export(path: Path) -> bool:
    """Whether `path` is a folder written by `gear export` (it holds the export manifest)."""
    return path.is_dir() and (path / EXPORT_MANIFEST).is_file()


def _predates_marker(out_dir: Path) -> bool:
    """Published outputs without the completion marker: a run written by a gear older than the
    marker (its outputs went straight into the folder), or one stopped between publishing its
    outputs and writing the marker. Either way its last checkpoint can rewrite them."""
    return (out_dir / "joints.json").is_file() and not (out_dir / COMPLETE).is_file()


def _predates_message(out_dir: Path) -> str:
    return (f"{out_dir}: has outputs but no {COMPLETE} (written by an older gear, or stopped "
            f"while publishing them); `gear train SCENE --out {out_dir} --resume` rewrites them "
            "from its last checkpoint and marks the run finished, --overwrite starts it over")


def write_atomic(path: Path, text: str) -> None:
    """`text` to `path` through a temporary name, so a reader never sees half a file."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif path.exists() or path.is_symlink():
        path.unlink()
