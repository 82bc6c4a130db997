"""User distance ("User Dist."): how far the agent keeps from the user on the floor (proxemics).

Not in the paper, which names proxemics (interpersonal distance) among the signals it learns
but scores none. The mean, over a window's frames, of the horizontal distance between the
agent's pelvis and the user's floor-projected head. People in conversation keep a distance
(on the fixtures 1.3-2.7 m); an agent that walks up to the user, or away, moves it, and FGD
sees that only as a spread of positions. Read against GT's, paired by window.
"""

from __future__ import annotations

import numpy as np

from .clips import as_numpy, floor_path
from .spec import Metric


def user_distance(joint_positions, user_head_xz, root_joint: str = "pelvis") -> float:
    """Mean horizontal distance (m) between the root joint and the user's head over frames."""
    user = np.asarray(as_numpy(user_head_xz), dtype=np.float64)
    return float(np.mean(np.linalg.norm(floor_path(joint_positions, root_joint) - user, axis=1)))


METRIC = Metric(name="user_distance", label="User Dist.", kind="clip", order=46, unit="{u}",
                length_power=1, decimals=1, better="gt",
                function=lambda clip, config: user_distance(clip.joints[0], clip.clip.user_head,
                                                            config.root_joint))
