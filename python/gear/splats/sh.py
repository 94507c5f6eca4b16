"""View-dependent colour of a set of Gaussians (docs/training.md, "sh_degree").

With `sh_degree` = d > 0 the Gaussians carry `sh` [N, (d+1)^2 - 1, 3]: the spherical-harmonic
coefficients above degree 0, initialised at zero, with their own learning rate (`lr_sh`);
densification, pruning and checkpoints treat them like every other parameter. The degree-0
term stays the existing colour (`colors`, logits of RGB), so a model with zero coefficients
renders exactly as without them, and at d = 0 nothing here runs.

Each render evaluates the colours for its camera (gear.sh.sh_to_rgb) along the direction from
the Gaussian to the camera centre, taken in the canonical frame the coefficients were learned
in: a posed Gaussian's direction is turned back by its part's rotation, so a moved door keeps
its highlights attached to it and the pose receives the colour's gradient too.
"""

from __future__ import annotations

import torch

from gear.camera import Camera
from gear.kinematics import quat_conj, quat_mul, quat_normalize, quat_rotate
from gear.sh import SH_C0, coefficient_count, sh_to_rgb
from gear.splats.gaussians import Gaussians

SH_PARAM = "sh"


def add_sh(g: Gaussians, degree: int, lr: float) -> None:
    """Gives `g` zero coefficients of degrees 1..`degree` (nothing at degree 0 or when it
    already has them, e.g. a resumed model)."""
    if degree == 0 or SH_PARAM in g.params:
        return
    g.add_param(SH_PARAM, torch.zeros(len(g), coefficient_count(degree) - 1, 3), lr)


def view_rgb(
    splats: object,
    rgb: torch.Tensor,
    camera: Camera,
    means: torch.Tensor,
    quats: torch.Tensor,
    canonical_quats: torch.Tensor,
    detach: bool = False,
) -> torch.Tensor:
    """The colours [N,3] of `splats` seen from `camera`: `rgb` itself when they carry no
    higher-order coefficients, else the spherical-harmonic colour with `rgb` as its degree-0
    term. `means` / `quats` are what is drawn, `canonical_quats` the stored orientations (the
    same tensor when unposed); `detach` keeps gradients from the stored coefficients."""
    params = getattr(splats, "params", None)
    rest = None if params is None else params.get(SH_PARAM)
    if rest is None:
        return rgb
    if detach:
        rest = rest.detach()
    centre = torch.as_tensor(camera.center, dtype=means.dtype)
    dirs = centre - means
    if quats is not canonical_quats:
        # Posed: q = r * q_canonical, so q_canonical * q^-1 = r^-1 turns the direction back.
        undo = quat_mul(quat_normalize(canonical_quats), quat_conj(quat_normalize(quats)))
        dirs = quat_rotate(undo, dirs)
    dc = ((rgb - 0.5) / SH_C0)[:, None, :]
    return sh_to_rgb(dirs.contiguous(), torch.cat([dc, rest], dim=1))
