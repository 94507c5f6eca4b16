"""Training configuration: every hyperparameter of the method in one dataclass (each field's
role: docs/method.md, "Config fields").

The paper's Table S1 values are the defaults of the `full` profile. `fast` and `quick` rescale
the schedule (iteration counts and the iterations at which things happen) but keep every loss
weight and threshold. A JSON file (`--config FILE`) overrides any field; the resolved config
is written to the output folder as config.json.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

SCHEDULES = ("em", "joint", "em-refine")
PROFILES = ("quick", "fast", "full")
ANCHORS = ("frozen", "images")


@dataclass
class TrainConfig:
    profile: str = "full"
    seed: int = 0
    schedule: str = "em"  # em | joint (no alternation) | em-refine (joint, then EM)
    num_parts: int | None = None  # K including the static part; None = estimated from the data

    # --- Table S1: initialisation (stage 2) ---
    voxel_size: float | None = None  # None = adaptive: 0.1 one movable part / 0.01 several
    dilation_radius: int = 1  # voxels the static set grows by before the dynamic cut

    # --- Table S1: training loop ---
    stage1_iterations: int = 30_000  # per state
    stage3_iterations: int = 30_000
    em_interval: int = 500  # E-step and M-step length (one field: the paper studies 50..3000)
    knn_neighbors: int = 3
    # Target views averaged per M-step: single-view noise biases where the motion settles
    # (docs/method.md, "M-step").
    m_step_views: int = 4
    joint_classify_iteration: int = 10_000  # stage-3 iteration
    revolute_eps_deg: float = 10.0
    # [beyond] an ambiguous joint keeps its readings (hinge, slide, stage-2 candidates) and the
    # one the target images prefer wins; False = the paper's ε rule (docs/method.md,
    # "Joint types")
    resolve_ambiguous_joints: bool = True
    # Motion-only steps each reading gets before it is scored, so none wins by a head start;
    # 0 = score the readings as they are (docs/method.md, "Joint types").
    classify_tune_steps: int = 30
    # Relative loss margin a reading against the ε rule (a hinge below ε, a slide of a part
    # that turned beyond it) must win by: the rule as a prior on near-ties, since a tuned hinge
    # contains its slide (docs/method.md, "Joint types").
    small_hinge_margin: float = 0.01
    em_refine_joint_iterations: int = 10_000  # em-refine: joint optimisation before EM starts
    # [beyond] at joint_classify_iteration, a part that another part's motion (or staying put)
    # explains about as well as its own joins that part (docs/method.md, "Parts read twice")
    merge_redundant_parts: bool = True
    # [beyond] at the end of stage 3, a rod-like hinge (a lever) keeps only the swing of its
    # length: its twist about that length is invisible in any image (docs/method.md, "Rods")
    untwist_rods: bool = True
    # [beyond] at the end of stage 3, a hinge or slide within a few degrees of a direction of
    # the body's frame is tried along it, kept unless the images see it worse (docs/method.md,
    # "Axes square to the body")
    square_axes: bool = True
    # [beyond] at the end of stage 3, after the squaring, each hinge searched locally for the
    # turn that lands its part on the target state's stage-1 model, kept when it lands clearly
    # closer and the images do not see it worse (docs/method.md, "Hinges landed on the
    # target's reconstruction")
    land_hinges: bool = True
    # [beyond] at the end of stage 3, after the landing, each hinge's turn tried about the line
    # stage 2 gave it, kept where the images see it better (docs/method.md, "Stage 2's hinge
    # lines tried again")
    recall_hinge_lines: bool = True
    # [beyond] with K estimated, a hinged part tall along its axis enters stage 3 cut in two
    # (doors stacked on one hinge line); the merge of parts read twice joins the halves again
    # when one motion explains both (docs/method.md, "Doors stacked on one hinge line")
    split_stacked_hinges: bool = True

    # --- Table S1: loss weights ---
    lambda_dssim: float = 0.2
    lambda_depth: float = 1.0
    lambda_sam: float = 0.1
    lambda_knn: float = 0.1
    lambda_opacity: float = 0.1  # opacity binarisation BCE
    lambda_anchor: float = 1.0  # canonical anchor (see `anchor`)
    # [beyond] what stage 3 holds the undeformed canonical model to: "images" = the canonical
    # state's own training images; "frozen" (the paper) = the stage-1 canonical model rendered
    # from the target cameras, stage 1's errors included (docs/training.md, "The canonical anchor")
    anchor: str = "images"
    static_class_weight: float = 1.2

    # --- A.2: part-aware refinements ---
    gamma_prism: float = 4.0
    small_part_threshold: int = 2000  # N_thresh: parts below keep their opacity at reset
    pseudo_min_conf: float = 0.5
    pseudo_min_gap: float = 0.2
    pseudo_min_area: int = 50

    # --- densification (stage-1 iterations; stage 3 uses the stage3_* window) ---
    densify_from: int = 500
    densify_until: int = 15_000
    densify_interval: int = 100
    densify_grad_threshold: float = 2e-4
    stage3_densify_until: int = 15_000
    opacity_reset_interval: int = 3000
    percent_dense: float = 0.01  # clone below this fraction of the scene extent, split above
    prune_opacity: float = 0.005
    prune_max_scale: float = 0.1  # fraction of the scene extent
    max_gaussians: int = 1_000_000
    # Also at most this many per pixel of a training view (None: no such cap); the image
    # resolution bounds the detail a model can show (docs/training.md, "Performance").
    max_gaussians_per_pixel: float | None = None

    # --- appearance ---
    # Degree (0..3) of the spherical harmonics that make colours view-dependent: 0 = one colour
    # per Gaussian, no cost; real captures' highlights need 3 (docs/training.md, "sh_degree").
    sh_degree: int = 0

    # --- initialisation (stage 1) ---
    init_voxel_fraction: float = 0.005  # depth back-projection downsampling, x scene extent
    init_max_points: int = 100_000
    random_init_points: int = 100_000  # visual-hull grid cells when the scene has no depth

    # --- learning rates (Adam) ---
    lr_means: float = 1.6e-4  # x scene extent, decays exponentially to lr_means_final
    lr_means_final: float = 1.6e-6
    lr_quats: float = 1e-3
    lr_log_scales: float = 5e-3
    lr_opacity: float = 0.05
    lr_colors: float = 5e-3
    lr_logits: float = 0.05
    lr_sh: float = 1e-3  # the spherical-harmonic coefficients above degree 0
    lr_motion_rot: float = 1e-3
    lr_motion_trans: float = 1e-3  # x scene extent

    # --- bookkeeping ---
    checkpoint_every: int = 5000
    log_every: int = 10
    mesh_voxel: float = 0.004
    mesh_trunc: float = 0.02

    def __post_init__(self) -> None:
        for f in fields(self):
            check_field(f.name, getattr(self, f.name))

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self), indent=2)

    def save(self, path: Path) -> None:
        Path(path).write_text(self.to_json() + "\n")

    def replace(self, **changes: Any) -> TrainConfig:
        return dataclasses.replace(self, **changes)


# Each field's declared type as written ("int", "float | None", ...).
_FIELD_TYPES = {f.name: str(f.type) for f in fields(TrainConfig)}

# Allowed range of every numeric field: (lowest, highest, whether the lowest is allowed).
_AT_LEAST_1 = (1, None, True)
_AT_LEAST_0 = (0, None, True)
_POSITIVE = (0, None, False)
_FRACTION = (0, 1, True)
RANGES: dict[str, tuple[float, float | None, bool]] = {
    "seed": _AT_LEAST_0, "num_parts": _AT_LEAST_1, "voxel_size": _POSITIVE,
    "dilation_radius": _AT_LEAST_0, "stage1_iterations": _AT_LEAST_1,
    "stage3_iterations": _AT_LEAST_1, "em_interval": _AT_LEAST_1, "knn_neighbors": _AT_LEAST_1,
    "m_step_views": _AT_LEAST_1, "joint_classify_iteration": _AT_LEAST_0,
    "revolute_eps_deg": (0, 180, True), "classify_tune_steps": _AT_LEAST_0,
    "small_hinge_margin": _AT_LEAST_0, "em_refine_joint_iterations": _AT_LEAST_0,
    "static_class_weight": _POSITIVE, "gamma_prism": _AT_LEAST_0,
    "small_part_threshold": _AT_LEAST_0, "pseudo_min_conf": _FRACTION,
    "pseudo_min_gap": _FRACTION, "pseudo_min_area": _AT_LEAST_0, "densify_from": _AT_LEAST_0,
    "densify_until": _AT_LEAST_0, "densify_interval": _AT_LEAST_1,
    "densify_grad_threshold": _POSITIVE, "stage3_densify_until": _AT_LEAST_0,
    "opacity_reset_interval": _AT_LEAST_1, "percent_dense": _POSITIVE,
    "prune_opacity": _FRACTION, "prune_max_scale": _POSITIVE, "max_gaussians": _AT_LEAST_1,
    "max_gaussians_per_pixel": _POSITIVE,
    "init_voxel_fraction": _POSITIVE, "init_max_points": _AT_LEAST_1,
    "random_init_points": _AT_LEAST_1, "checkpoint_every": _AT_LEAST_1,
    "log_every": _AT_LEAST_1, "mesh_voxel": _POSITIVE, "mesh_trunc": _POSITIVE,
    "sh_degree": (0, 3, True),
    **{name: _AT_LEAST_0 for name in ("lambda_dssim", "lambda_depth", "lambda_sam",
                                     "lambda_knn", "lambda_opacity", "lambda_anchor")},
    **{name: _POSITIVE for name in ("lr_means", "lr_means_final", "lr_quats", "lr_log_scales",
                                   "lr_opacity", "lr_colors", "lr_logits", "lr_sh",
                                   "lr_motion_rot", "lr_motion_trans")},
}
CHOICES = {"schedule": SCHEDULES, "profile": PROFILES, "anchor": ANCHORS}


def _kind(value: Any) -> str:
    return {bool: "a boolean", str: "a string", int: "an integer", float: "a number",
            type(None): "null"}.get(type(value), f"a {type(value).__name__}")


def check_field(name: str, value: Any) -> None:
    """ValueError naming the field when `value` has the wrong type or is out of range."""
    annotation = _FIELD_TYPES[name]
    wanted = annotation.removesuffix(" | None")
    expected = f"expected {'an' if wanted == 'int' else 'a'} {wanted}"
    if value is None:
        if not annotation.endswith("| None"):
            raise ValueError(f"{name}: {expected}, got null")
        return
    if wanted == "bool":
        ok = isinstance(value, bool)
    elif wanted == "str":
        ok = isinstance(value, str)
    elif wanted == "int":
        ok = isinstance(value, int) and not isinstance(value, bool)
    else:  # float: an integer is a fine number too
        ok = isinstance(value, int | float) and not isinstance(value, bool)
    if not ok:
        raise ValueError(f"{name}: {expected}, got {value!r} ({_kind(value)})")
    if name in CHOICES and value not in CHOICES[name]:
        raise ValueError(f"{name}: must be one of {CHOICES[name]}, got {value!r}")
    if isinstance(value, str | bool):
        return
    if not math.isfinite(value):
        raise ValueError(f"{name}: must be finite, got {value}")
    if name in RANGES:
        low, high, low_allowed = RANGES[name]
        if value < low or (value == low and not low_allowed):
            raise ValueError(f"{name}: must be {'>=' if low_allowed else '>'} {low}, got {value}")
        if high is not None and value > high:
            raise ValueError(f"{name}: must be <= {high}, got {value}")


def _profile_changes(profile: str) -> dict[str, Any]:
    if profile == "full":
        return {}
    if profile == "fast":  # the paper's fast version: 10k + 10k, events rescaled by 1/3
        # At most 8 Gaussians per pixel: no built-in object reaches it at 128² or 256², but a
        # textured real capture grows past 300k without it, at twice the time for the same
        # joints (docs/training.md, "A cap that binds only on real scenes").
        return dict(
            stage1_iterations=10_000, stage3_iterations=10_000, densify_until=5000,
            stage3_densify_until=5000, joint_classify_iteration=3333,
            em_refine_joint_iterations=3333, max_gaussians_per_pixel=8.0,
        )
    if profile == "quick":  # demo / CI: a few hundred iterations, few Gaussians, 64-128 px
        return dict(
            stage1_iterations=300, stage3_iterations=300, em_interval=50,
            densify_from=100, densify_until=250, densify_interval=50,
            stage3_densify_until=150, opacity_reset_interval=100_000,
            joint_classify_iteration=150, em_refine_joint_iterations=100,
            init_max_points=2500, random_init_points=30_000, max_gaussians=4000,
            checkpoint_every=200, mesh_voxel=0.01, mesh_trunc=0.04,
            lr_means=1.6e-3, lr_means_final=1.6e-5, lr_colors=1e-2, lr_motion_rot=3e-3,
            lr_motion_trans=3e-3,
            # 150 iterations before the merge hardly move two halves' motions apart, and a
            # half trained on half of its door cost fridge-180's half-turned door its hinge
            # (docs/method.md, "Doors stacked on one hinge line").
            split_stacked_hinges=False,
        )
    raise ValueError(f"unknown profile {profile!r}; choose one of {PROFILES}")


def make_config(profile: str = "full", overrides: dict[str, Any] | None = None) -> TrainConfig:
    """The profile's config with `overrides` (field -> value) applied on top."""
    config = TrainConfig(profile=profile, **_profile_changes(profile))
    return config.replace(**(overrides or {}))


def load_overrides(path: Path) -> dict[str, Any]:
    """Reads a JSON object of config fields; unknown names are an error naming the file."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError as err:
        raise ValueError(f"{path}: config file not found") from err
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: not valid JSON ({err})") from err
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object of config fields")
    known = {f.name for f in fields(TrainConfig)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise ValueError(f"{path}: unknown config fields {unknown}")
    for name, value in data.items():
        try:
            check_field(name, value)
        except ValueError as err:
            raise ValueError(f"{path}: {err}") from None
    return data


def load_config(path: Path) -> TrainConfig:
    """A config saved by `TrainConfig.save` (e.g. OUT_DIR/config.json)."""
    return TrainConfig(**load_overrides(path))
