"""Global rotations <-> local rotations of the SMPL-X tree, forward kinematics, and the fit of a
rigid skeleton to a motion.

Our icosahedra give every joint's global orientation, so a joint's local rotation is exactly
``R_parent^T R_child``. Rebuilding the joints from local rotations, the rest skeleton and the
root position is the same forward pass SMPL-X makes (joints do not depend on the pose blend
shapes), so for ground truth it reproduces the joints to float precision.

Generated motion is another matter: the decoding chain moves joints (bones at the training
data's lengths, planted feet, legs bent to reach them) and leaves each joint's decoded rotation
as it was, so the rotations no longer point the bones where the joints are, and a body posed by
them alone skates where the motion's feet stand (docs/export.md has the demo clip's figures).
``aim_rotations`` turns each rotation as little as it must for the body to follow the joints;
the fit uses it unless asked for the rotations as they are.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sarah_data.constants import JOINT, JOINT_PARENTS
from sarah_data.bone_turns import best_rotation, rotation_angle, shortest_rotation
from sarah_data.two_bone_ik import two_bone_ik

# What a body follows: the motion's joints (its rotations turned onto them) or its rotations alone.
POSE_SOURCES = ("joints", "rotations")
# Limbs whose middle joint the fit places by two-bone IK on the body's own bone lengths, so that
# their ends land on the motion's: an ankle that stands stays where it stands.
LIMBS = (("left_hip", "left_knee", "left_ankle"), ("right_hip", "right_knee", "right_ankle"),
         ("left_shoulder", "left_elbow", "left_wrist"), ("right_shoulder", "right_elbow", "right_wrist"))
# Joints whose rotation the fit keeps as the motion has it, their children following: the head,
# whose facing is the agent's gaze (what the gaze score and eye contact read), and the neck that
# carries it. The head's children are the face's jaw and eyes, points 3-12 cm from it that the
# decoder placed loosely, and the decoded head joint sat off where the neck's rotation puts it
# (on one window of the shipped model's: the eyes ~40 degrees around the head from where its
# rotation puts them, the jaw pointing backward, a neck swung to reach the head bent 56 degrees
# from the spine where the data's bends 18). Turned onto them, over 68 clips of the shipped
# model, the file's head faced ~100 degrees from the motion's and its gaze score fell 0.87 below
# the motion's. Kept, the file's head faces as the motion's faces (docs/results.md, ninety-eighth
# run). A motion decoded with ``vae.rigid_skull`` (the default since the ninety-ninth run) has
# its skull where these rotations put it, and the file's head sits within a centimetre of its.
KEEP_ROTATION = ("neck", "head")
# m: the most the fit lowers the pelvis for legs too short to reach the motion's ankles (the
# shipped model's clips needed up to 3.4 cm: its bones are the training data's mean lengths, the
# file's the agent's own); beyond it the ankles stop short.
MAX_PELVIS_DROP = 0.1


def children_of(parents=JOINT_PARENTS) -> list[list[int]]:
    """Each joint's children, in joint order."""
    return [[c for c, p in enumerate(parents) if p == j] for j in range(len(parents))]


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


def pelvis_drop(hips: np.ndarray, ankles: np.ndarray, reach: np.ndarray) -> np.ndarray:
    """(T,) metres the pelvis must come down for legs of ``reach`` (2,) metres from ``hips`` to
    reach ``ankles`` (T, 2, 3): 0 where both reach, else the larger leg's shortfall in height
    (where an ankle lies further off on the floor than the leg is long, the height that brings
    the hip to the ankle's), at most ``MAX_PELVIS_DROP``."""
    gap = hips - ankles
    floor = np.hypot(gap[..., 0], gap[..., 2])
    allowed = np.sqrt(np.maximum((reach * (1.0 - 1e-5)) ** 2 - floor ** 2, 0.0))
    return np.clip((gap[..., 1] - allowed).max(axis=-1), 0.0, MAX_PELVIS_DROP)


def aim_rotations(positions: np.ndarray, rotations: np.ndarray, rest_joints: np.ndarray,
                  parents=JOINT_PARENTS) -> tuple[np.ndarray, np.ndarray]:
    """(T, J, 3, 3) global rotations and (T, 3) pelvis positions for the skeleton
    ``rest_joints`` to follow the motion's joints ``positions`` (T, J, 3), each rotation turned as
    little as it must: each joint's bones point at its children (the best turn over several
    children), the limbs of ``LIMBS`` bend by two-bone IK so that their ends land on the motion's
    where the body's bones reach, and a joint without children keeps its rotation (the feet's and
    the fingertips' orientation, each bone's twist), as do those of ``KEEP_ROTATION`` (the
    neck and the head: the gaze). The pelvis is the motion's, lowered where
    the body's legs are too short for the motion's ankles (``pelvis_drop``), since a foot that
    stands is what a viewer sees first. Where the rotations already point the bones at the joints
    (ground truth) nothing turns, to float precision. Frame by frame."""
    positions = np.asarray(positions, dtype=np.float64)
    rest = np.asarray(rest_joints, dtype=np.float64)
    aimed = np.array(rotations, dtype=np.float64)
    children = children_of(parents)
    kept = {JOINT[name] for name in KEEP_ROTATION}
    limbs = [tuple(JOINT[name] for name in limb) for limb in LIMBS]
    middle_of = {top: (middle, end) for top, middle, end in limbs}
    legs = [limb for limb in limbs if parents[limb[0]] == 0]
    hips, ankles = [t for t, _, _ in legs], [e for _, _, e in legs]
    reach = np.array([np.linalg.norm(rest[m] - rest[t]) + np.linalg.norm(rest[e] - rest[m])
                      for t, m, e in legs])
    targets = positions.copy()  # where each bone points: the motion's joints, a limb's middle by IK
    placed = np.empty_like(positions)  # the body's joints as the turned rotations pose them
    placed[:, 0] = positions[:, 0]
    for joint, kids in enumerate(children):  # SMPL-X lists every parent before its children
        if not kids:
            continue
        if joint in middle_of:
            middle, end = middle_of[joint]
            upper = np.linalg.norm(rest[middle] - rest[joint])
            lower = np.linalg.norm(rest[end] - rest[middle])
            targets[:, middle], _ = two_bone_ik(placed[:, joint], positions[:, middle],
                                                positions[:, end], upper, lower)
        bones = rest[kids] - rest[joint]  # (K, 3)
        if joint not in kept:
            posed = np.einsum("tij,kj->tki", aimed[:, joint], bones)
            wanted = targets[:, kids] - placed[:, joint, None]
            turn = (shortest_rotation(posed[:, 0], wanted[:, 0]) if len(kids) == 1
                    else best_rotation(posed, wanted))
            aimed[:, joint] = turn @ aimed[:, joint]
        placed[:, kids] = placed[:, joint, None] + np.einsum("tij,kj->tki", aimed[:, joint], bones)
        if joint == 0 and legs:  # the pelvis and its children down where the legs fall short
            drop = pelvis_drop(placed[:, hips], positions[:, ankles], reach)
            placed[:, [0] + kids, 1] -= drop[:, None]
    return aimed, placed[:, 0]


@dataclass
class SkeletonFit:
    """A motion expressed on a rigid skeleton: what both exporters write."""

    rest_joints: np.ndarray  # (J, 3) the skeleton
    local: np.ndarray  # (T, J, 3, 3) local rotations
    root_position: np.ndarray  # (T, 3) the pelvis, world
    positions: np.ndarray  # (T, J, 3) the rigid body's joints (forward kinematics)
    residual: np.ndarray  # (T,) per frame, mean distance (m) to the motion's own joints
    residual_max: np.ndarray  # (T,) per frame, largest distance (m)
    # (T,) per frame, degrees between the body's head and the motion's: where it looks
    head_turn: np.ndarray
    pose_from: str = "joints"  # what the body follows (``POSE_SOURCES``)

    def summary(self) -> str:
        # The head's turn is on the line because the gaze is the head's facing: a fit that
        # turned it onto the face joints faced ~100 degrees away and no figure said so
        # (docs/results.md, ninety-eighth run).
        return (f"joint residual to the motion: mean {1000 * self.residual.mean():.3f} mm, "
                f"worst frame {1000 * self.residual_max.max():.3f} mm; head "
                f"{self.head_turn.mean():.1f} degrees from the motion's (mean)")


def fit_skeleton(positions: np.ndarray, rotations: np.ndarray, rest_joints: np.ndarray,
                 parents=JOINT_PARENTS, pose_from: str = "joints") -> SkeletonFit:
    """The motion on the rigid skeleton ``rest_joints``: the skeleton's bone lengths, and the
    motion's global rotations and pelvis, turned onto its joints (``pose_from="joints"``,
    ``aim_rotations``) or as they are (``"rotations"``). Generated motion need not keep the
    body's bone lengths; this body always does, and the residual says how far it is from the
    generated joints."""
    if pose_from not in POSE_SOURCES:
        raise ValueError(f"pose_from must be one of {POSE_SOURCES}, got {pose_from!r}")
    positions = np.asarray(positions, dtype=np.float64)
    root = positions[:, 0]
    head = JOINT["head"]
    given_head = np.asarray(rotations, dtype=np.float64)[:, head]
    if pose_from == "joints":
        rotations, root = aim_rotations(positions, rotations, rest_joints, parents)
    local = local_rotations(rotations, parents)
    posed, turned = forward_kinematics(rest_joints, local, root, parents)
    distance = np.linalg.norm(posed - positions, axis=-1)
    return SkeletonFit(np.asarray(rest_joints, np.float64), local, root, posed,
                       distance.mean(axis=1), distance.max(axis=1),
                       rotation_angle(given_head, turned[:, head]), pose_from)
