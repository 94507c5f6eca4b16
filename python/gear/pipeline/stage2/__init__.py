"""Stage 2: coarse parts and motions from the two states' stage-1 models (docs/method.md)."""

from gear.pipeline.stage2.initialise import Stage2Result, initialise_parts

__all__ = ["Stage2Result", "initialise_parts"]
