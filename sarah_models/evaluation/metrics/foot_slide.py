"""Foot slide: the fraction of frame steps in which a foot near the floor moves horizontally."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from sarah_data.constants import FPS, JOINT
from sarah_data.skeleton import FEET

from .clips import as_numpy
from .spec import FOOT_MAX_HEIGHT, FOOT_MIN_SPEED, Metric


def foot_slide(joint_positions, fps: float = FPS, max_height: float = FOOT_MAX_HEIGHT,
               min_speed: float = FOOT_MIN_SPEED, foot_joints: Sequence[str] = FEET) -> float:
    """Fraction of frame steps (t-1 -> t) in which at least one foot slides; in [0, 1].

    A foot slides during a step when its joint is below `max_height` (metres above the floor
    y = 0) at both ends of the step and its horizontal (x, z) speed over the step exceeds
    `min_speed` (m/s). joint_positions: (T,J,3) in metres, y up.
    """
    p = np.asarray(as_numpy(joint_positions), dtype=np.float64)[:, [JOINT[n] for n in foot_joints]]
    if len(p) < 2:
        raise ValueError(f"foot_slide needs at least 2 frames, got {len(p)}")
    low = np.maximum(p[1:, :, 1], p[:-1, :, 1]) < max_height
    speed = np.linalg.norm(np.diff(p[..., [0, 2]], axis=0), axis=-1) * fps
    return float(np.mean(np.any(low & (speed > min_speed), axis=1)))


def foot_steps(feet, fps: float = FPS, min_speed: float = FOOT_MIN_SPEED) -> list[list[tuple[int, int]]]:
    """Per foot, its steps in (T, F, 3) foot positions (metres, y up): the runs [start, end) of
    frame steps in which the foot moves horizontally faster than ``min_speed`` (m/s), the
    speed foot slide counts; a step carries the foot from frame ``start`` to frame ``end``."""
    p = np.asarray(as_numpy(feet), dtype=np.float64)
    moving = np.linalg.norm(np.diff(p[..., [0, 2]], axis=0), axis=-1) * fps > min_speed
    steps = []
    for foot in range(p.shape[1]):
        edges = np.flatnonzero(np.diff(np.concatenate([[0], moving[:, foot], [0]])))
        steps.append([(int(a), int(b)) for a, b in zip(edges[0::2], edges[1::2])])
    return steps


def step_reaches(feet, steps) -> list[float]:
    """Each step's horizontal distance from where the foot lifts to where it lands, metres, for
    (T, F, 3) foot positions and their ``foot_steps``."""
    p = np.asarray(as_numpy(feet), dtype=np.float64)
    return [float(np.hypot(*(p[end, foot] - p[start, foot])[[0, 2]]))
            for foot, runs in enumerate(steps) for start, end in runs]


def step_paths(feet, steps, frames: int) -> np.ndarray:
    """(N, frames, 2): each step's rise (m above where it lifted off) and travel (share of its
    way) over the ``frames`` frames after the last frame its foot stands (the foot rises before
    it moves), for (T, F, 3) foot positions and their ``foot_steps``. Steps too near the clip's
    ends are left out."""
    p = np.asarray(as_numpy(feet), dtype=np.float64)
    paths = []
    for foot, runs in enumerate(steps):
        for start, _ in runs:
            if start < 1 or start + frames > len(p):
                continue
            path = p[start - 1:start + frames, foot]
            way = np.linalg.norm((path - path[0])[:, [0, 2]], axis=-1)
            paths.append(np.stack([path[1:, 1] - path[0, 1], way[1:] / max(way[-1], 1e-9)], -1))
    return np.reshape(paths, (-1, frames, 2))


METRIC = Metric(name="foot_slide", label="Foot Slide", kind="clip", order=30,
                unit="fraction of frame steps", decimals=2, better="lower", value_range=" ∈ [0, 1]",
                function=lambda clip, config: foot_slide(
                    clip.joints[0], clip.fps, config.foot_max_height, config.foot_min_speed,
                    config.foot_joints))
