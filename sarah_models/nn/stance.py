"""Stance: which foot is planted, frame by frame, read from the latent tokens.

Not in the paper. The benchmark's decoders never take a step: around the data's step onsets
their feet glide from 0.65 to 0.78 m/s where the data's go from 0 to 2.7, and every step the
foot lock made was timed by how far a gliding foot had drifted, 1.7-2.3x as many as the data's
and half as long (docs/results.md, sixty-ninth run). The latent knows when a step happens (a
decoder weighted to the legs steps at the data's moments, with the feet confused), so a small
head says it outright: per frame and per foot, planted or swinging, trained with a binary
cross-entropy against the data's own stance (``stance_of``). The foot lock then steps when the
stance lifts (``sampling.foot_lock``); with the data's stance, a VAE's reconstruction of the
data through the benchmark's chain came from FGD_acc 624 to 278 (seventieth run).

The head is causal over tokens (two convolutions that see the last ``RECEPTIVE_TOKENS``
tokens), so a stream reads a token's stance from the tokens it has (``StanceHead.last``) and
gets the offline pass's values.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from sarah_data.constants import FPS
from sarah_data.skeleton import FEET, MotionLayout

# m/s: a foot moving slower than this on the floor plane is planted. The data's steps travel
# 0.38 m in 5 frames above it (peak 4.9 m/s); a planted foot's jitter stays far below it.
STANCE_SPEED = 0.15
WIDTH = 256  # channels of the head's two convolutions
FIRST_REACH, SECOND_REACH = 4, 3  # tokens each convolution sees
RECEPTIVE_TOKENS = FIRST_REACH + SECOND_REACH - 1


def stance_of(motion: Tensor, layout: MotionLayout) -> Tensor:
    """(B, T, Dx) motion in metres -> (B, T, feet) 1.0 where the foot is planted: its horizontal
    speed from the frame before under ``STANCE_SPEED`` (frame 0: planted); a single frame that
    disagrees with the frames on both sides of it takes theirs (a blip is not a step)."""
    feet = layout.joint_positions(motion, FEET)[..., [0, 2]]
    speed = (feet[:, 1:] - feet[:, :-1]).norm(dim=-1) * FPS
    planted = torch.cat([torch.ones_like(speed[:, :1]), (speed < STANCE_SPEED).to(speed.dtype)], 1)
    before, here, after = planted[:, :-2], planted[:, 1:-1], planted[:, 2:]
    blip = (before == after) & (here != before)
    return torch.cat([planted[:, :1], torch.where(blip, before, here), planted[:, -1:]], 1)


class StanceHead(nn.Module):
    """Latent tokens (B, K, Dz) -> stance logits (B, K * stride, feet), causal over tokens."""

    def __init__(self, latent_dim: int, stride: int, feet: int = len(FEET)) -> None:
        super().__init__()
        self.stride, self.feet = stride, feet
        self.first = nn.Conv1d(latent_dim, WIDTH, FIRST_REACH)
        self.second = nn.Conv1d(WIDTH, WIDTH, SECOND_REACH)
        self.out = nn.Linear(WIDTH, stride * feet)

    def forward(self, z: Tensor) -> Tensor:
        x = z.transpose(1, 2)
        x = F.gelu(self.first(F.pad(x, (FIRST_REACH - 1, 0))))
        x = F.gelu(self.second(F.pad(x, (SECOND_REACH - 1, 0))))
        logits = self.out(x.transpose(1, 2))  # (B, K, stride * feet)
        return logits.view(z.shape[0], -1, self.feet)

    def last(self, tokens: Tensor) -> Tensor:
        """The newest token's stride frames (B, stride, feet) from the tokens so far (B, K, Dz),
        of which only the last ``RECEPTIVE_TOKENS`` matter: what ``forward`` gives that token."""
        return self(tokens[:, -RECEPTIVE_TOKENS:])[:, -self.stride:]

    @staticmethod
    def planted(logits: Tensor) -> Tensor:
        return logits > 0.0
