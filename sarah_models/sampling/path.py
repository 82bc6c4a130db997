"""The probability path of the flow matcher (paper eq. 4-5): straight lines from noise to data.

Flow time tau runs from 0 (pure noise eps) to 1 (the clean latent z1):

    z_tau = tau z1 + (1 - tau) eps,        dz/dtau = z1 - eps = (z1 - z_tau) / (1 - tau)

The model predicts z1 (x1-prediction), so the velocity a solver integrates is the second form
with the model's z1; 1 - tau is floored at ``min_denominator`` (only tau > 0.95 is affected,
and a midpoint solver on the grid 0, 1/n, ... never evaluates tau = 1). Training
(``training/objectives.py``) and streaming imputation (``solver.imputer``) both form z_tau here.
"""

from __future__ import annotations

import torch
from torch import Tensor


def interpolate(noise: Tensor, data: Tensor, tau: Tensor | float) -> Tensor:
    """z_tau = tau * data + (1 - tau) * noise (``tau`` broadcasts against the latents)."""
    return tau * data + (1 - tau) * noise


def velocity_from_x1(x1: Tensor, z_tau: Tensor, tau: Tensor | float,
                     min_denominator: float) -> Tensor:
    """The velocity implied by an x1 prediction, with 1 - tau floored at ``min_denominator``."""
    tau = torch.as_tensor(tau, device=z_tau.device, dtype=z_tau.dtype)
    while tau.dim() < z_tau.dim():
        tau = tau[..., None]
    return (x1 - z_tau) / (1.0 - tau).clamp_min(min_denominator)
