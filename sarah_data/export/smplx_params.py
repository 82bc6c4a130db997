"""SMPL-X parameters in the AMASS layout, the file AMASS-style loaders and the Blender SMPL-X
add-on read.

``poses`` (T, 165) is every joint's local rotation as axis-angle in SMPL-X joint order: root
(3), body (63), jaw (3), left eye (3), right eye (3), left hand (45), right hand (45); the split
keys hold the same numbers. Hands are absolute rotations (``flat_hand_mean`` True, no PCA), as
Embody 3D fits them. ``trans`` puts the pelvis where the motion has it: the SMPL-X forward pass
rotates the body about its rest pelvis, so ``trans = pelvis - rest_joints[pelvis]``.

Axes: our world is y up, metres, floor at y = 0 (``up_axis`` "y"). ``up="z"`` rotates the whole
motion by +90 degrees about x, (x, y, z) -> (x, -z, y), for tools that want z up (AMASS's own
files are z up).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from sarah_data.atomic import atomic_path
from sarah_data.constants import FPS, JOINT, NUM_JOINTS

from .kinematics import SkeletonFit
from .motion import ExportError, ExportMotion

Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
UP_AXES = ("y", "z")
# The split keys: name -> (first joint, joint count) in SMPL-X order.
SPLIT_KEYS = {"root_orient": (0, 1), "pose_body": (1, 21), "pose_jaw": (JOINT["jaw"], 1),
              "pose_eye": (JOINT["left_eye_smplhf"], 2), "pose_hand": (JOINT["left_index1"], 30)}


def smplx_parameters(motion: ExportMotion, fit: SkeletonFit, up: str = "y") -> dict[str, np.ndarray]:
    """The AMASS-layout arrays of ``fit`` (``motion.fit()``: the body in our world), turned to
    ``up``: the whole body turns with the root, so only the root's rotation and the pelvis turn."""
    if not motion.shape.known:
        raise ExportError(motion.source or motion.name,
                          f"no body shape ({motion.shape.source}); SMPL-X parameters need the "
                          f"betas and their rest skeleton: pass --body-model to use that model "
                          f"with neutral (zero) betas")
    if up not in UP_AXES:
        raise ValueError(f"up axis must be one of {UP_AXES}, got {up!r}")
    local, root = fit.local, fit.root_position
    if up == "z":
        local = local.copy()
        local[:, 0] = Y_UP_TO_Z_UP @ local[:, 0]
        root = root @ Y_UP_TO_Z_UP.T
    rest = fit.rest_joints
    frames = motion.frames
    axis_angle = Rotation.from_matrix(local.reshape(-1, 3, 3)).as_rotvec().reshape(frames, NUM_JOINTS * 3)
    arrays = {
        "poses": axis_angle,
        "trans": root - rest[0],
        "betas": np.asarray(motion.shape.betas, np.float64),
        "num_betas": np.int64(len(motion.shape.betas)),
        "gender": np.array(motion.shape.gender),
        "mocap_frame_rate": np.float64(FPS),
        "surface_model_type": np.array("smplx"),
        "flat_hand_mean": np.bool_(True),
        "up_axis": np.array(up),
        "units": np.array("metres"),
        "body_shape_source": np.array(motion.shape.source),
        "source": np.array(motion.source),
    }
    for key, (first, count) in SPLIT_KEYS.items():
        arrays[key] = axis_angle[:, 3 * first: 3 * (first + count)]
    return arrays


def save_npz(path: str | Path, arrays: dict[str, np.ndarray]) -> None:
    with atomic_path(Path(path)) as tmp, open(tmp, "wb") as handle:
        np.savez(handle, **arrays)


def write_smplx(path: str | Path, motion: ExportMotion, up: str = "y",
                pose_from: str = "joints") -> SkeletonFit:
    """Write ``path`` (.npz) atomically; returns the fit (for its residual)."""
    fit = motion.fit(pose_from)
    save_npz(path, smplx_parameters(motion, fit, up))
    return fit
