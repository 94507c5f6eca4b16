"""Optional imperfections of a generated scene. Every effect is off by default and costs
nothing when off; the default scene is clean."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from gear.synth import regions as reg
from gear.synth.render import Rendered

EFFECTS = {
    "depth-noise": "Gaussian depth noise, sigma 0.4% of the depth",
    "depth-dropout": "missing depth: random pixels, blobs and most depth edges",
    "mask-over": "over-segmented region masks: large regions split into 2-3 pieces",
    "mask-under": "under-segmented region masks: touching regions of two parts merged",
    "mask-jitter": "region boundaries wobble by about 1% of the image size",
    "specular": "Blinn-Phong highlights on top of Lambertian + ambient lighting",
    "background": "a smooth coloured backdrop in RGB behind the object (alpha stays the mask)",
}
DEPTH_SIGMA = 0.004
DROPOUT_PIXELS = 0.02
DROPOUT_EDGE = 0.6


def parse_effects(
    spec: str | list[str] | tuple[str, ...] | frozenset[str] | None,
) -> frozenset[str]:
    """ "depth-noise,mask-over" (or a list of names) -> a validated set of effect names."""
    if spec is None:
        return frozenset()
    names = [n.strip() for n in spec.split(",")] if isinstance(spec, str) else list(spec)
    names = [n for n in names if n]
    unknown = sorted(set(names) - set(EFFECTS))
    if unknown:
        raise ValueError(f"unknown effect(s) {', '.join(unknown)}; known: {', '.join(EFFECTS)}")
    return frozenset(names)


def noisy_depth(depth: np.ndarray, effects: frozenset[str], rng: np.random.Generator) -> np.ndarray:
    if not effects & {"depth-noise", "depth-dropout"}:
        return depth
    out = depth.copy()
    valid = out > 0
    if "depth-noise" in effects:
        out[valid] *= 1.0 + DEPTH_SIGMA * rng.normal(size=int(valid.sum()))
    if "depth-dropout" in effects:
        drop = rng.random(out.shape) < DROPOUT_PIXELS
        gy, gx = np.gradient(np.where(valid, depth, depth[valid].max() * 1.5))
        edge = np.hypot(gx, gy) > 0.02 * np.where(valid, depth, 1.0)
        drop |= edge & (rng.random(out.shape) < DROPOUT_EDGE)
        h, w = out.shape
        yy, xx = np.mgrid[0:h, 0:w]
        for _ in range(rng.integers(1, 4)):  # a few holes, as on dark or shiny surfaces
            cy, cx = rng.integers(h), rng.integers(w)
            r = rng.uniform(0.02, 0.06) * max(h, w)
            drop |= (yy - cy) ** 2 + (xx - cx) ** 2 < r * r
        out[drop] = 0.0
    return np.clip(out, 0.0, None)


def flawed_regions(
    regions: np.ndarray, parts: np.ndarray, effects: frozenset[str], rng: np.random.Generator
) -> np.ndarray:
    if "mask-over" in effects:
        regions = reg.over_segment(regions, rng)
    if "mask-under" in effects:
        regions = reg.under_segment(regions, parts, rng)
    if "mask-jitter" in effects:
        regions = reg.jitter_boundaries(regions, rng)
    if effects & {"mask-over", "mask-under", "mask-jitter"}:
        regions = reg.shuffle_ids(regions, rng)
    return regions


def add_background(image: Rendered, rng: np.random.Generator) -> None:
    """Fill background RGB with a smooth random colour field (in place)."""
    h, w = image.alpha.shape
    low = rng.random((4, 4, 3))
    field = ndimage.zoom(low, (h / 4, w / 4, 1), order=1)[:h, :w]
    bg = image.alpha == 0
    image.rgb[bg] = field[bg].astype(np.float32)
