"""Wrist speed ("Wrist Var"): the mean 3D speed of both wrists."""

from __future__ import annotations

from typing import Sequence

from sarah_data.constants import FPS, JOINT
from sarah_data.skeleton import WRISTS

from .clips import as_numpy, mean_speed
from .spec import Metric


def wrist_speed(joint_positions, fps: float = FPS, wrist_joints: Sequence[str] = WRISTS) -> float:
    """Mean 3D speed of the wrists over all frame steps and both wrists, in m/s."""
    wrists = as_numpy(joint_positions)[:, [JOINT[n] for n in wrist_joints]]
    return mean_speed(wrists, fps, "wrist_speed")


METRIC = Metric(name="wrist_speed", label="Wrist Var", kind="clip", order=40, unit="{u}/s",
                length_power=1, decimals=1, better="higher", ratio_to_gt=True,
                function=lambda clip, config: wrist_speed(clip.joints[0], clip.fps,
                                                          config.wrist_joints))
