"""Pelvis speed: how fast the agent's pelvis moves over the floor, walking and swaying alike.

Not in the paper. FGD scores where the body is and FGD_local how it moves about its pelvis;
neither says how much the agent walks. On the fixtures the agents stand in ~70 % of frames and
walk in the rest, and a model that walks twice the data's distance, or walks while the user does
(when the data's agent stands still), hides inside FGD's spread of positions. Read it against
GT's, paired by window: the closer the better.
"""

from __future__ import annotations

from sarah_data.constants import FPS

from .clips import floor_path, mean_speed
from .spec import Metric


def pelvis_speed(joint_positions, fps: float = FPS, root_joint: str = "pelvis") -> float:
    """Mean horizontal (x, z) speed of the root joint over all frame steps, m/s."""
    return mean_speed(floor_path(joint_positions, root_joint), fps, "pelvis_speed")


METRIC = Metric(name="pelvis_speed", label="Pelvis Speed", kind="clip", order=45, unit="{u}/s",
                length_power=1, decimals=1, better="gt", ratio_to_gt=True,
                function=lambda clip, config: pelvis_speed(clip.joints[0], clip.fps,
                                                           config.root_joint))
