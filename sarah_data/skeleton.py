"""The motion vector's layout: which channels hold which joint, and the named joints we score.

A window's ``motion`` (T, J*12*3 + V*3) is every joint's icosahedron (12 points x 3 coordinates,
sarah_data/icosahedron.py) in the order of the shard's ``joint_names``, then the V shell points
(docs/representation.md). Every module that slices a motion vector asks a ``MotionLayout`` for
the slice, so the layout is written down once. A joint's position is its icosahedron's centroid.
Works on numpy arrays and torch tensors alike (reshape and mean only).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from sarah_data.constants import DEFAULT_SHELL_POINTS, JOINT_NAMES, JOINT_PARENTS

ICOSAHEDRON_POINTS = 12
POINT_WIDTH = ICOSAHEDRON_POINTS * 3  # channels per joint

# The joints the paper's metrics and our losses look at (SMPL-X names).
FEET = ("left_foot", "right_foot")
WRISTS = ("left_wrist", "right_wrist")
HEAD = "head"
ROOT = "pelvis"

# The body in parts, for errors reported per part (sarah-eval's reconstruction table): every
# SMPL-X joint in exactly one group (a test checks), fingers as "hands".
_FINGERS = ("index", "middle", "pinky", "ring", "thumb")
JOINT_GROUPS: dict[str, tuple[str, ...]] = {
    "root": (ROOT,),
    "spine and head": ("spine1", "spine2", "spine3", "neck", HEAD, "jaw", "left_eye_smplhf",
                       "right_eye_smplhf"),
    "legs": ("left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle"),
    "feet": FEET,
    "arms": ("left_collar", "right_collar", "left_shoulder", "right_shoulder", "left_elbow",
             "right_elbow") + WRISTS,
    "hands": tuple(n for n in JOINT_NAMES if n.rstrip("123").split("_")[-1] in _FINGERS),
}


def shell_parts(icosahedra, shell, joint_names: Sequence[str] = JOINT_NAMES,
                groups: Mapping[str, Sequence[str]] = JOINT_GROUPS) -> dict[str, tuple[int, ...]]:
    """One frame's icosahedra (J, 12, 3) and shell points (V, 3) -> the shell point indices of
    each of ``groups`` (name -> joint names; the body's parts by default), by the joint each point
    lies nearest to among all joints; groups in ``groups`` order, those no point lies nearest to
    left out (a point nearest a joint of no group is in none)."""
    icosahedra, shell = np.asarray(icosahedra, np.float64), np.asarray(shell, np.float64)
    if icosahedra.ndim != 3 or icosahedra.shape[0] != len(joint_names) or shell.ndim != 2:
        raise ValueError(f"shell_parts: want one frame's icosahedra ({len(joint_names)}, 12, 3) "
                         f"and shell (V, 3), got {icosahedra.shape} and {shell.shape}")
    centres = icosahedra.mean(axis=-2)
    nearest = np.argmin(np.sum((shell[:, None] - centres[None]) ** 2, axis=-1), axis=1)
    group_of = {name: group for group, names in groups.items() for name in names}
    found = np.array([group_of.get(joint_names[j], "") for j in nearest])
    parts = {group: tuple(int(p) for p in np.flatnonzero(found == group)) for group in groups}
    return {group: points for group, points in parts.items() if points}


@dataclass(frozen=True)
class MotionLayout:
    joint_names: tuple[str, ...] = JOINT_NAMES
    shell_points: int = DEFAULT_SHELL_POINTS

    @classmethod
    def from_width(cls, width: int, joint_names: Sequence[str] = JOINT_NAMES) -> "MotionLayout":
        """The layout of a ``width``-channel motion vector over ``joint_names``; ValueError when
        the width is not that many icosahedra plus whole shell points."""
        joints = len(joint_names) * POINT_WIDTH
        shell, rest = divmod(width - joints, 3)
        if width < joints or rest:
            raise ValueError(f"motion width {width} is not {len(joint_names)}*12*3 icosahedron "
                             f"coordinates plus 3 per shell point")
        return cls(tuple(joint_names), shell)

    @classmethod
    def of_shards(cls, attrs: Any) -> "MotionLayout":
        """The layout of a shards folder's motion, from its root attributes (``ShardAttrs``)."""
        return cls(tuple(attrs.joint_names), len(attrs.shell_vertex_ids))

    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    @property
    def icosahedra_width(self) -> int:
        return self.num_joints * POINT_WIDTH

    @property
    def width(self) -> int:
        return self.icosahedra_width + 3 * self.shell_points

    def joint(self, name: str) -> int:
        try:
            return self.joint_names.index(name)
        except ValueError:
            raise KeyError(f"no joint {name!r} in this layout") from None

    @property
    def bones(self) -> tuple[tuple[int, int], ...]:
        """(child, parent) joint indices of every joint whose SMPL-X parent is in the layout,
        parents before children (the order forward kinematics walks)."""
        parent_name = {name: JOINT_NAMES[p] if p >= 0 else None
                       for name, p in zip(JOINT_NAMES, JOINT_PARENTS)}
        pairs = [(i, self.joint_names.index(parent_name[n])) for i, n in enumerate(self.joint_names)
                 if parent_name.get(n) in self.joint_names]
        return tuple(sorted(pairs, key=lambda pair: _depth(self.joint_names[pair[0]], parent_name)))

    def rest_bone_lengths(self, rest_joints) -> np.ndarray:
        """(55, 3) joints of a body at rest, SMPL-X's order (``BodyModel.rest_joints``, a shard
        person's ``rest_joints``) -> (len(bones),) its bone lengths, metres."""
        rest_joints = np.asarray(rest_joints, dtype=np.float64)
        if rest_joints.shape != (len(JOINT_NAMES), 3):
            raise ValueError(f"rest joints of shape {rest_joints.shape}: expected "
                             f"({len(JOINT_NAMES)}, 3)")
        order = [JOINT_NAMES.index(name) for name in self.joint_names]
        return bone_lengths(rest_joints[order], self.bones)

    def motion_bone_lengths(self, motion) -> np.ndarray:
        """(T, width) motion vectors of one person -> (len(bones),) the median length of each
        bone over the frames, metres: a captured person's skeleton (their bones keep one length;
        the median passes over a badly tracked frame)."""
        joints = self.joint_positions(np.asarray(motion, dtype=np.float64))
        return np.median(bone_lengths(joints, self.bones), axis=0)

    def joint_slice(self, name: str) -> slice:
        """The channels of ``name``'s icosahedron in a motion vector."""
        start = self.joint(name) * POINT_WIDTH
        return slice(start, start + POINT_WIDTH)

    def split(self, motion):
        """(..., width) -> icosahedra (..., J, 12, 3) and shell points (..., V, 3)."""
        lead = tuple(motion.shape[:-1])
        ico = motion[..., :self.icosahedra_width].reshape(lead + (self.num_joints, ICOSAHEDRON_POINTS, 3))
        return ico, motion[..., self.icosahedra_width:].reshape(lead + (self.shell_points, 3))

    def group_points(self, frame, groups: Sequence[str]) -> np.ndarray:
        """The indices of the points (``split``'s icosahedron vertices, then its shell points)
        of ``JOINT_GROUPS``' ``groups``: their joints' icosahedra, and the shell points that lie
        nearest to those joints in ``frame`` (one motion vector, ``shell_parts``)."""
        joints = [self.joint(n) for group in groups for n in JOINT_GROUPS[group]
                  if n in self.joint_names]
        vertices = (np.asarray(joints, int)[:, None] * ICOSAHEDRON_POINTS
                    + np.arange(ICOSAHEDRON_POINTS)).ravel()
        icosahedra, shell = self.split(np.asarray(frame, np.float64))
        parts = shell_parts(icosahedra, shell, self.joint_names)
        shell_points = np.asarray([p for group in groups for p in parts.get(group, ())], int)
        return np.concatenate([vertices, self.num_joints * ICOSAHEDRON_POINTS + shell_points])

    def joint_positions(self, motion, names: Sequence[str] | None = None):
        """(..., width) -> (..., J, 3) joint positions (icosahedron centroids); only ``names``
        (in that order) when given."""
        if names is None:
            return self.split(motion)[0].mean(-2)
        lead = tuple(motion.shape[:-1])
        points = [motion[..., self.joint_slice(n)].reshape(lead + (ICOSAHEDRON_POINTS, 3)).mean(-2)
                  for n in names]
        if isinstance(motion, np.ndarray):
            return np.stack(points, axis=-2)
        import torch

        return torch.stack(points, dim=-2)


def _depth(name: str, parent_name: dict) -> int:
    depth = 0
    while parent_name.get(name) is not None:
        name, depth = parent_name[name], depth + 1
    return depth


def bone_lengths(joint_positions, bones: Sequence[tuple[int, int]]) -> np.ndarray:
    """(..., J, 3) joint positions -> (..., len(bones)) lengths of the (child, parent) bones."""
    p = np.asarray(joint_positions, dtype=np.float64)
    child, parent = (np.array(side, dtype=np.int64) for side in zip(*bones))
    return np.linalg.norm(p[..., child, :] - p[..., parent, :], axis=-1)
