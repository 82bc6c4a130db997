"""The user's head as seen from where the agent stands: a flow input (``flow.user_relative``).

The flow's user_head input is the user's floor position in the window frame, where the agent
stood at frame 0. Where the agent stands later is only in its own latents, which a walking agent
has to read to know which way goes around its user. With ``FlowConfig.user_relative`` the
user_head encoder also reads, for every frame of block k, the user's head (x, z) less the
agent's pelvis (x, z) at the last frame of block k - 1, in metres; block 0 reads it from the
window origin, where every window's agent starts. Training takes the pelvis from the data's
motion; a stream takes it from the frames it has just decoded (``sampling/stream.py``), so the
agent reads where it really stands, and generation runs block by block, offline too.
"""

from __future__ import annotations

import torch
from torch import Tensor

from sarah_data.skeleton import ROOT, MotionLayout


def pelvis_floor(motion: Tensor) -> Tensor:
    """Motion vectors (..., T, D) in metres -> the pelvis's floor (x, z) path (..., T, 2)."""
    layout = MotionLayout.from_width(motion.shape[-1])
    return layout.joint_positions(motion, [ROOT])[..., 0, :][..., [0, 2]]


def block_starts(floor: Tensor, stride: int) -> Tensor:
    """(B, T, 2) pelvis floor path -> (B, K, 2) where the agent stands as each block begins:
    the origin for block 0, the last frame of block k - 1 for block k."""
    b, t, _ = floor.shape
    if t % stride:
        raise ValueError(f"a floor path of {t} frames is not whole blocks of {stride}")
    return torch.cat([floor.new_zeros(b, 1, 2), floor[:, stride - 1:t - 1:stride]], dim=1)


def user_offset(user_head: Tensor, starts: Tensor, stride: int) -> Tensor:
    """user_head (B, T, 2) floor positions in metres, starts (B, K, 2) from ``block_starts``
    (or a stream's own) -> (B, T, 2): every frame's head less its block's start."""
    b, t, _ = user_head.shape
    if starts.shape != (b, t // stride, 2) or t % stride:
        raise ValueError(f"user_head has {t} frames in blocks of {stride}; block starts have "
                         f"shape {tuple(starts.shape)}, expected ({b}, {t // stride}, 2)")
    return user_head - starts.repeat_interleave(stride, dim=1).to(user_head.dtype)
