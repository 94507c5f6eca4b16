"""The trained articulated twin: canonical Gaussians + part ids + joints, posed at any state.

A finished run's OUT_DIR (docs/training.md, "Outputs") holds `gaussians_canonical.ply`
(standard 3D Gaussian Splatting layout plus an int `part` property), `parts.npy` (part id per
Gaussian) and `joints.json` (start -> end motion of each movable part). `Twin.load(out_dir)`
reads them and `Twin.pose(s)` moves every Gaussian rigidly with its part to state s: 0 is the
start state, 1 the end state, and in between a revolute part has turned by s * angle about its
axis, a prismatic part slid s * distance along its axis (the joint's screw motion, as in
training).

When the PLY carries higher spherical-harmonic bands (`f_rest_*`, degree 1..3) the twin keeps
them in the canonical frame, and every render evaluates them for its camera exactly as training
does (gear.splats.sh.view_rgb); `Twin.posed_sh(s)` gives them turned into a posed state's frame
for files that store posed Gaussians.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from gear.camera import Camera
from gear.kinematics import (
    dq_from_rt,
    dq_to_rt,
    pose_parts,
    quat_from_axis_angle,
    quat_identity,
    quat_to_matrix,
)
from gear.sh import MAX_DEGREE, SH_C0, coefficient_count
from gear.sh_rotation import rotate_sh
from gear.splats.sh import SH_PARAM

PLY_NAME = "gaussians_canonical.ply"
PARTS_NAME = "parts.npy"
JOINTS_NAME = "joints.json"
STATE_VALUE = {"start": 0.0, "end": 1.0}
VISIBLE_OPACITY = 0.1  # Gaussians fainter than this do not decide where the object is
# Vertex properties a Gaussian PLY must carry (3D Gaussian Splatting names).
REQUIRED_PROPERTIES = (
    "x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
    "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
)
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


class TwinError(ValueError):
    """A missing or malformed file in OUT_DIR (the message names it)."""


# ---------------------------------------------------------------- files


def read_ply_vertices(path: Path) -> dict[str, np.ndarray]:
    """The `vertex` element of a PLY file (ascii or binary, scalar properties) as name -> array."""
    if not path.is_file():
        raise TwinError(f"{path}: missing (the canonical Gaussians of a trained run)")
    raw = path.read_bytes()
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise TwinError(f"{path}: not a PLY file (no 'ply' magic or no end_header)")
    body_start = raw.index(b"\n", end) + 1
    lines = raw[:end].decode("ascii", errors="replace").splitlines()
    fmt, elements = None, []  # elements: [name, count, [(prop, dtype)]]
    for line in lines[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format" and len(words) >= 2:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3 and words[2].isdigit():
            elements.append([words[1], int(words[2]), []])
        elif words[0] == "property" and elements:
            if words[1] == "list" or len(words) != 3 or words[1] not in _PLY_TYPES:
                raise TwinError(f"{path}: unsupported property line {line.strip()!r}")
            elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
        else:
            raise TwinError(f"{path}: malformed header line {line.strip()!r}")
    if not elements or elements[0][0] != "vertex":
        raise TwinError(f"{path}: the first element must be 'vertex'")
    _, count, props = elements[0]
    if fmt == "ascii":
        rows = raw[body_start:].decode("ascii", errors="replace").split("\n")[:count]
        try:
            table = np.array([[float(v) for v in r.split()] for r in rows], dtype=np.float64)
        except ValueError:
            raise TwinError(f"{path}: non-numeric vertex data") from None
        if table.shape != (count, len(props)):
            raise TwinError(f"{path}: expected {count} vertices of {len(props)} values")
        return {name: table[:, i].astype(t) for i, (name, t) in enumerate(props)}
    order = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(fmt or "")
    if order is None:
        raise TwinError(f"{path}: unknown PLY format {fmt!r}")
    dtype = np.dtype([(name, order + t) for name, t in props])
    if len(raw) - body_start < count * dtype.itemsize:
        raise TwinError(f"{path}: truncated ({count} vertices announced, file too short)")
    data = np.frombuffer(raw, dtype=dtype, count=count, offset=body_start)
    return {name: data[name].astype(data[name].dtype.newbyteorder("=")) for name, _ in props}


@dataclass(frozen=True)
class TwinJoint:
    """One joints.json entry: the start -> end motion of part `part`.

    `amount` is the revolute angle in degrees (right-hand rule about `axis`) or the prismatic
    travel along `axis`; `origin` is a point on the axis.
    """

    part: int
    type: str
    axis: np.ndarray  # [3] unit
    origin: np.ndarray  # [3]
    amount: float

    def motion(self, fraction: float) -> tuple[np.ndarray, np.ndarray]:
        """(R [3,3], t [3]) float64 of `fraction` of the start -> end motion (any sign: -1 is
        end -> start)."""
        qr, qd = self.dual_quaternion(fraction)
        return quat_to_matrix(qr).numpy(), dq_to_rt(qr, qd)[1].numpy()

    def dual_quaternion(self, fraction: float) -> tuple[torch.Tensor, torch.Tensor]:
        """The same motion as a unit dual quaternion (float64), the form kinematics blends.

        Built from the axis and the scaled amount rather than by kinematics.dq_sclerp of the
        full motion: ScLERP follows the shorter screw, which would turn a joint of more than
        180 degrees the wrong way, and a canonical "end" state needs negative fractions. For
        angles below 180 degrees both agree (tests/test_twin.py checks it).
        """
        axis = torch.as_tensor(self.axis, dtype=torch.float64)
        origin = torch.as_tensor(self.origin, dtype=torch.float64)
        if self.type == "prismatic":
            quat = quat_from_axis_angle(axis, torch.tensor(0.0, dtype=torch.float64))
            return dq_from_rt(quat, axis * self.amount * fraction)
        quat = quat_from_axis_angle(axis, torch.tensor(math.radians(self.amount * fraction),
                                                       dtype=torch.float64))
        rot = quat_to_matrix(quat)
        return dq_from_rt(quat, origin - rot @ origin)


def _vector(value: object, what: str) -> np.ndarray:
    try:
        v = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise TwinError(f"{what}: expected 3 numbers, got {value!r}") from None
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise TwinError(f"{what}: expected 3 finite numbers, got {value!r}")
    return v


def _joint(entry: object, index: int, path: Path) -> TwinJoint:
    what = f"{path}: joints[{index}]"
    if not isinstance(entry, dict):
        raise TwinError(f"{what}: expected an object, got {type(entry).__name__}")
    kind = entry.get("type")
    if kind not in ("revolute", "prismatic"):
        raise TwinError(f"{what}: type must be 'revolute' or 'prismatic', got {kind!r}")
    axis = _vector(entry.get("axis"), f"{what} axis")
    norm = float(np.linalg.norm(axis))
    if norm < 1e-9:
        raise TwinError(f"{what}: axis is the zero vector")
    origin = _vector(entry.get("origin"), f"{what} origin")
    key = "angle_deg" if kind == "revolute" else "distance"
    amount = entry.get(key)
    if isinstance(amount, bool) or not isinstance(amount, (int, float)) or not math.isfinite(
        amount
    ):
        raise TwinError(f"{what}: {key} must be a finite number, got {amount!r}")
    part = entry.get("part", index + 1)
    if isinstance(part, bool) or not isinstance(part, int) or part < 1:
        raise TwinError(f"{what}: part must be an integer >= 1, got {part!r}")
    return TwinJoint(part, kind, axis / norm, origin, float(amount))


def load_joints(out_dir: Path) -> tuple[str, list[TwinJoint]]:
    """(canonical state, joints ordered by part id 1..K-1) from OUT_DIR/joints.json."""
    path = Path(out_dir) / JOINTS_NAME
    if not path.is_file():
        raise TwinError(f"{path}: missing (the joints of a trained run)")
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise TwinError(f"{path}: not valid JSON ({err})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("joints"), list):
        raise TwinError(f"{path}: expected {{\"canonical\": ..., \"joints\": [...]}}")
    canonical = doc.get("canonical", "start")
    if canonical not in STATE_VALUE:
        raise TwinError(f"{path}: canonical must be 'start' or 'end', got {canonical!r}")
    joints = sorted((_joint(e, i, path) for i, e in enumerate(doc["joints"])),
                    key=lambda j: j.part)
    if [j.part for j in joints] != list(range(1, len(joints) + 1)):
        raise TwinError(f"{path}: joint parts must be 1..{len(joints)} once each, got "
                        f"{[j.part for j in joints]}")
    return canonical, joints


# ---------------------------------------------------------------- the twin


def _float_column(props: dict[str, np.ndarray], names: tuple[str, ...]) -> np.ndarray:
    return np.stack([props[n].astype(np.float64) for n in names], axis=1)


@dataclass
class Twin:
    """Canonical Gaussians (float32 torch, [N, ...]) with part ids and the joints moving them."""

    means: torch.Tensor  # [N,3]
    quats: torch.Tensor  # [N,4] (w, x, y, z)
    log_scales: torch.Tensor  # [N,3]
    opacity: torch.Tensor  # [N] logits
    rgb: torch.Tensor  # [N,3] in [0, 1]
    parts: torch.Tensor  # [N] int64: 0 static, k moved by joints[k-1]
    joints: list[TwinJoint]
    canonical: str  # "start" | "end": the state the Gaussians are stored in
    sh: torch.Tensor | None = None  # [N, (d+1)^2 - 1, 3] SH bands 1..d (canonical frame)

    @property
    def params(self) -> dict[str, torch.Tensor]:
        """The stored parameters the renderer looks up beyond `splat_arrays` (as on
        gear.splats.Gaussians): the SH coefficients when the twin has them."""
        return {} if self.sh is None else {SH_PARAM: self.sh}

    @property
    def sh_degree(self) -> int:
        return 0 if self.sh is None else round(math.sqrt(self.sh.shape[1] + 1)) - 1

    @property
    def num_parts(self) -> int:
        return len(self.joints) + 1

    @classmethod
    def load(cls, out_dir: str | Path) -> Twin:
        out_dir = Path(out_dir)
        if not out_dir.is_dir():
            raise TwinError(f"{out_dir}: not a folder (expected a trained run's OUT_DIR)")
        canonical, joints = load_joints(out_dir)
        ply = out_dir / PLY_NAME
        props = read_ply_vertices(ply)
        missing = [n for n in REQUIRED_PROPERTIES if n not in props]
        if missing:
            raise TwinError(f"{ply}: vertex properties {missing} missing (3D Gaussian "
                            "Splatting layout expected)")
        table = _float_column(props, REQUIRED_PROPERTIES)
        if len(table) == 0:
            raise TwinError(f"{ply}: holds no Gaussians")
        bad = ~np.isfinite(table).all(axis=1)
        if bad.any():
            raise TwinError(f"{ply}: {int(bad.sum())} Gaussian(s) with non-finite values "
                            f"(first: vertex {int(np.argmax(bad))})")
        parts = _part_ids(out_dir, props, len(table), len(joints))

        def column(*names: str) -> np.ndarray:
            return _float_column(props, names)

        return cls(
            means=_f32(column("x", "y", "z")),
            quats=_f32(column("rot_0", "rot_1", "rot_2", "rot_3")),
            log_scales=_f32(column("scale_0", "scale_1", "scale_2")),
            opacity=_f32(column("opacity")[:, 0]),
            rgb=_f32(np.clip(0.5 + SH_C0 * column("f_dc_0", "f_dc_1", "f_dc_2"), 0.0, 1.0)),
            parts=torch.as_tensor(parts, dtype=torch.int64),
            joints=joints,
            canonical=canonical,
            sh=_sh_bands(ply, props, len(table)),
        )

    def part_motions(self, s: float) -> tuple[torch.Tensor, torch.Tensor]:
        """Dual quaternions (qr, qd) [K,4] float64 moving each part from the canonical state
        to state s (part 0: identity)."""
        fraction = _check_state(s) - STATE_VALUE[self.canonical]
        static = (quat_identity((), torch.float64), torch.zeros(4, dtype=torch.float64))
        pairs = [static] + [j.dual_quaternion(fraction) for j in self.joints]
        return torch.stack([p[0] for p in pairs]), torch.stack([p[1] for p in pairs])

    def pose(self, s: float) -> tuple[torch.Tensor, torch.Tensor]:
        """(means [N,3], quats [N,4]) float32 of the Gaussians at state s in [0, 1]."""
        qr, qd = self.part_motions(s)
        means, quats = pose_parts(self.means.double(), self.quats.double(), self.parts, qr, qd)
        return means.float(), quats.float()

    def posed_sh(self, s: float) -> torch.Tensor | None:
        """The SH coefficients [N, (d+1)^2 - 1, 3] of the Gaussians posed at state s, in the
        world frame (each part's bands turned with it), or None without them. Rendering does
        not need this (it turns the view direction back instead); a file holding posed
        Gaussians does."""
        if self.sh is None:
            return None
        qr, _ = self.part_motions(s)
        out = self.sh.clone()
        for k in range(self.num_parts):
            rows = self.parts == k
            if k and bool(rows.any()):
                out[rows] = rotate_sh(self.sh[rows], quat_to_matrix(qr[k]))
        return out

    def splat_arrays(self) -> tuple[torch.Tensor, ...]:
        """(means, quats, log_scales, opacity logits, rgb) in the canonical state."""
        return self.means, self.quats, self.log_scales, self.opacity, self.rgb

    def render(self, s: float, camera: Camera, background: torch.Tensor | None = None,  # noqa: ANN201
               depth: bool = False, colors: torch.Tensor | None = None):
        """RenderOutput (features [H,W,C], alpha, depth if asked) of the twin at s: its RGB, or
        `colors` [N,C] per Gaussian (e.g. a colour per part) over `background` [C]."""
        from gear.splats import render

        feats = None if colors is None else colors.float()
        bg = None if background is None else background.float()
        with torch.no_grad():
            return render(self, camera, bg, pose=self.pose(s), features=feats, depth=depth)

    def bounds(self, states: list[float]) -> tuple[np.ndarray, float]:
        """(centre [3], radius) of a sphere holding the visible Gaussians (opacity >= 0.1) at
        every state, with room for their size; the 0.5% farthest are ignored so a stray
        floater does not shrink the object in view."""
        visible = torch.sigmoid(self.opacity) >= VISIBLE_OPACITY
        if int(visible.sum()) < 4:
            visible = torch.ones_like(visible)
        pts = np.concatenate([self.pose(s)[0][visible].numpy() for s in states]).astype(np.float64)
        lo, hi = np.percentile(pts, 0.5, axis=0), np.percentile(pts, 99.5, axis=0)
        center = (lo + hi) / 2
        radius = float(np.percentile(np.linalg.norm(pts - center, axis=1), 99.5))
        size = float(torch.exp(self.log_scales[visible].max(dim=1).values).median())
        return center, max(radius + 2.0 * size, 1e-6)


def _f32(array: np.ndarray) -> torch.Tensor:
    return torch.as_tensor(np.ascontiguousarray(array), dtype=torch.float32)


def _sh_bands(ply: Path, props: dict[str, np.ndarray], n: int) -> torch.Tensor | None:
    """[N, K-1, 3] from the `f_rest_*` properties (channel-major: all of red's coefficients,
    then green's, then blue's), or None when the PLY has none."""
    count = sum(1 for name in props if name.startswith("f_rest_"))
    if count == 0:
        return None
    counts = [3 * (coefficient_count(d) - 1) for d in range(1, MAX_DEGREE + 1)]  # 9, 24, 45
    names = tuple(f"f_rest_{i}" for i in range(count))
    if count not in counts or any(name not in props for name in names):
        raise TwinError(f"{ply}: {count} f_rest_* properties, expected f_rest_0.. with "
                        f"{', '.join(map(str, counts))} of them (3, 8 or 15 per colour channel: "
                        "SH degree 1, 2 or 3)")
    rest = _float_column(props, names)
    bad = ~np.isfinite(rest).all(axis=1)
    if bad.any():
        raise TwinError(f"{ply}: {int(bad.sum())} Gaussian(s) with non-finite f_rest_* values "
                        f"(first: vertex {int(np.argmax(bad))})")
    return _f32(rest.reshape(n, 3, count // 3).transpose(0, 2, 1))


def _check_state(s: float) -> float:
    s = float(s)
    if not (math.isfinite(s) and 0.0 <= s <= 1.0):
        raise ValueError(f"state s must be in [0, 1] (0 = start, 1 = end), got {s}")
    return s


def _part_ids(out_dir: Path, props: dict[str, np.ndarray], n: int, num_joints: int) -> np.ndarray:
    """Part id per Gaussian: the PLY's `part` property and parts.npy, which must agree."""
    ply, npy = out_dir / PLY_NAME, out_dir / PARTS_NAME
    sources = []
    if "part" in props:
        sources.append((ply, props["part"]))
    if npy.is_file():
        try:
            sources.append((npy, np.load(npy, allow_pickle=False)))
        except (OSError, ValueError) as err:
            raise TwinError(f"{npy}: unreadable ({err})") from None
    if not sources:
        raise TwinError(f"{npy}: missing, and {ply} has no 'part' property")
    for path, ids in sources:
        if ids.shape != (n,) or not np.issubdtype(ids.dtype, np.number):
            raise TwinError(f"{path}: expected {n} part ids (one per Gaussian), got shape "
                            f"{ids.shape} of {ids.dtype}")
        if not np.all(np.isfinite(ids)) or np.any(ids != np.round(ids)):
            raise TwinError(f"{path}: part ids must be integers")
        if ids.min() < 0 or ids.max() > num_joints:
            raise TwinError(f"{path}: part ids must be in 0..{num_joints} (joints.json has "
                            f"{num_joints} joint(s)), got {int(ids.min())}..{int(ids.max())}")
    if len(sources) == 2 and not np.array_equal(sources[0][1], sources[1][1]):
        raise TwinError(f"{ply} ('part') and {npy} disagree on "
                        f"{int(np.sum(sources[0][1] != sources[1][1]))} Gaussian(s)")
    return sources[0][1].astype(np.int64)
