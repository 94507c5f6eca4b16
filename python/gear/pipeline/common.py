"""What stages 1 and 3 share: training views as tensors, the image loss terms, learning rates,
the non-finite guard and the per-stage random source (docs/architecture.md)."""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import TYPE_CHECKING, TypeVar

import numpy as np
import torch

from gear.camera import Camera
from gear.config import TrainConfig
from gear.losses import composite, depth_log_l1, photometric

if TYPE_CHECKING:
    from gear.splats import Gaussians


class NonFiniteLoss(RuntimeError):
    def __init__(self, stage: str, iteration: int, term: str) -> None:
        super().__init__(
            f"non-finite loss in {stage} at iteration {iteration} (term '{term}'); "
            "the last good checkpoint is kept"
        )
        self.stage, self.iteration, self.term = stage, iteration, term


@dataclass
class TrainView:
    """One training image as torch tensors (converted once)."""

    camera: Camera
    rgb: torch.Tensor  # [H,W,3]
    alpha: torch.Tensor  # [H,W]
    depth: torch.Tensor | None  # [H,W], 0 = missing
    regions: np.ndarray | None  # [H,W] int

    @classmethod
    def from_view(cls, view) -> TrainView:  # noqa: ANN001 (gear.data.View)
        depth = None if view.depth is None else torch.as_tensor(view.depth, dtype=torch.float32)
        return cls(
            view.camera,
            torch.as_tensor(view.rgb, dtype=torch.float32),
            torch.as_tensor(view.alpha, dtype=torch.float32),
            depth,
            view.regions,
        )


def gaussian_lrs(config: TrainConfig, extent: float) -> dict[str, float]:
    return dict(
        means=config.lr_means * extent,
        quats=config.lr_quats,
        log_scales=config.lr_log_scales,
        opacity=config.lr_opacity,
        colors=config.lr_colors,
        logits=config.lr_logits,
        sh=config.lr_sh,
    )


def means_lr(config: TrainConfig, it: int, total: int) -> float:
    """Exponential decay from lr_means to lr_means_final over the stage (times the extent)."""
    f = min(max(it / max(total, 1), 0.0), 1.0)
    return float(np.exp((1 - f) * np.log(config.lr_means) + f * np.log(config.lr_means_final)))


def check_finite(terms: dict[str, torch.Tensor], stage: str, it: int) -> None:
    for name, value in terms.items():
        if not bool(torch.isfinite(value).all()):
            raise NonFiniteLoss(stage, it, name)


def image_terms(out, view: TrainView, background: torch.Tensor, config: TrainConfig):  # noqa: ANN001, ANN201
    """Photometric (L1 + D-SSIM) term of a render against `view` over `background`, plus the
    depth term when both have depth."""
    target = composite(view.rgb, view.alpha, background)
    terms = {"rgb": photometric(out.features[..., :3], target, config.lambda_dssim)}
    if view.depth is not None and out.depth is not None:
        terms["depth"] = config.lambda_depth * depth_log_l1(out.depth, view.depth)
    return terms


Item = TypeVar("Item")
Result = TypeVar("Result")

# The one worker thread of map_beside (started on first use).
_BESIDE = ThreadPoolExecutor(max_workers=1, thread_name_prefix="gear-beside")
_on_worker = threading.local()


def map_beside(work: Callable[[Item], Result], items: Sequence[Item]) -> list[Result]:
    """[work(item) for item in items], every second item on a worker thread beside the
    caller. The native ops (rasterizer, SSIM, deformation) release Python's lock and give the
    same bits on any thread, so independent work (two states' steps, one step's views) comes
    out exactly as in turn, while one item's single-threaded torch part runs beside the other's
    multi-threaded native part, which the cores otherwise leave half idle. torch's grad mode,
    which is per thread, is the caller's on the worker too. The caller waits for the worker's
    items before anything else happens, even when its own raise. Called from the worker (work
    inside work), or inside `in_turn()`, it runs everything in turn."""
    if len(items) < 2 or getattr(_on_worker, "active", False):
        return [work(item) for item in items]
    grad = torch.is_grad_enabled()

    def on_worker(item: Item) -> Result:
        _on_worker.active = True
        with torch.set_grad_enabled(grad):
            return work(item)

    elsewhere = [_BESIDE.submit(on_worker, item) for item in items[1::2]]
    try:
        here = [work(item) for item in items[0::2]]
    finally:
        there = [f.result() for f in elsewhere]
    return [here[i // 2] if i % 2 == 0 else there[i // 2] for i in range(len(items))]


@contextlib.contextmanager
def in_turn() -> Iterator[None]:
    """Inside it, map_beside runs every item on the calling thread, in turn (same results): for
    a profiler that sees only the thread it was started on."""
    before = getattr(_on_worker, "active", False)
    _on_worker.active = True
    try:
        yield
    finally:
        _on_worker.active = before


class Iterating:
    """What the runner asks of an iterative stage beside its steps, as a stage without
    sub-phases answers it; and its log events."""

    name = "stage"

    def __init__(self) -> None:
        self.events: list[dict] = []  # densify / reset / classification events for the log

    def phase(self, it: int) -> str | None:
        """The sub-phase at iteration `it` (stage 3's E/M/J), None for a stage without."""
        return None

    def status(self) -> str | None:
        """A few words for the progress bar, beside the loss terms."""
        return None

    def snapshot(self) -> dict:
        """What the log records at each phase change."""
        return {}


class Stage(Iterating):
    """What a stage's per-iteration object shares: its config, its log events and its own
    torch.Generator. Every random draw of a stage (view choice, background, split offsets)
    comes from that generator, which is checkpointed, so seeded runs resume identically."""

    gaussians: Gaussians  # what the stage trains, set by each stage

    def __init__(self, config: TrainConfig, seed: int) -> None:
        super().__init__()
        self.config = config
        self.generator = torch.Generator().manual_seed(seed)

    def pick_index(self, count: int) -> int:
        return int(torch.randint(count, (1,), generator=self.generator))

    def pick(self, views: Sequence[TrainView]) -> TrainView:
        return views[self.pick_index(len(views))]

    def background(self) -> torch.Tensor:
        return torch.rand(3, generator=self.generator)

    def gaussian_count(self) -> int:
        """How many Gaussians the stage trains (the log and the progress bar show it)."""
        return len(self.gaussians)
