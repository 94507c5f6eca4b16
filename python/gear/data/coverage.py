"""What a scene's optional inputs cover, and warnings where training would use them only in part.

Training decides per view what to use: stage 1 initialises a state from depth back-projection
only when every training view of that state has depth (else from the masks' visual hull) and
adds the depth loss on the views that have it; the part losses use region masks on the views
that have them. A scene where some views lack depth or region masks therefore trains
differently from what its owner may expect, and `gear check` and `gear train` say so.
"""

from __future__ import annotations

from gear.data.scene import STATES, Scene, View

SHOWN = 3  # view names listed in a warning before "..."
# Below this fraction of object pixels with depth, the depth initialisation and loss see only
# part of the object (a depth map cut off, wrongly scaled to zeros, or masks that do not match).
LOW_DEPTH_FRACTION = 0.5


def _names(views: list[View]) -> str:
    names = [v.name for v in views[:SHOWN]]
    return ", ".join(names) + (" ..." if len(views) > SHOWN else "")


def count(views: list[View], kind: str) -> int:
    """How many of `views` have the optional input `kind` ("depth", "regions", "parts")."""
    return sum(getattr(v, kind) is not None for v in views)


def depth_on_object(views: list[View]) -> float | None:
    """The fraction of the object pixels (mask above half) of `views` that have depth (> 0),
    over the views that have a depth map; None when none has."""
    pairs = [(v.alpha > 0.5, v.depth) for v in views if v.depth is not None]
    total = sum(int(mask.sum()) for mask, _ in pairs)
    if not total:
        return None
    return sum(int((mask & (depth > 0)).sum()) for mask, depth in pairs) / total


def inputs_used(scene: Scene) -> str:
    """One line saying what training uses of the scene (said at the start of training)."""
    parts = []
    for state in STATES:
        views = scene.train(state)
        depth, regions = count(views, "depth"), count(views, "regions")
        on_object = depth_on_object(views)
        depth_text = f"depth on {depth}" + (
            f" ({100 * on_object:.0f}% of object pixels)" if on_object is not None else "")
        parts.append(f"{state}: {len(views)} training views with object masks, {depth_text}, "
                     f"region masks on {regions}")
    return "inputs: " + "; ".join(parts) + " (GT part ids and test views are never trained on)"


def input_warnings(scene: Scene) -> list[str]:
    """The loader's warnings, then one per state whose training views have depth or region
    masks only in part, and one when one state has depth and the other has none."""
    out = list(scene.warnings)
    for state in STATES:
        views = scene.train(state)
        lacking_depth = [v for v in views if v.depth is None]
        if lacking_depth and len(lacking_depth) < len(views):
            out.append(
                f"depth on {len(views) - len(lacking_depth)} of {len(views)} {state} training "
                f"views (none on {_names(lacking_depth)}): {state} starts from the masks' visual "
                "hull instead of depth, and the depth loss covers only the views with depth"
            )
        lacking_regions = [v for v in views if v.regions is None]
        if lacking_regions and len(lacking_regions) < len(views):
            out.append(
                f"region masks on {len(views) - len(lacking_regions)} of {len(views)} {state} "
                f"training views (none on {_names(lacking_regions)}): the part losses use only "
                "the views with region masks"
            )
    for state in STATES:
        on_object = depth_on_object(scene.train(state))
        if on_object is not None and on_object < LOW_DEPTH_FRACTION:
            out.append(f"depth covers only {100 * on_object:.0f}% of the object pixels of the "
                       f"{state} training views (0 = no depth): check the depth maps' scale "
                       "and that they match the masks")
    with_some = [s for s in STATES if count(scene.train(s), "depth")]
    if len(with_some) == 1:
        other = next(s for s in STATES if s not in with_some)
        out.append(f"depth on {with_some[0]} views only, none on {other}: the states are "
                   f"initialised differently ({other} from the masks' visual hull)")
    regions_some = [s for s in STATES if count(scene.train(s), "regions")]
    if len(regions_some) == 1:
        other = next(s for s in STATES if s not in regions_some)
        out.append(f"region masks on {regions_some[0]} views only, none on {other}: the part "
                   f"losses are used only when {regions_some[0]} is the canonical state")
    return out
