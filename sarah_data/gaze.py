"""Floor-projected head trajectories and the gaze score (paper 3.4, eqs. 6-8).

The score is computed in the floor plane. The paper's Fig. 4 is a top view, and the user's
position p_y is a floor-projected head position: with a 3D facing direction d_x and a floor-level
p_y, looking straight at a partner's eyes would score below 1 by an amount that depends on head
height and distance. Projecting both directions to (x, z) makes g = 1 mean "facing the partner".
"""

from __future__ import annotations

import numpy as np

# Front and back of the head: the head joint moved this far along the head's facing axis (its
# global +z, the rest pose's facing direction). One definition for data and metrics alike.
HEAD_HALF_DEPTH = 0.10
FACING_AXIS = 2  # the column of the head's global rotation that it faces along (+z)

_EPS = 1e-8


def head_trajectory(eye_mid: np.ndarray) -> np.ndarray:
    """Eye midpoints (...,3) -> floor-projected head positions (...,2) as (x, z)."""
    return np.asarray(eye_mid)[..., [0, 2]]


def head_points(head_position: np.ndarray, head_rotation: np.ndarray):
    """Head joint position (...,3) and global rotation (...,3,3) -> (front (...,3), back (...,3))."""
    axis = np.asarray(head_rotation)[..., :, FACING_AXIS] * HEAD_HALF_DEPTH
    return head_position + axis, head_position - axis


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), _EPS)


def gaze_score(head_front: np.ndarray, head_back: np.ndarray, partner_head_xz: np.ndarray) -> np.ndarray:
    """g = d_x . d_y in the floor plane, in [-1, 1]; shapes (...,3), (...,3), (...,2) -> (...)."""
    front_xz, back_xz = np.asarray(head_front)[..., [0, 2]], np.asarray(head_back)[..., [0, 2]]
    d_x = _unit(front_xz - back_xz)
    d_y = _unit(np.asarray(partner_head_xz) - back_xz)
    return np.clip(np.sum(d_x * d_y, axis=-1), -1.0, 1.0)
