"""Classifier-free guidance (3.4): which modalities each branch drops, and how branches combine.

Training drops each modality of ``MODALITIES`` independently with probability ``drop_prob``
(the gaze score with ``gaze_drop_prob`` where set: ``drop_probs``, ``sample_drop_mask``); a
dropped modality's encoding becomes its learned null vector. At inference the conditional pass
sees c = [p_y; a; b; g] with g the target gaze score on every frame; the unconditional pass is
the same with the modalities of ``StreamConfig.guide`` dropped (default: all four, so w = 1.3
guides the conditioning as a whole, as in the paper; with ("gaze",) only gaze control is guided,
and for g = None both passes would be identical, so no guidance at all was applied -- the former
default). Then

    x1 = x1_uncond + w (x1_cond - x1_uncond),     w = cfg_scale (1.3)

With ``StreamConfig.guidance_interval`` (lo, hi) only evaluations at flow times lo <= tau < hi
are guided; the others take x1_cond (w = 1). Both passes run as one batch of 2. At fixed tau
and z_tau the velocity is affine in x1 with the same offset for both passes, so guiding x1 or
guiding v is the same thing. ``gaze=None`` drops g in the conditional pass too (the paper's row
"no gaze"); whenever both passes would be identical, or w = 1 (outside the interval too), only
the conditional pass is run.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..config import FlowConfig
from ..nn.flow import MODALITIES


def drop_probs(config: FlowConfig) -> tuple[float, ...]:
    """Each modality's training drop rate in MODALITIES order: ``drop_prob``, the gaze score's
    ``gaze_drop_prob`` where set."""
    return tuple(config.gaze_drop_prob if name == "gaze" and config.gaze_drop_prob is not None
                 else config.drop_prob for name in MODALITIES)


def sample_drop_mask(batch_size: int, drop_prob: float | tuple[float, ...],
                     generator: torch.Generator | None = None,
                     device: torch.device | str | None = None) -> Tensor:
    """(B, 4) bool: each modality dropped independently with probability ``drop_prob`` (one
    rate, or one per modality in MODALITIES order)."""
    u = torch.rand(batch_size, len(MODALITIES), generator=generator, device=device)
    return u < torch.as_tensor(drop_prob, dtype=u.dtype, device=u.device)


def drop_masks(gaze: float | None, guide: tuple[str, ...], cfg_scale: float) -> Tensor:
    """(B, 4) bool drop masks in MODALITIES order: row 0 conditional, row 1 unconditional.
    B = 1 when the unconditional pass would equal the conditional one (or w = 1)."""
    cond = torch.tensor([name == "gaze" and gaze is None for name in MODALITIES])
    uncond = cond | torch.tensor([name in guide for name in MODALITIES])
    if cfg_scale == 1.0 or torch.equal(cond, uncond):
        return cond[None]
    return torch.stack((cond, uncond))


def scale_at(tau: float, cfg_scale: float, interval: tuple[float, float]) -> float:
    """The guidance scale of an evaluation at flow time tau: w inside the interval, else 1."""
    lo, hi = interval
    return cfg_scale if lo <= tau < hi else 1.0


def branches_run(branches: int, cfg_scale: float) -> int:
    """How many of the ``drop_masks`` branches an evaluation at guidance scale w runs: at w = 1
    (outside the guidance interval too) the conditional one alone, its result being x1_cond."""
    return branches if cfg_scale != 1.0 else 1


def guided(cond: Tensor, uncond: Tensor, cfg_scale: float) -> Tensor:
    """x1 = x1_uncond + w (x1_cond - x1_uncond); x1_cond itself at w = 1 (not rounded)."""
    return cond if cfg_scale == 1.0 else uncond + cfg_scale * (cond - uncond)


def combine(x1: Tensor, cfg_scale: float) -> Tensor:
    """The guided prediction from branches in ``drop_masks`` order (1 or 2) on axis -3:
    x1 (B, L, Dz) -> (L, Dz), or per stream (G, B, L, Dz) -> (G, L, Dz)."""
    if x1.shape[-3] == 2:
        return guided(x1[..., 0, :, :], x1[..., 1, :, :], cfg_scale)
    return x1[..., 0, :, :]
