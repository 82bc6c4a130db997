"""Acceleration RMS: how hard the agent's shell accelerates, the magnitude FGD_acc compares.

Not in the paper. FGD_acc is one distance for two different failures: motion too smooth (a
decoder that averages away the steps and beats it cannot place) and motion that jitters (a young
decoder, seams between latent blocks). Both put FGD_acc far from the data; this column says
which. It is the root mean square, over frames and shell points, of each point's acceleration
(x[t+1] - 2 x[t] + x[t-1]) * fps^2; read it against GT's, paired by window: below 1x the motion
is too smooth, above it jitters.
"""

from __future__ import annotations

import numpy as np

from sarah_data.constants import FPS

from .clips import accelerations
from .spec import Metric


def acceleration_rms(shell, fps: float = FPS) -> float:
    """RMS of the points' acceleration norms, shell (T, V, 3) or (T, V*3), in units/s^2."""
    a = accelerations(shell, fps)
    if len(a) == 0:
        raise ValueError(f"acceleration_rms needs at least 3 frames, got {len(shell)}")
    return float(np.sqrt(np.mean(np.sum(a.reshape(len(a), -1, 3) ** 2, axis=-1))))


METRIC = Metric(name="acceleration_rms", label="Acc. RMS", kind="clip", order=25, unit="{u}/s^2",
                length_power=1, decimals=0, better="gt", ratio_to_gt=True,
                function=lambda clip, config: acceleration_rms(clip.shell_window, clip.fps))
