"""Root-relative FGD: the Fréchet distance of per-frame shell positions relative to the pelvis,
turned into the pelvis's own heading (x, z rotated by minus its yaw), in cm^2.

Global FGD mixes body shape and pose with where each agent walked in its window (the mean term
of two small sets of walks dominates it); this one scores the body alone.
"""

from __future__ import annotations

import numpy as np

from sarah_data.constants import JOINT

from .spec import Metric


def root_relative_points(points: np.ndarray, root_position: np.ndarray,
                         root_rotation: np.ndarray) -> np.ndarray:
    """(T, N, 3) points minus the root position, rotated about y by minus the root's yaw (the
    heading of its +z axis on the floor): (T, N*3)."""
    forward = root_rotation[:, :, 2]
    yaw = np.arctan2(forward[:, 0], forward[:, 2])
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    d = points - root_position[:, None]
    x, z = c * d[..., 0] - s * d[..., 2], s * d[..., 0] + c * d[..., 2]
    return np.stack((x, d[..., 1], z), axis=-1).reshape(len(points), -1)


def _samples(clip, config) -> np.ndarray:
    positions, rotations = clip.joints
    root = JOINT[config.root_joint]
    shell = np.asarray(clip.clip.shell, dtype=np.float64)
    return root_relative_points(shell, positions[:, root], rotations[:, root])


METRIC = Metric(name="fgd_local", label="FGD_local", kind="frechet", order=15, unit="{u}^2",
                length_power=2, scale=10.0, decimals=2, better="lower", function=_samples)
