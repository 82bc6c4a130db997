"""Seam share: how much of the root's acceleration falls at the seams between latent blocks.

The VAE decodes each latent token to s frames (the stride). When consecutive tokens disagree on
where the body is, the whole body jumps between the last frame of one block and the first of the
next, and a jump of the root between frames t-1 and t puts its acceleration on the second
differences centred on t-1 and t. Motion without seams spreads its acceleration evenly over the
s phases of a block, so those two phases hold 2 / s of it (0.5 at the paper's s = 4); the
fixture benchmark's shipped model put 0.95 there before its decoder continued the motion across
seams (docs/results.md, sixteenth run). FGD_acc counts the same jumps among everything else; this
column says whether they are seams. At s = 2 every second difference is centred on a block's first
or last frame, so it reads 1 whatever the motion: it tells seams apart from s = 3 on.
"""

from __future__ import annotations

import numpy as np

from sarah_data.constants import JOINT
from sarah_data.skeleton import ROOT

from .spec import Metric


def seam_share(joint_positions, block_frames: int, root_joint: str = ROOT) -> float:
    """Share of the root's squared acceleration on the second differences centred on the last
    and the first frame of a block (frame 0 starts a block); 2 / block_frames without seams."""
    p = np.asarray(joint_positions, dtype=np.float64)[:, JOINT[root_joint]]
    return points_seam_share(p, block_frames)


def points_seam_share(points, block_frames: int) -> float:
    """``seam_share`` of any points (T, ..., 3) together: the share of their squared
    acceleration on the second differences centred on a block's last or first frame."""
    p = np.asarray(points, dtype=np.float64)
    if block_frames < 2:
        raise ValueError(f"seam_share needs blocks of at least 2 frames, got {block_frames}")
    if len(p) < block_frames + 2:
        raise ValueError(f"seam_share needs at least {block_frames + 2} frames, got {len(p)}")
    energy = ((p[2:] - 2.0 * p[1:-1] + p[:-2]) ** 2).reshape(len(p) - 2, -1).sum(axis=-1)
    centre = np.arange(1, len(p) - 1)  # the frame each second difference is centred on
    at_seam = (centre % block_frames == 0) | (centre % block_frames == block_frames - 1)
    total = energy.sum()
    return float(energy[at_seam].sum() / total) if total > 0 else 2.0 / block_frames


METRIC = Metric(name="seam_share", label="Seam Share", kind="clip", order=90, unit="fraction",
                decimals=2, better="lower", value_range=" ∈ [0, 1]",
                function=lambda clip, config: seam_share(clip.joints[0], config.block_frames,
                                                         config.root_joint))
