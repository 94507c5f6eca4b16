"""Built-in procedural articulated objects (z up, front facing -y, floor at z = 0).

Each builder takes a seeded generator (colours and small appearance changes vary with the seed;
the geometry and joints do not) and returns an `Articulated` whose joints have real limits and
two states inside them.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from gear.synth.model import Articulated, Joint, Part
from gear.synth.shapes import box, cylinder, shell, tint

Rng = np.random.Generator
DOWN = np.array([0.0, 0.0, -1.0])
UP = np.array([0.0, 0.0, 1.0])
OUT = np.array([0.0, -1.0, 0.0])  # towards the front


def _metal(rng: Rng) -> np.ndarray:
    return tint(rng, 0.6, 0.08, 0.35)


def _door(
    name: str,
    width: float,
    height: float,
    thick: float,
    x0: float,
    front_y: float,
    z0: float,
    hinge: str,
    color: np.ndarray,
    rng: Rng,
    limits: tuple[float, float],
    states: tuple[float, float],
    hinge_at_front: bool = False,
) -> Part:
    """A vertical door covering x in [x0, x0+width], z in [z0, z0+height], its back face at
    `front_y`, hinged on its "left" or "right" edge, opening outwards for positive values."""
    y = front_y - thick / 2
    surfaces = [box((width, thick, height), (x0 + width / 2, y, z0 + height / 2), color, rng)]
    handle_x = x0 + width - 0.06 if hinge == "left" else x0 + 0.06
    handle_h = min(0.3, height * 0.5)
    surfaces.append(
        box(
            (0.025, 0.03, handle_h),
            (handle_x, front_y - thick - 0.015, z0 + height / 2),
            _metal(rng),
            rng,
        )
    )
    hinge_x = x0 if hinge == "left" else x0 + width
    hinge_y = front_y - thick if hinge_at_front else front_y
    axis = DOWN if hinge == "left" else UP
    joint = Joint(name, "revolute", np.array([hinge_x, hinge_y, 0.0]), axis, *limits, *states)
    return Part(joint, surfaces)


def _drawer(
    name: str,
    width: float,
    height: float,
    depth: float,
    cx: float,
    front_y: float,
    z0: float,
    color: np.ndarray,
    rng: Rng,
    states: tuple[float, float],
) -> Part:
    """An open-top drawer whose front panel closes flush at `front_y` (slides along -y)."""
    t = 0.015
    inner = color * 0.85
    y_mid = front_y + depth / 2
    surfaces = [
        box((width, t * 1.5, height), (cx, front_y + t * 0.75, z0 + height / 2), color, rng),
        box((width - 0.02, depth, t), (cx, y_mid, z0 + t / 2 + 0.01), inner, rng),
        box(
            (t, depth, height * 0.7),
            (cx - width / 2 + 0.01 + t / 2, y_mid, z0 + height * 0.35 + 0.01),
            inner,
            rng,
        ),
        box(
            (t, depth, height * 0.7),
            (cx + width / 2 - 0.01 - t / 2, y_mid, z0 + height * 0.35 + 0.01),
            inner,
            rng,
        ),
        box(
            (width - 0.02, t, height * 0.7),
            (cx, front_y + depth - t / 2, z0 + height * 0.35 + 0.01),
            inner,
            rng,
        ),
        box(
            (min(0.2, width * 0.4), 0.025, 0.025),
            (cx, front_y - 0.0125, z0 + height / 2),
            _metal(rng),
            rng,
        ),
    ]
    joint = Joint(name, "prismatic", np.array([cx, front_y, z0]), OUT, 0.0, depth * 0.9, *states)
    return Part(joint, surfaces)


def fridge(rng: Rng) -> Articulated:
    w, d, h, t = 0.7, 0.65, 1.5, 0.03
    body_c, door_c = tint(rng, 0.55, 0.1, 0.85), tint(rng, 0.55, 0.12, 0.78)
    static = shell((w, d, h), (0, 0, h / 2), t, body_c, rng)
    static += [
        box((w - 2 * t, d - 2 * t, 0.015), (0, t / 2, z), tint(rng, 0.15, 0.3, 0.7), rng)
        for z in (0.5, 1.0)
    ]
    door = _door(
        "door", w, h, 0.05, -w / 2, -d / 2, 0.0, "left", door_c, rng, (0.0, 2.0), (0.15, 1.3)
    )
    return Articulated("fridge", static, [door])


def drawer_cabinet(rng: Rng) -> Articulated:
    w, d, h, t = 0.8, 0.5, 0.9, 0.025
    body_c, front_c = tint(rng, 0.08, 0.45, 0.6), tint(rng, 0.1, 0.35, 0.8)
    static = shell((w, d, h), (0, 0, h / 2), t, body_c, rng)
    rows = [t + i * (h - 2 * t) / 3 for i in range(3)]
    drawer_h = (h - 2 * t) / 3 - 0.01
    parts = []
    for i, z0 in enumerate(rows):
        drawer = _drawer(
            f"drawer_{i}",
            w - 2 * t - 0.01,
            drawer_h,
            d - 0.06,
            0,
            -d / 2,
            z0 + 0.005,
            front_c,
            rng,
            (0.05, 0.3) if i == 1 else (0.0, 0.0),
        )
        if i == 1:
            parts.append(drawer)
        else:  # closed drawers that never move belong to the static body
            static += drawer.surfaces
    return Articulated("drawer_cabinet", static, parts)


def laptop(rng: Rng) -> Articulated:
    w, d, base_t, lid_t = 0.5, 0.35, 0.025, 0.015
    shell_c = tint(rng, 0.6, 0.05, 0.55)
    static = [
        box((w, d, base_t), (0, 0, base_t / 2), shell_c, rng),
        box(
            (w * 0.85, d * 0.45, 0.003),
            (0, d * 0.1, base_t + 0.0015),
            tint(rng, 0.6, 0.1, 0.2),
            rng,
        ),
        box(
            (w * 0.3, d * 0.22, 0.002),
            (0, -d * 0.3, base_t + 0.001),
            tint(rng, 0.6, 0.05, 0.45),
            rng,
        ),
    ]
    lid_z = base_t + lid_t / 2 + 0.002
    lid = [
        box((w, d, lid_t), (0, 0, lid_z), shell_c * 1.05, rng),
        box(
            (w * 0.9, d * 0.85, 0.002),
            (0, 0.005, lid_z - lid_t / 2 - 0.001),
            tint(rng, 0.62, 0.5, 0.3),
            rng,
            pattern=0.35,
        ),
    ]
    joint = Joint(
        "hinge",
        "revolute",
        np.array([0.0, d / 2, base_t + 0.002]),
        np.array([-1.0, 0, 0]),
        0.0,
        2.3,
        1.2,
        1.9,
    )
    return Articulated("laptop", static, [Part(joint, lid)])


def box_lid(rng: Rng) -> Articulated:
    w, d, h, t = 0.5, 0.4, 0.3, 0.02
    body_c = tint(rng, 0.3, 0.45, 0.6)
    static = shell((w, d, h), (0, 0, h / 2), t, body_c, rng, open_side="+z")
    lid = [
        box((w, d, t), (0, 0, h + t / 2), tint(rng, 0.32, 0.5, 0.5), rng),
        box((0.12, 0.03, 0.025), (0, -d / 2 + 0.04, h + t + 0.0125), _metal(rng), rng),
    ]
    joint = Joint(
        "lid", "revolute", np.array([0.0, d / 2, h]), np.array([-1.0, 0, 0]), 0.0, 1.9, 0.1, 1.5
    )
    return Articulated("box_lid", static, [Part(joint, lid)])


def oven(rng: Rng) -> Articulated:
    w, d, h, t = 0.6, 0.6, 0.85, 0.03
    body_c = tint(rng, 0.0, 0.05, 0.8)
    door_h, z0 = 0.6, 0.05
    static = shell(
        (w, d, door_h + 0.02), (0, 0, z0 + door_h / 2), t, tint(rng, 0.05, 0.2, 0.3), rng
    )
    static += [
        box((w, d, z0), (0, 0, z0 / 2), body_c, rng),
        box((w, d, h - z0 - door_h - 0.02), (0, 0, (h + z0 + door_h + 0.02) / 2), body_c, rng),
        box((w - 2 * t, d - 2 * t, 0.01), (0, 0.01, z0 + 0.25), _metal(rng), rng),
    ]
    panel_z = (h + z0 + door_h + 0.02) / 2
    static += [
        cylinder(0.025, 0.03, (x, -d / 2 - 0.015, panel_z), "y", tint(rng, 0.0, 0.0, 0.15), rng)
        for x in (-0.18, -0.06, 0.06, 0.18)
    ]
    door_c = tint(rng, 0.0, 0.05, 0.7)
    door = [
        box((w, 0.04, door_h), (0, -d / 2 - 0.02, z0 + door_h / 2), door_c, rng),
        box(
            (w * 0.6, 0.005, door_h * 0.4),
            (0, -d / 2 - 0.0425, z0 + door_h * 0.5),
            tint(rng, 0.6, 0.3, 0.15),
            rng,
        ),
        box((w * 0.7, 0.03, 0.025), (0, -d / 2 - 0.06, z0 + door_h - 0.05), _metal(rng), rng),
    ]
    joint = Joint(
        "door", "revolute", np.array([0.0, -d / 2, z0]), np.array([1.0, 0, 0]), 0.0, 1.57, 0.1, 1.35
    )
    return Articulated("oven", static, [Part(joint, door)])


def _door_pair(
    width: float,
    height: float,
    front_y: float,
    z0: float,
    color: np.ndarray,
    rng: Rng,
    left_states: tuple[float, float],
    right_states: tuple[float, float],
) -> list[Part]:
    """Two 3 cm doors of `width` meeting at x = 0, hinged on their outer edges."""
    return [
        _door("door_left", width, height, 0.03, -width, front_y, z0, "left", color, rng,
              (0.0, 2.0), left_states),
        _door("door_right", width, height, 0.03, 0.0, front_y, z0, "right", color, rng,
              (0.0, 2.0), right_states),
    ]


def storage7(rng: Rng) -> Articulated:
    """A cabinet with six moving parts (four drawers, two doors) plus its body: 7 parts."""
    w, d, h, t = 1.0, 0.5, 1.3, 0.025
    body_c, front_c = tint(rng, 0.1, 0.3, 0.75), tint(rng, 0.58, 0.35, 0.65)
    static = shell((w, d, h), (0, 0, h / 2), t, body_c, rng)
    static += [
        box((w - 2 * t, d - t, t), (0, t / 2, 0.75), body_c, rng),
        box((t, d - t, 0.5 - t), (0, t / 2, 1.0), body_c, rng),
        box((w - 2 * t, d - t, t), (0, t / 2, 1.0), body_c, rng),
    ]
    half = (w - 2 * t) / 2
    parts = []
    states = iter([(0.0, 0.25), (0.12, 0.0), (0.05, 0.3), (0.2, 0.1)])
    for z0 in (0.75 + t / 2, 1.0 + t / 2):
        for side in (-1, 1):
            cx = side * (half / 2 + t / 4)
            parts.append(
                _drawer(
                    f"drawer_{len(parts)}",
                    half - 0.02,
                    0.25 - t - 0.01,
                    d - 0.06,
                    cx,
                    -d / 2,
                    z0 + 0.005,
                    front_c,
                    rng,
                    next(states),
                )
            )
    door_h = 0.75 - t - t / 2 - 0.01
    parts += _door_pair(half, door_h, -d / 2, t + 0.005, front_c, rng, (0.2, 1.2), (0.9, 0.3))
    return Articulated("storage7", static, parts)


def double_door(rng: Rng) -> Articulated:
    """Two doors flush against each other in the closed start state."""
    w, d, h, t = 0.9, 0.45, 0.9, 0.025
    static = shell((w, d, h), (0, 0, h / 2), t, tint(rng, 0.75, 0.25, 0.6), rng)
    static.append(box((w - 2 * t, d - t, t), (0, t / 2, h / 2), tint(rng, 0.75, 0.2, 0.5), rng))
    door_c = tint(rng, 0.8, 0.3, 0.75)
    parts = _door_pair(w / 2, h, -d / 2, 0.0, door_c, rng, (0.0, 1.1), (0.0, 0.7))
    return Articulated("double_door", static, parts)


def safe180(rng: Rng) -> Articulated:
    """A safe whose door swings from closed to fully open flat against the front (180 deg)."""
    w, d, h, t = 0.6, 0.6, 0.6, 0.06
    static = shell((w, d, h), (0, 0, h / 2), t, tint(rng, 0.35, 0.3, 0.35), rng)
    static.append(box((w - 2 * t, d - 2 * t, 0.02), (0, t / 2, h / 2), _metal(rng), rng))
    door = _door(
        "door",
        w,
        h,
        0.06,
        -w / 2,
        -d / 2,
        0.0,
        "left",
        tint(rng, 0.35, 0.3, 0.45),
        rng,
        (0.0, np.pi),
        (0.0, np.pi),
        hinge_at_front=True,
    )
    door.surfaces.append(
        cylinder(
            0.06, 0.03, (0.0, -d / 2 - 0.075, h / 2 + 0.1), "y", tint(rng, 0.12, 0.6, 0.7), rng
        )
    )
    return Articulated("safe180", static, [door])


def handle(rng: Rng) -> Articulated:
    """A door panel with a thin lever handle that turns about the axis out of the panel."""
    w, d, h = 0.4, 0.08, 0.6
    static = [
        box((w, d, h), (0, 0, h / 2), tint(rng, 0.1, 0.25, 0.8), rng),
        cylinder(0.035, 0.01, (0.1, -d / 2 - 0.005, 0.35), "y", _metal(rng), rng),
    ]
    lever = [
        cylinder(0.012, 0.05, (0.1, -d / 2 - 0.035, 0.35), "y", _metal(rng), rng),
        box(
            (0.16, 0.018, 0.018), (0.1 - 0.08, -d / 2 - 0.06, 0.35), tint(rng, 0.12, 0.5, 0.6), rng
        ),
    ]
    joint = Joint(
        "lever",
        "revolute",
        np.array([0.1, -d / 2, 0.35]),
        np.array([0.0, 1.0, 0.0]),
        0.0,
        0.9,
        0.0,
        0.8,
    )
    return Articulated("handle", static, [Part(joint, lever)])


BUILDERS: dict[str, tuple[Callable[[Rng], Articulated], str]] = {
    "fridge": (fridge, "one-door fridge (revolute door, shelves inside)"),
    "drawer_cabinet": (
        drawer_cabinet,
        "three-drawer cabinet, the middle drawer slides (prismatic)",
    ),
    "laptop": (laptop, "laptop (revolute lid)"),
    "box_lid": (box_lid, "open box with a hinged lid (revolute)"),
    "oven": (oven, "oven with a bottom-hinged door (revolute)"),
    "storage7": (storage7, "storage cabinet, 7 parts: body, 4 drawers, 2 doors"),
    "double_door": (double_door, "cabinet with two flush doors (2 revolute)"),
    "safe180": (safe180, "safe whose door swings 180 degrees (revolute)"),
    "handle": (handle, "panel with a thin lever handle (small revolute part)"),
}


def build(name: str, seed: int = 0) -> Articulated:
    if name not in BUILDERS:
        raise ValueError(f"unknown object {name!r}; built-in objects: {', '.join(BUILDERS)}")
    return BUILDERS[name][0](np.random.default_rng(seed))


def describe() -> list[tuple[str, str]]:
    return [(name, text) for name, (_, text) in BUILDERS.items()]
