"""Stage 3's M-step: only the part motions learn, under hard assignment, with every Gaussian
parameter held (docs/method.md, "Stage 3: M-step")."""

from __future__ import annotations

from gear.pipeline.common import check_finite
from gear.pipeline.stage3.shared import RefineState


def motion_step(state: RefineState, it: int) -> dict[str, float]:
    """The motion of `state` alone has to explain `m_step_views` target views: holding the
    Gaussians keeps them from absorbing the motion's error, and saves the anchor render and
    their backward (docs/method.md, "Stage 3: M-step")."""
    drawn = [state.target_view()[1:] for _ in range(state.config.m_step_views)]
    state.motion_optimizer.zero_grad(set_to_none=True)
    terms = state.held_image_step(state.motion, *zip(*drawn, strict=True))
    check_finite(terms, state.name, it)
    state.step_motion()
    return {k: v.item() for k, v in terms.items()}
