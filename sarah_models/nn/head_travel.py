"""How much the user has been walking: a running mean of the user's head speed over the floor.

Not in the paper (``FlowConfig.head_travel_seconds``). In dyadic capture one partner often walks
while the other turns in place, and which one the agent is holds for a whole sequence. A flow
whose attention reaches a few seconds back cannot see it: between the walker's arcs both
partners stand (docs/results.md, forty-first and forty-seventh runs). This feature carries it at
a constant cost per frame, for streams of any length.

At frame t it is the exponentially weighted mean of the head's floor speed over the frames so
far (time constant ``seconds``), divided by the weights' sum, so that a stream's first seconds
read as the mean of what there is rather than as a walk slowly fading in. A stream's first frame
has no step behind it: weight 0, value 0. The state after any frame is three numbers per stream,
so a stream fed block by block computes what one call over the whole stream computes, up to
float rounding (tests/test_flow.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from sarah_data.constants import FPS

# Frames per exact scan step: exp(CHUNK / (FPS * seconds)) must stay far from float64's range.
CHUNK = 512


@dataclass(frozen=True)
class TravelState:
    """Where a stream's running mean stands after its latest frame."""

    last: Tensor  # (B, 2) the latest head position
    total: Tensor  # (B, 1) the weighted sum of speeds
    weight: Tensor  # (B, 1) the sum of the weights


def head_travel(user_head: Tensor, seconds: float,
                state: TravelState | None = None) -> tuple[Tensor, TravelState]:
    """user_head (B, T, 2) floor positions (any units) -> (B, T, 1) their running mean speed in
    units per second over about the last ``seconds``, and the state after frame T - 1 (pass it
    with the stream's next frames). ``state`` None: the stream starts at frame 0."""
    if seconds <= 0:
        raise ValueError(f"head_travel needs seconds > 0, got {seconds}")
    b, t, _ = user_head.shape
    if t == 0:
        raise ValueError("head_travel needs at least one frame")
    head = user_head.double()
    decay = math.exp(-1.0 / (seconds * FPS))
    valid = torch.ones(b, t, 1, dtype=head.dtype, device=head.device)
    if state is None:  # the first frame has no step behind it
        previous, total, weight = head[:, :1], head.new_zeros(b, 1), head.new_zeros(b, 1)
        valid[:, 0] = 0.0
    else:
        previous = state.last.double()[:, None]
        total, weight = state.total.double(), state.weight.double()
    steps = torch.linalg.vector_norm(torch.diff(torch.cat([previous, head], 1), dim=1), dim=-1,
                                     keepdim=True) * FPS * valid
    values = []
    for start in range(0, t, CHUNK):
        speed, counted = steps[:, start:start + CHUNK], valid[:, start:start + CHUNK]
        n = speed.shape[1]
        # y_j = decay^j (y_0 + (1 - decay) sum_{i <= j} decay^-i x_i), exact in one cumsum
        grow = decay ** -torch.arange(1, n + 1, dtype=head.dtype, device=head.device)[:, None]
        shrink = 1.0 / grow
        sums = shrink * (total[:, None] + (1 - decay) * torch.cumsum(grow * speed, dim=1))
        weights = shrink * (weight[:, None] + (1 - decay) * torch.cumsum(grow * counted, dim=1))
        values.append(torch.where(weights > 0, sums / weights.clamp_min(1e-300), 0.0))
        total, weight = sums[:, -1], weights[:, -1]
    mean = torch.cat(values, 1).to(user_head.dtype)
    return mean, TravelState(head[:, -1].to(user_head.dtype), total, weight)
