"""Synthetic articulated scenes: procedural objects and URDF assets rendered with ground truth."""

from gear.synth.effects import EFFECTS, parse_effects
from gear.synth.generate import generate, render_scene
from gear.synth.objects import build, describe

__all__ = ["EFFECTS", "build", "describe", "generate", "parse_effects", "render_scene"]
