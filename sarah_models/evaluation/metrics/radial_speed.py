"""Radial speed: how fast the agent walks toward or away from the user, as against around them.

Not in the paper. Pelvis Speed says how much the agent walks; this says where to. The mean,
over a window's frame steps, of the agent's own floor velocity projected on the line to the
user, |v . r| with r the unit vector from the pelvis to the user's head: the user's walking
does not count, only the agent's. People who walk while they talk keep their distance and go
around their partner: on the fixtures, while the walking agent moves (faster than 0.2 m/s), its
velocity is 0.17 m/s along that line and 0.97 m/s across it, and the benchmark's flow went
0.5 m/s either way. Every frame step counts, so sway and jitter count too: real motion drawn for
another user reads about 3x GT's, the VAE reconstructing GT 2x (docs/results.md, forty-ninth
run). Read it against GT's (a ratio, like Pelvis Speed), paired by window.
"""

from __future__ import annotations

import numpy as np

from sarah_data.constants import FPS

from .clips import as_numpy, floor_path
from .spec import Metric


def radial_speed(joint_positions, user_head_xz, fps: float = FPS, root_joint: str = "pelvis") -> float:
    """Mean |v . r| (m/s) of the root's horizontal velocity v on the unit vector r toward the
    user's head at the start of each frame step; a step taken on top of the user counts 0."""
    root = floor_path(joint_positions, root_joint)
    user = np.asarray(as_numpy(user_head_xz), dtype=np.float64)
    if len(root) < 2:
        raise ValueError(f"radial_speed needs at least 2 frames, got {len(root)}")
    unit = toward_user(root[:-1], user[:-1])
    return float(np.mean(np.abs(np.sum(np.diff(root, axis=0) * unit, axis=1))) * fps)


def toward_user(root_xz, user_head_xz) -> np.ndarray:
    """(T, 2) unit floor vectors from the root toward the user's head, frame by frame; zero where
    the two stand on the same spot."""
    toward = np.asarray(user_head_xz, dtype=np.float64) - np.asarray(root_xz, dtype=np.float64)
    length = np.linalg.norm(toward, axis=-1, keepdims=True)
    return np.divide(toward, length, out=np.zeros_like(toward), where=length > 1e-9)


METRIC = Metric(name="radial_speed", label="Radial Speed", kind="clip", order=47, unit="{u}/s",
                length_power=1, decimals=1, better="gt", ratio_to_gt=True,
                function=lambda clip, config: radial_speed(clip.joints[0], clip.clip.user_head,
                                                           clip.fps, config.root_joint))
