"""Frame-0 offset: how far the agent's pelvis starts from the window origin, on the floor.

Every clip is in its window frame, where the agent's pelvis is at the origin at frame 0 by
construction: ground truth scores 0. A model that cannot tell the first token from the others
starts its agent anywhere (the issue that added the flow's position embedding measured 113 cm).
"""

from __future__ import annotations

import numpy as np

from .clips import floor_path
from .spec import Metric


def frame0_offset(joint_positions, root_joint: str = "pelvis") -> float:
    """Horizontal (x, z) distance of the root joint at frame 0 from the origin, metres."""
    return float(np.linalg.norm(floor_path(joint_positions, root_joint)[0]))


METRIC = Metric(name="frame0_offset", label="Frame-0 Off.", kind="clip", order=70,
                unit="{u}", length_power=1, decimals=1, better="lower", window_frame=True,
                function=lambda clip, config: frame0_offset(clip.joints[0], config.root_joint))
