"""gear: articulated digital twins from two articulation states with Gaussian splatting."""

from gear._core import __version__

__all__ = ["__version__"]
