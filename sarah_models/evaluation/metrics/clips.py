"""The clips metrics read: an agent's motion and the user's floor trajectory, and their decoding.

Clips hold metres and seconds, y up, floor at y = 0, in the world or the window frame.
``DecodedClip`` decodes a clip once (joint positions and rotations from the icosahedra, the
shell in the window frame) for every metric that reads it.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from sarah_data import frames, icosahedron
from sarah_data.constants import FPS, JOINT, NUM_JOINTS
from sarah_data.skeleton import ROOT


def as_numpy(x) -> np.ndarray:
    if hasattr(x, "detach"):  # torch tensor
        x = x.detach().cpu().numpy()
    return np.asarray(x)


def floor_path(joint_positions, root_joint: str = ROOT) -> np.ndarray:
    """(T, 2) horizontal (x, z) positions of ``root_joint`` from (T, J, 3) joint positions, float64."""
    return np.asarray(as_numpy(joint_positions), dtype=np.float64)[:, JOINT[root_joint]][:, [0, 2]]


def step_lengths(points) -> np.ndarray:
    """How far each point moves in each frame step: (T, ..., D) -> (T-1, ...), in its units."""
    return np.linalg.norm(np.diff(np.asarray(as_numpy(points), dtype=np.float64), axis=0), axis=-1)


def mean_speed(points, fps: float = FPS, name: str = "mean_speed") -> float:
    """Mean speed over all frame steps and all points of ``points`` (T, ..., D) in units/s;
    ValueError naming ``name`` (the metric asking) for fewer than 2 frames."""
    if len(points) < 2:
        raise ValueError(f"{name} needs at least 2 frames, got {len(points)}")
    return float(np.mean(step_lengths(points)) * fps)


def accelerations(points, fps: float = FPS) -> np.ndarray:
    """Second finite difference over time times fps^2: (T,...) -> (T-2,...), units/s^2."""
    p = np.asarray(as_numpy(points), dtype=np.float64)
    return (p[2:] - 2.0 * p[1:-1] + p[:-2]) * fps**2


@dataclass
class Clip:
    """One evaluated clip: the agent's motion and the user's floor head trajectory.

    icosahedra (T,55,12,3) and shell (T,V,3) in metres, y up, floor at y = 0, world or window
    frame; user_head (T,2) as (x, z) in the same frame; fps frames per second.
    Torch tensors are accepted and converted to numpy arrays.
    """

    icosahedra: np.ndarray
    shell: np.ndarray
    user_head: np.ndarray
    fps: float = FPS

    def __post_init__(self) -> None:
        # Kept in the given float precision (float32 halves memory); metrics compute in float64.
        for name in ("icosahedra", "shell", "user_head"):
            value = np.asarray(as_numpy(getattr(self, name)))
            setattr(self, name, value if np.issubdtype(value.dtype, np.floating) else value.astype(np.float64))
        frames_ = self.icosahedra.shape[0] if self.icosahedra.ndim else 0
        problems = []
        if self.icosahedra.shape[1:] != (NUM_JOINTS, 12, 3):
            problems.append(f"icosahedra shape {self.icosahedra.shape}, want (T,{NUM_JOINTS},12,3)")
        if self.shell.ndim != 3 or self.shell.shape[0] != frames_ or self.shell.shape[2] != 3:
            problems.append(f"shell shape {self.shell.shape}, want ({frames_},V,3)")
        if self.user_head.shape != (frames_, 2):
            problems.append(f"user_head shape {self.user_head.shape}, want ({frames_},2)")
        if frames_ < 3:
            problems.append(f"{frames_} frames; accelerations need at least 3")
        if not self.fps > 0:
            problems.append(f"fps {self.fps} is not positive")
        if problems:
            raise ValueError("Clip: " + "; ".join(problems))
        for name in ("icosahedra", "shell", "user_head"):
            if not np.all(np.isfinite(getattr(self, name))):
                raise ValueError(f"Clip: {name} contains non-finite values")

    @property
    def num_frames(self) -> int:
        return self.icosahedra.shape[0]


class DecodedClip:
    """A clip with what metrics compute from it, each computed once on first use (float64)."""

    def __init__(self, clip: Clip, root_joint: str, normalize_window: bool) -> None:
        self.clip, self.root_joint, self.normalize_window = clip, root_joint, normalize_window

    @property
    def fps(self) -> float:
        return self.clip.fps

    @cached_property
    def joints(self) -> tuple[np.ndarray, np.ndarray]:
        """Joint positions (T, J, 3) and global rotations (T, J, 3, 3)."""
        return icosahedron.decode(np.asarray(self.clip.icosahedra, dtype=np.float64))

    @cached_property
    def shell_window(self) -> np.ndarray:
        """(T, V*3) shell points in the window frame (the root at frame 0 at the origin facing
        +z) when ``normalize_window``, else as given; metres."""
        shell = np.asarray(self.clip.shell, dtype=np.float64)
        if self.normalize_window:
            positions, rotations = self.joints
            root = JOINT[self.root_joint]
            shell = frames.window_transform(positions[0, root], rotations[0, root]).apply_points(shell)
        return shell.reshape(len(shell), -1)
