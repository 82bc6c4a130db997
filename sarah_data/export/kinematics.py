"""Global rotations <-> local rotations of the SMPL-X tree, forward kinematics, and the fit of a
rigid skeleton to a motion.

Our icosahedra give every joint's global orientation, so a joint's local rotation is exactly
``R_parent^T R_child``: no inverse kinematics. Rebuilding the joints from local rotations, the
rest skeleton and the root position is the same forward pass SMPL-X makes (joints do not depend
on the pose blend shapes), so for ground truth it reproduces the joints to float precision.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sarah_data.constants import JOINT_PARENTS


def local_rotations(rotations: np.ndarray, parents=JOINT_PARENTS) -> np.ndarray:
    """(T, J, 3, 3) global rotations -> local ones (the root's stays global)."""
    rotations = np.asarray(rotations, dtype=np.float64)
    local = rotations.copy()
    for joint, parent in enumerate(parents):
        if parent >= 0:
            local[:, joint] = np.swapaxes(rotations[:, parent], -1, -2) @ rotations[:, joint]
    return local


def forward_kinematics(rest_joints: np.ndarray, local: np.ndarray, root_position: np.ndarray,
                       parents=JOINT_PARENTS) -> tuple[np.ndarray, np.ndarray]:
    """Joints (T, J, 3) and global rotations (T, J, 3, 3) of the skeleton ``rest_joints`` (J, 3)
    posed by ``local`` (T, J, 3, 3) with its root at ``root_position`` (T, 3)."""
    local = np.asarray(local, dtype=np.float64)
    rest = np.asarray(rest_joints, dtype=np.float64)
    frames, joints = local.shape[:2]
    positions = np.empty((frames, joints, 3))
    rotations = np.empty_like(local)
    positions[:, 0], rotations[:, 0] = root_position, local[:, 0]
    for joint in range(1, joints):  # SMPL-X lists every parent before its children
        parent = parents[joint]
        rotations[:, joint] = rotations[:, parent] @ local[:, joint]
        positions[:, joint] = positions[:, parent] + rotations[:, parent] @ (rest[joint] - rest[parent])
    return positions, rotations


def rest_offsets_from_motion(positions: np.ndarray, rotations: np.ndarray,
                             parents=JOINT_PARENTS) -> np.ndarray:
    """A rest skeleton (J, 3), root at the origin, fitted to a motion: each bone is the median over
    frames of the child's position in its parent's frame. Exact for a rigid body (ground truth);
    for generated motion it is the body whose bones the motion keeps most of the time."""
    positions = np.asarray(positions, dtype=np.float64)
    rotations = np.asarray(rotations, dtype=np.float64)
    rest = np.zeros((positions.shape[1], 3))
    for joint in range(1, positions.shape[1]):
        parent = parents[joint]
        bone = positions[:, joint] - positions[:, parent]
        in_parent = np.einsum("tji,tj->ti", rotations[:, parent], bone)  # R_parent^T bone
        rest[joint] = rest[parent] + np.median(in_parent, axis=0)
    return rest


@dataclass
class SkeletonFit:
    """A motion expressed on a rigid skeleton: what both exporters write."""

    rest_joints: np.ndarray  # (J, 3) the skeleton
    local: np.ndarray  # (T, J, 3, 3) local rotations
    root_position: np.ndarray  # (T, 3) the pelvis, world
    positions: np.ndarray  # (T, J, 3) the rigid body's joints (forward kinematics)
    residual: np.ndarray  # (T,) per frame, mean distance (m) to the motion's own joints
    residual_max: np.ndarray  # (T,) per frame, largest distance (m)

    def summary(self) -> str:
        return (f"joint residual to the motion: mean {1000 * self.residual.mean():.3f} mm, "
                f"worst frame {1000 * self.residual_max.max():.3f} mm")


def fit_skeleton(positions: np.ndarray, rotations: np.ndarray, rest_joints: np.ndarray,
                 parents=JOINT_PARENTS) -> SkeletonFit:
    """The motion on the rigid skeleton ``rest_joints``: its global rotations, its pelvis
    position, the skeleton's bone lengths. Generated motion need not keep its bone lengths; this
    body always does, and the residual says how far it is from the generated joints."""
    positions = np.asarray(positions, dtype=np.float64)
    local = local_rotations(rotations, parents)
    root = positions[:, 0]
    posed, _ = forward_kinematics(rest_joints, local, root, parents)
    distance = np.linalg.norm(posed - positions, axis=-1)
    return SkeletonFit(np.asarray(rest_joints, np.float64), local, root, posed,
                       distance.mean(axis=1), distance.max(axis=1))
