"""Two-bone inverse kinematics: a limb (hip, knee, ankle or shoulder, elbow, wrist) whose end
reaches a target with its two bones at given lengths, bending the way a given middle joint bends.

Shared by the decoding chain (``sarah_models.sampling``: the rigid skeleton's and the foot lock's
legs) and the exporters (``sarah_data.export.kinematics``: the exported body's limbs on the
motion's own ends).
"""

from __future__ import annotations

import numpy as np


def soft_reach(distance: np.ndarray, full: float, softness: float) -> np.ndarray:
    """How far a limb of ``full`` length reaches toward a target ``distance`` away: all the way
    until ``softness`` short of its length, then easing toward it (``full - softness *
    exp(-(distance - full + softness) / softness)``: the same value and slope where the easing
    begins, never quite straight). A limb that reaches all the way snaps straight as its target
    passes the full length and bends again as it comes back: a knee that flicks between
    locked and bent in a frame or two, which game engines ease the same way ("soft IK").
    ``softness`` 0: all the way."""
    if softness <= 0:
        return distance
    start = full - softness
    eased = full - softness * np.exp(-(np.maximum(distance, start) - start) / softness)
    return np.where(distance > start, eased, distance)


def two_bone_ik(root: np.ndarray, middle: np.ndarray, target: np.ndarray, upper: float,
                lower: float, softness: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(..., 3) root (a hip), the decoded middle joint (a knee: which way the limb bends) and the
    end's target (an ankle) -> (middle, end) with the limb's bones at ``upper`` and ``lower``
    metres; a target out of reach is reached for along the root-target line. ``softness``
    (metres): the reach eases toward the limb's length over its last ``softness``
    (``soft_reach``), the end falling that much short of a target at full length."""
    reach = target - root
    distance = np.linalg.norm(reach, axis=-1, keepdims=True)
    clamped = np.clip(soft_reach(distance, upper + lower, softness), abs(upper - lower) + 1e-6,
                      (upper + lower) * (1.0 - 1e-6))
    axis = np.divide(reach, distance, out=np.zeros_like(reach), where=distance > 1e-9)
    axis[distance[..., 0] <= 1e-9] = (0.0, -1.0, 0.0)  # the target on the root: straight down
    end = root + axis * clamped
    bend = middle - root
    bend -= axis * np.sum(bend * axis, axis=-1, keepdims=True)
    norm = np.linalg.norm(bend, axis=-1, keepdims=True)
    forward = np.array([0.0, 0.0, 1.0]) - axis * axis[..., 2:3]  # a straight limb bends forward
    bend = np.where(norm > 1e-9, bend / np.maximum(norm, 1e-12),
                    forward / np.maximum(np.linalg.norm(forward, axis=-1, keepdims=True), 1e-12))
    along = (upper ** 2 - lower ** 2 + clamped ** 2) / (2.0 * clamped)
    middle_at = root + axis * along + bend * np.sqrt(np.maximum(upper ** 2 - along ** 2, 0.0))
    return middle_at, end
