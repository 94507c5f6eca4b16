"""`export_twin`: a trained run written as a simulation-ready folder (URDF and/or MJCF, shared
meshes, a GLB per state, a Gaussian PLY per part, export.json), never half-written: everything
goes to a temporary folder beside the destination, renamed into place when complete."""

from __future__ import annotations

import json
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from tqdm import tqdm

from gear.export.assembly import Assembly, ExportOptions, build_assembly
from gear.export.assets import write_link_meshes
from gear.export.glb import write_glb
from gear.export.mjcf import write_mjcf
from gear.export.source import RunSource, load_run
from gear.export.splats import write_part_splats
from gear.export.urdf import write_urdf
from gear.run_folder import EXPORT_MANIFEST as MANIFEST
from gear.run_folder import is_export


@dataclass
class ExportResult:
    assembly: Assembly
    folders: list[Path]  # the folders written
    urdf: Path | None
    mjcf: Path | None
    seconds: float
    notes: list[str] = field(default_factory=list)


def _check_destination(folder: Path) -> None:
    """Refuses a destination that is a file, or a non-empty folder other than a previous
    export (which is replaced), and one whose parent cannot be written."""
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"{folder}: exists and is not a folder")
    if folder.is_dir() and any(folder.iterdir()) and not is_export(folder):
        raise ValueError(f"{folder}: exists and is not empty (and is not a gear export)")
    try:
        folder.parent.mkdir(parents=True, exist_ok=True)
        probe = tempfile.mkdtemp(prefix=f".{folder.name}.", dir=folder.parent)
    except OSError as err:
        raise ValueError(f"{folder}: cannot write the output folder here "
                         f"({err.strerror or err})") from None
    Path(probe).rmdir()


def _replace(tmp: Path, folder: Path) -> None:
    """Moves the finished `tmp` to `folder`, replacing a previous export only now."""
    old = None
    if folder.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{folder.name}.old.", dir=folder.parent))
        old.rmdir()
        folder.rename(old)
    tmp.rename(folder)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def _manifest(assembly: Assembly, run: RunSource, files: dict[str, object]) -> dict:
    return {
        "name": assembly.name,
        "state": assembly.state,
        "state_note": f"every file holds the twin in its {assembly.state} state (joint value 0); "
                      f"the run's canonical Gaussians are in its {run.twin.canonical} state",
        "density": assembly.density,
        "files": files,
        "links": [{
            "name": link.name, "part": link.part, "frame": link.frame.tolist(),
            "mass": link.inertial.mass, "volume": link.inertial.volume,
            "center_of_mass": link.inertial.com.tolist(),
            "visual_faces": 0 if link.visual is None else len(link.visual.faces),
            "collision_pieces": len(link.pieces),
        } for link in assembly.links],
        "joints": [{
            "name": j.name, "child": j.child, "type": j.type, "origin": j.origin.tolist(),
            "axis": j.axis.tolist(), "lower": j.lower, "upper": j.upper, "end": j.end,
            "damping": j.damping, "friction": j.friction,
        } for j in assembly.joints],
        "notes": assembly.notes,
    }


def _write_folder(run: RunSource, assembly: Assembly, folder: Path, urdf: bool,
                  mjcf: bool) -> None:
    files: dict[str, object] = {}
    mesh_files = write_link_meshes(assembly, folder)
    files["meshes"] = {name: {"visual": f.visual, "collision": f.collision}
                       for name, f in mesh_files.items()}
    if urdf:
        files["urdf"] = f"{assembly.name}.urdf"
        write_urdf(assembly, mesh_files, folder / files["urdf"])
    if mjcf:
        files["mjcf"] = f"{assembly.name}.xml"
        write_mjcf(assembly, mesh_files, folder / files["mjcf"])
    files["glb"] = {}
    for state, fraction in (("start", 0.0), ("end", 1.0)):
        files["glb"][state] = f"{assembly.name}_{state}.glb"
        write_glb(assembly, fraction, folder / files["glb"][state])
    files["splats"] = write_part_splats(run, assembly, folder)
    (folder / MANIFEST).write_text(json.dumps(_manifest(assembly, run, files), indent=1) + "\n")


def export_twin(out_dir: str | Path, urdf_dir: str | Path | None = None,
                mjcf_dir: str | Path | None = None, name: str | None = None,
                options: ExportOptions | None = None, quiet: bool = False) -> ExportResult:
    """Writes the twin in OUT_DIR to URDF_DIR (NAME.urdf) and/or MJCF_DIR (NAME.xml), each
    folder with its meshes, GLBs, part PLYs and export.json (the same folder may hold both)."""
    t0 = time.perf_counter()
    options = options or ExportOptions()
    options.check()
    wanted: dict[Path, set[str]] = {}
    for kind, folder in (("urdf", urdf_dir), ("mjcf", mjcf_dir)):
        if folder is not None:
            wanted.setdefault(Path(folder).absolute(), set()).add(kind)
    if not wanted:
        raise ValueError("nothing to export: give --urdf DIR and/or --mjcf DIR")
    for folder in wanted:
        _check_destination(folder)
    run = load_run(out_dir)
    name = name or Path(out_dir).resolve().name
    with tqdm(total=len(run.parts), desc="export: meshes and convex decomposition", unit="part",
              disable=quiet) as bar:
        def advance(part: str) -> None:
            bar.set_postfix_str(part)
            bar.update(1)

        assembly = build_assembly(run, name, options, progress=advance)
    paths: dict[str, Path] = {}
    for folder, kinds in wanted.items():
        tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", dir=folder.parent))
        try:
            _write_folder(run, assembly, tmp, "urdf" in kinds, "mjcf" in kinds)
            _replace(tmp, folder)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        for kind in kinds:
            paths[kind] = folder / f"{name}.{'urdf' if kind == 'urdf' else 'xml'}"
    return ExportResult(assembly, list(wanted), paths.get("urdf"), paths.get("mjcf"),
                        time.perf_counter() - t0, assembly.notes)
