"""Look-away share: the share of windows in which the agent mostly looks away from the user.

Not in the paper. Head Ang. is a mean over every frame of every window, and it cannot tell an
agent that looks away for whole windows, as people who avoid eye contact do, from one that
half-faces the user everywhere. On the fixtures a fifth of the data's windows have a mean gaze
score below 0.5; a flow trained twice as long faced the user in all but 6 % of them while its
Head Ang. was off by 0.12 only, and guidance that brought the mean back brought the share back
too (docs/results.md, forty-eighth run). Per clip the value is 1 when the clip's Head Ang. is
below ``LOOK_AWAY_SCORE`` and 0 otherwise, so the column's mean is the share, with the same
bootstrap interval and GT pairing as every per-clip column.
"""

from __future__ import annotations

from .head_angle import clip_head_angle
from .spec import Metric

# A mean gaze score below cos 60°: the head on average more than 60° off the user's bearing.
LOOK_AWAY_SCORE = 0.5


def looks_away(head_angle: float, threshold: float = LOOK_AWAY_SCORE) -> float:
    """1.0 when a window's mean gaze score (Head Ang.) is below ``threshold``, else 0.0."""
    return float(head_angle < threshold)


METRIC = Metric(name="look_away", label="Look-Away", kind="clip", order=51, unit="share of windows",
                decimals=2, better="gt", value_range=" ∈ [0, 1]",
                function=lambda clip, config: looks_away(clip_head_angle(clip, config)))
