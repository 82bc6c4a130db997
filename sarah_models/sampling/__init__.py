"""Sampling from the flow: the probability path, the ODE solver, classifier-free guidance and
the streaming / offline generators built on them."""

from .guidance import combine, drop_masks, guided, sample_drop_mask
from .path import interpolate, velocity_from_x1
from .solver import (imputer, integrate, replay_times, replayer, stage_times, time_grid,
                     token_noise)
from .stream import (
           IDENTITY,
           StreamingGenerator,
           StreamingSession,
           generate_offline,
           solve,
)

__all__ = ["IDENTITY", "StreamingGenerator", "StreamingSession", "combine", "drop_masks",
           "generate_offline", "guided", "imputer", "integrate", "interpolate",
           "replay_times", "replayer", "sample_drop_mask", "solve", "stage_times", "time_grid",
           "token_noise", "velocity_from_x1"]
