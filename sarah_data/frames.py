"""The world frame and per-window normalization.

World convention (SMPL-X's, and Embody 3D's): y up, metres, floor at y = 0; a body in the rest
pose faces +z. Floor-plane quantities are (x, z) pairs.

A window is normalized by a rotation about y and a translation in the floor plane that put the
agent's root (pelvis), at the window's first frame, at the origin facing +z (paper 3.1). Height is
left alone so the floor stays at y = 0. Shards keep world coordinates; this runs when data is read.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def yaw_of(rotation: np.ndarray) -> np.ndarray:
    """Heading angle about +y of the rotation's +z axis (0 = facing +z, pi/2 = facing +x)."""
    forward = np.asarray(rotation)[..., :, 2]
    return np.arctan2(forward[..., 0], forward[..., 2])


def wrap_angle(angle):
    """Angles (rad) in [-pi, pi)."""
    return (angle + np.pi) % (2.0 * np.pi) - np.pi


def rotation_about_y(angle) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    zero, one = np.zeros_like(c), np.ones_like(c)
    return np.stack([np.stack([c, zero, s], -1), np.stack([zero, one, zero], -1),
                     np.stack([-s, zero, c], -1)], -2)


@dataclass(frozen=True)
class WindowTransform:
    """World -> window: p' = R_y(-yaw) (p - (x, 0, z))."""

    yaw: float
    x: float
    z: float

    @property
    def _to_window(self) -> np.ndarray:
        return rotation_about_y(-self.yaw)

    def apply_points(self, points: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        return self._rotate(np.asarray(points), -self.yaw, before=(self.x, self.z), out=out)

    def invert_points(self, points: np.ndarray) -> np.ndarray:
        return self._rotate(np.asarray(points), self.yaw, after=(self.x, self.z))

    @staticmethod
    def _rotate(points: np.ndarray, angle: float, before=(0.0, 0.0), after=(0.0, 0.0),
                out: np.ndarray | None = None) -> np.ndarray:
        # Rotation about y touches only x and z: two fused element-wise lines instead of a
        # (N,3)x(3,3) matmul, which numpy runs several times slower for 3-wide rows.
        c, s = float(np.cos(angle)), float(np.sin(angle))  # Python floats keep float32 float32
        x = points[..., 0] - before[0]
        z = points[..., 2] - before[1]
        out = np.empty_like(points) if out is None else out
        out[..., 0] = c * x + s * z + after[0]
        out[..., 1] = points[..., 1]
        out[..., 2] = c * z - s * x + after[1]
        return out

    def apply_floor(self, floor_xz: np.ndarray) -> np.ndarray:
        floor_xz = np.asarray(floor_xz)
        lifted = np.stack([floor_xz[..., 0], np.zeros_like(floor_xz[..., 0]), floor_xz[..., 1]], -1)
        return self.apply_points(lifted)[..., [0, 2]]

    def invert_floor(self, floor_xz: np.ndarray) -> np.ndarray:
        floor_xz = np.asarray(floor_xz)
        lifted = np.stack([floor_xz[..., 0], np.zeros_like(floor_xz[..., 0]), floor_xz[..., 1]], -1)
        return self.invert_points(lifted)[..., [0, 2]]

    def apply_rotations(self, rotations: np.ndarray) -> np.ndarray:
        rotations = np.asarray(rotations)
        return (self._to_window.astype(rotations.dtype) @ rotations).astype(rotations.dtype)

    def invert_rotations(self, rotations: np.ndarray) -> np.ndarray:
        rotations = np.asarray(rotations)
        return (self._to_window.T.astype(rotations.dtype) @ rotations).astype(rotations.dtype)

    def matrix(self) -> np.ndarray:
        """(4, 3) M with [p, 1] @ M = apply_points(p): the transform as one matmul over
        homogeneous points, which the window loader runs over a whole window at once."""
        rotation = self._to_window
        return np.concatenate([rotation.T, -(rotation @ np.array([self.x, 0.0, self.z]))[None]])

    def as_array(self) -> np.ndarray:
        """(4,) float32 [yaw, x, z, 0], the form datasets and checkpoints carry."""
        return np.array([self.yaw, self.x, self.z, 0.0], dtype=np.float32)

    @classmethod
    def from_array(cls, values) -> "WindowTransform":
        values = np.asarray(values, dtype=np.float64)
        return cls(float(values[0]), float(values[1]), float(values[2]))


def window_transform(root_position: np.ndarray, root_rotation: np.ndarray) -> WindowTransform:
    """The transform that puts a root at (root_position, root_rotation) at the origin facing +z."""
    root_position = np.asarray(root_position, dtype=np.float64)
    return WindowTransform(float(yaw_of(np.asarray(root_rotation, dtype=np.float64))),
                           float(root_position[0]), float(root_position[2]))
