"""Scoring a training output against the scene's ground truth: the field's metrics, for the
`gear eval` command and the benchmarks alike (docs/evaluation.md).

Computes the metrics that the inputs allow: joint errors after part matching, Chamfer
distances of the fused meshes (whole, static, movable), part-segmentation IoU against the
scene's GT part images and PSNR of the held-out renders. Whatever cannot be computed is listed
under "skipped" with the reason.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from PIL import Image

from gear.data import Scene, load_scene
from gear.data.scene import BACKGROUND_PART, STATES
from gear.metrics import (
    Matching,
    chamfer,
    match_parts,
    part_iou,
    psnr,
    untie_same_motions,
)

BACKGROUNDS = {"black": (0.0, 0.0, 0.0), "white": (1.0, 1.0, 1.0)}
_UNMATCHED_LABEL = 200  # predicted parts with no GT joint are relabelled 200, 201, ... (not GT ids)


def evaluate(out_dir: str | Path, scene_dir: str | Path, samples: int = 10000, seed: int = 0,
             background: str = "black", scene: Scene | None = None) -> dict[str, Any]:
    """All computable metrics as a JSON-ready dict (see docs/evaluation.md for its keys)."""
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        raise FileNotFoundError(f"{out_dir}: no such output folder")
    scene = scene if scene is not None else load_scene(scene_dir)
    result: dict[str, Any] = {"out_dir": str(out_dir), "scene": str(scene.root), "skipped": []}
    result.update({key: None for key, _ in SUMMARY})  # present even when not computable
    skipped: list[str] = result["skipped"]

    pred_joints = _read_joints(out_dir, skipped)
    matching = None
    if scene.gt is None:
        skipped.append("scene has no gt/trans.json: joint errors, part matching and Chamfer "
                       "distances cannot be computed")
    elif pred_joints is not None:
        try:
            matching = match_joints(out_dir, scene, pred_joints)
        except ValueError as err:
            raise ValueError(f"{out_dir / 'joints.json'}: {err}") from err
        result.update(_joint_summary(matching, pred_joints, scene.gt.joints))
    if scene.gt is not None:
        result.update(_chamfer_summary(out_dir, scene, matching, samples, seed, skipped))
    result.update(_iou_summary(out_dir, scene, matching, skipped))
    result.update(_psnr_summary(out_dir, scene, BACKGROUNDS[background], skipped))
    result["timings"] = _read_timings(out_dir, skipped)
    return result


def match_joints(out_dir: Path, scene: Scene, pred_joints: list[Any]) -> Matching:
    """The predicted joints of the run in `out_dir` matched to `scene`'s ground truth (which it
    must have): by joint errors (metrics.match_parts), and among ground-truth joints that are
    one motion by where the parts' meshes are (metrics.untie_same_motions)."""
    assert scene.gt is not None
    matching = match_parts(pred_joints, scene.gt.joints)
    return untie_same_motions(matching, pred_joints, scene.gt.joints,
                              *_part_centres(Path(out_dir), scene))


def _part_centres(out_dir: Path, scene: Scene) -> tuple[dict[int, np.ndarray],
                                                         dict[int, np.ndarray]]:
    """Centres of the predicted parts' meshes (by joint index) and of the ground truth's (by
    GT joint index), in the first state with GT part meshes; what is missing is left out."""
    assert scene.gt is not None
    for state in STATES:
        gt_files = scene.gt.meshes.get(state, {})
        gt = {g: _centre(gt_files.get(f"part_{g}")) for g in range(len(scene.gt.joints))}
        if any(c is not None for c in gt.values()):
            folder = out_dir / "meshes" / state
            pred = {int(path.stem.removeprefix("part_")): _centre(path)
                    for path in folder.glob("part_*.ply")
                    if path.stem.removeprefix("part_").isdigit()}
            return ({k: c for k, c in pred.items() if c is not None},
                    {k: c for k, c in gt.items() if c is not None})
    return {}, {}


def _centre(path: Path | None) -> np.ndarray | None:
    """The area-weighted centre of the mesh at `path` (None: no such mesh)."""
    mesh = load_mesh(Path(path)) if path is not None else None
    return None if mesh is None else np.asarray(mesh.centroid)


def _read_timings(out_dir: Path, skipped: list[str]) -> dict[str, float] | None:
    """Wall seconds per stage: the last {"event": "timings"} record of log.jsonl."""
    path = out_dir / "log.jsonl"
    if not path.is_file():
        skipped.append(f"{path} missing: wall time per stage not reported")
        return None
    timings = None
    for line in path.read_text().splitlines():
        try:
            record = json.loads(line)
        except ValueError:
            continue  # a line cut short by an interrupted run
        if isinstance(record, dict) and record.get("event") == "timings":
            timings = {k: float(v) for k, v in record.items()
                       if k != "event" and isinstance(v, int | float)}
    if timings is None:
        skipped.append(f"{path} has no timings record (unfinished run?)")
    return timings


def _read_joints(out_dir: Path, skipped: list[str]) -> list[dict] | None:
    path = out_dir / "joints.json"
    if not path.is_file():
        skipped.append(f"{path} missing: joint errors and part matching cannot be computed")
        return None
    try:
        data = json.loads(path.read_text())
        joints = data["joints"]
        if not isinstance(joints, list):
            raise TypeError("'joints' is not a list")
    except (ValueError, KeyError, TypeError) as err:
        raise ValueError(f"{path}: not a valid joints file ({err})") from err
    return joints


def _mean(values: list[float]) -> float | None:
    return float(np.mean(values)) if values else None


def _joint_summary(matching: Matching, pred: list[dict], gt: list[Any]) -> dict[str, Any]:
    rows = []
    for (g, p), err in zip(matching.pairs, matching.errors, strict=True):
        rows.append({"gt": g, "pred": p, "gt_type": gt[g].type, "pred_type": pred[p]["type"],
                     **err})
    revolute = [r for r in rows if r["gt_type"] == "revolute"]
    prismatic = [r for r in rows if r["gt_type"] == "prismatic"]
    return {
        "joints": rows,
        "unmatched_gt": matching.unmatched_gt,
        "unmatched_pred": matching.unmatched_pred,
        "type_mismatches": len(matching.type_mismatches),
        "count_mismatch": matching.count_mismatch,
        "axis_ang": _mean([r["axis_ang"] for r in rows]),
        "axis_pos": _mean([r["axis_pos"] for r in revolute]),
        "geo_dist_deg": _mean([r["geo_dist"] for r in revolute]),
        "geo_dist_m": _mean([r["geo_dist"] for r in prismatic]),
    }


def load_mesh(path: Path) -> trimesh.Trimesh | None:
    """The mesh at `path`, or None when the file is missing or holds no triangles."""
    if not path.is_file():
        return None
    loaded = trimesh.load(path, force="mesh", process=False)
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        return None
    return loaded


def _chamfer_summary(out_dir: Path, scene: Scene, matching: Matching | None, samples: int,
                     seed: int, skipped: list[str]) -> dict[str, Any]:
    """CD per state and mesh; CD-w / CD-s / CD-m averaged over states (CD-m also over parts)."""
    assert scene.gt is not None
    # Which predicted part file stands for each GT part: via the matching, else none.
    part_pairs = ([(f"part_{g}", f"part_{p}") for g, p in matching.pairs]
                  if matching is not None else [])
    per_state: dict[str, dict[str, float]] = {}
    groups: dict[str, list[float]] = {"cd_w": [], "cd_s": [], "cd_m": []}
    for state in STATES:
        gt_files = scene.gt.meshes.get(state, {})
        if not gt_files:
            skipped.append(f"scene has no GT meshes for the {state} state: its CD is skipped")
            continue
        pairs = [("whole", "whole", "cd_w"), ("static", "static", "cd_s")]
        pairs += [(gk, pk, "cd_m") for gk, pk in part_pairs]
        for gt_key, pred_key, group in pairs:
            if gt_key not in gt_files:
                skipped.append(f"{state}: no GT mesh '{gt_key}' in the scene")
                continue
            pred_path = out_dir / "meshes" / state / f"{pred_key}.ply"
            pred_mesh = load_mesh(pred_path)
            if pred_mesh is None:
                what = "missing" if not pred_path.is_file() else "empty"
                skipped.append(f"{pred_path} {what}: CD of {state}/{gt_key} not computed")
                continue
            gt_mesh = load_mesh(gt_files[gt_key])
            if gt_mesh is None:
                skipped.append(f"{gt_files[gt_key]} has no triangles: CD not computed")
                continue
            value = chamfer(pred_mesh, gt_mesh, n=samples, seed=seed)
            per_state.setdefault(state, {})[gt_key] = value
            groups[group].append(value)
    return {"chamfer": per_state, **{k: _mean(v) for k, v in groups.items()}}


def _label_map(matching: Matching | None) -> np.ndarray:
    """Lookup table predicted part id -> GT part id (static 0 -> 0, background kept).

    Predicted part p+1 (moved by joint p) becomes GT part g+1 when joint p was matched to GT
    joint g; unmatched predicted parts get ids no GT part has, so they count as false positives.
    """
    table = np.arange(256, dtype=np.uint8)
    if matching is None:
        return table
    for g, p in matching.pairs:
        table[p + 1] = g + 1
    for p in matching.unmatched_pred:
        table[p + 1] = _UNMATCHED_LABEL + p
    return table


def _iou_summary(out_dir: Path, scene: Scene, matching: Matching | None,
                 skipped: list[str]) -> dict[str, Any]:
    pairs: dict[str, tuple[list, list]] = {}
    missing = 0
    for view in scene.all_views():
        if view.parts is None:
            continue
        split = view.name.split("/")[1]
        path = out_dir / "parts" / f"{view.name}.png"
        if not path.is_file():
            missing += 1
            continue
        pred = np.asarray(Image.open(path))
        if pred.shape != view.parts.shape:
            raise ValueError(f"{path}: size {pred.shape} differs from the scene's "
                             f"{view.parts.shape}")
        preds, gts = pairs.setdefault(split, ([], []))
        preds.append(pred)
        gts.append(view.parts)
    if not pairs:
        reason = ("scene has no GT part images" if missing == 0
                  else f"{out_dir / 'parts'} has none of the {missing} part images")
        skipped.append(f"part IoU not computed: {reason}")
        return {"part_iou": None}
    if missing:
        skipped.append(f"part IoU: {missing} predicted part images missing, scored without them")
    if matching is None:
        skipped.append("part IoU without a joint matching: predicted part i+1 is compared with "
                       "GT part i+1")
    table = _label_map(matching)
    splits = {}
    for split, (preds, gts) in sorted(pairs.items()):
        remapped = [table[p] for p in preds]
        out = part_iou(remapped, gts, ignore=BACKGROUND_PART)
        splits[split] = {"mean": out["mean"], "per_part": {str(k): v for k, v in
                                                          out["per_part"].items()},
                         "views": len(preds)}
    all_preds = [table[p] for preds, _ in pairs.values() for p in preds]
    all_gts = [g for _, gts in pairs.values() for g in gts]
    return {"part_iou": part_iou(all_preds, all_gts, ignore=BACKGROUND_PART)["mean"],
            "part_iou_splits": splits}


def _read_rgb(path: Path, background: tuple[float, float, float]) -> np.ndarray:
    image = np.asarray(Image.open(path), dtype=np.float32) / 255.0
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=-1)
    if image.shape[-1] == 4:  # RGBA render: composite over the same background as the GT
        image = image[..., :3] * image[..., 3:] + np.asarray(background) * (1 - image[..., 3:])
    return image[..., :3]


def _psnr_summary(out_dir: Path, scene: Scene, background: tuple[float, float, float],
                  skipped: list[str]) -> dict[str, Any]:
    full, masked, missing = [], [], 0
    for state in STATES:
        for view in scene.test(state):
            path = out_dir / "renders" / f"{view.name}.png"
            if not path.is_file():
                missing += 1
                continue
            render = _read_rgb(path, background)
            if render.shape[:2] != view.rgb.shape[:2]:
                raise ValueError(f"{path}: size {render.shape[:2]} differs from the scene's "
                                 f"{view.rgb.shape[:2]}")
            alpha = view.alpha[..., None]
            gt = view.rgb * alpha + np.asarray(background, np.float32) * (1 - alpha)
            full.append(psnr(render, gt))
            if np.any(view.alpha > 0.5):
                masked.append(psnr(render, gt, mask=view.alpha > 0.5))
    if not full:
        reason = ("scene has no test views" if missing == 0
                  else f"{out_dir / 'renders'} has none of the {missing} test renders")
        skipped.append(f"PSNR not computed: {reason}")
        return {"psnr": None, "psnr_masked": None}
    if missing:
        skipped.append(f"PSNR: {missing} test renders missing, scored without them")
    return {"psnr": _mean(full), "psnr_masked": _mean(masked), "psnr_views": len(full)}


# --- report ----------------------------------------------------------------------------------

SUMMARY = [  # metrics.json key, table label
    ("axis_ang", "Axis Ang (deg)"),
    ("axis_pos", "Axis Pos (x10)"),
    ("geo_dist_deg", "Geo Dist revolute (deg)"),
    ("geo_dist_m", "Geo Dist prismatic"),
    ("cd_s", "CD-s (x1000)"),
    ("cd_m", "CD-m (x1000)"),
    ("cd_w", "CD-w (x1000)"),
    ("part_iou", "Part IoU"),
    ("psnr", "PSNR test (dB)"),
    ("psnr_masked", "PSNR test, object (dB)"),
]


def _fmt(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "NO"
    if isinstance(value, float):
        return f"{value:.4f}" if abs(value) < 10 else f"{value:.2f}"
    return str(value)


def format_table(metrics: dict[str, Any]) -> str:
    """Summary and per-joint tables as plain text."""
    lines = [f"{'metric':<26}value"]
    lines += [f"{label:<26}{_fmt(metrics.get(key))}" for key, label in SUMMARY]
    if metrics.get("timings"):
        stages = ", ".join(f"{k} {v:.1f}" for k, v in metrics["timings"].items())
        lines.append(f"{'wall time (s)':<26}{stages}")
    if metrics.get("joints"):
        lines += ["", f"{'GT joint':<10}{'pred':<6}{'type':<22}{'Axis Ang':>10}{'Axis Pos':>10}"
                      f"{'Geo Dist':>10}"]
        for r in metrics["joints"]:
            kind = r["gt_type"] if r["type_match"] else f"{r['gt_type']}!={r['pred_type']}"
            lines.append(f"{r['gt']:<10}{r['pred']:<6}{kind:<22}{_fmt(r['axis_ang']):>10}"
                         f"{_fmt(r['axis_pos']):>10}{_fmt(r['geo_dist']):>10}")
    if metrics.get("type_mismatches"):
        lines.append(f"type mismatches: {metrics['type_mismatches']} (errors count the whole GT "
                     "motion)")
    if metrics.get("unmatched_gt"):
        lines.append(f"GT joints with no prediction: {metrics['unmatched_gt']}")
    if metrics.get("unmatched_pred"):
        lines.append(f"predicted joints with no GT joint: {metrics['unmatched_pred']}")
    if metrics.get("skipped"):
        lines += ["", "not computed:"] + [f"  - {s}" for s in metrics["skipped"]]
    return "\n".join(lines)
