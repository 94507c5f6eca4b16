"""Gaussian splats: the parameters with their optimiser state, the densification strategy,
the initialisation and the one render call (docs/architecture.md)."""

from gear.splats.gaussians import Gaussians
from gear.splats.rendering import StaticLayers, render
from gear.splats.strategy import Densifier, gaussian_budget

__all__ = ["Densifier", "Gaussians", "StaticLayers", "gaussian_budget", "render"]
