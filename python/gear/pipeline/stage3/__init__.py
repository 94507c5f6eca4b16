"""Stage 3: EM refinement of parts and motions, and the joint-type decision (docs/method.md)."""

from gear.pipeline.stage3.refine import Refine, Stage3Result, refine_parts

__all__ = ["Refine", "Stage3Result", "refine_parts"]
