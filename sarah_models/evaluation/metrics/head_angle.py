"""Head angle ("Head Ang."): the agent's mean gaze score toward the user, in [-1, 1]."""

from __future__ import annotations

import numpy as np

from sarah_data import gaze
from sarah_data.constants import JOINT

from .clips import as_numpy
from .spec import Metric


def head_angle(head_position, head_rotation, user_head_xz) -> float:
    """Mean gaze score of the agent toward the user over frames, in [-1, 1].

    head_position (T,3), head_rotation (T,3,3): the agent's head joint; user_head_xz (T,2) the
    user's floor-projected head, in the same frame. Uses gaze.head_points and gaze.gaze_score,
    the definitions that produce the training data's gaze score.
    """
    front, back = gaze.head_points(np.asarray(as_numpy(head_position), dtype=np.float64),
                                   np.asarray(as_numpy(head_rotation), dtype=np.float64))
    return float(np.mean(gaze.gaze_score(front, back,
                                         np.asarray(as_numpy(user_head_xz), dtype=np.float64))))


def clip_head_angle(clip, config) -> float:
    """Head Ang. of a decoded clip (``clips.DecodedClip``) toward its user."""
    positions, rotations = clip.joints
    head = JOINT[config.head_joint]
    return head_angle(positions[:, head], rotations[:, head], clip.clip.user_head)


METRIC = Metric(name="head_angle", label="Head Ang.", kind="clip", order=50,
                unit="gaze score in [-1, 1]", decimals=2, better="higher",
                value_range=" ∈ [-1, 1]", function=clip_head_angle)
