"""BVH of the SMPL-X skeleton (55 joints: body, jaw, eyes and both hands), 30 fps.

Each joint's OFFSET is its rest position relative to its parent (from the body's betas, or a
skeleton fitted to the motion when it has no body shape); the root has position channels; every
joint has rotation channels in ``Zrotation Yrotation Xrotation`` order (R = Rz Ry Rx, degrees),
the local rotation of the SMPL-X tree, since SMPL-X's rest pose has identity rotations. Axes as
ours: y up. Units: metres (``units="m"``, Blender's default import scale) or centimetres
(``units="cm"``, what most game-engine importers expect).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from sarah_data.atomic import atomic_path
from sarah_data.constants import JOINT_NAMES, JOINT_PARENTS

from .kinematics import SkeletonFit, children_of
from .motion import ExportMotion

UNITS = {"m": 1.0, "cm": 100.0}
CHANNEL_ORDER = "ZYX"  # scipy's intrinsic order: R = Rz @ Ry @ Rx
END_SITE_FRACTION = 0.5  # a leaf's end site continues its bone by half its length


def bvh_text(motion: ExportMotion, fit: SkeletonFit, units: str = "m") -> str:
    """The BVH of ``fit`` (``motion.fit()``)."""
    if units not in UNITS:
        raise ValueError(f"BVH units must be one of {sorted(UNITS)}, got {units!r}")
    scale = UNITS[units]
    rest = fit.rest_joints
    children = children_of()
    lines = ["HIERARCHY"]
    order: list[int] = []  # joints as the hierarchy lists them: the MOTION columns' order

    def vector(v) -> str:
        return " ".join(f"{scale * x:.6f}" for x in v)

    def emit(joint: int, depth: int) -> None:
        pad = "\t" * depth
        order.append(joint)
        parent = JOINT_PARENTS[joint]
        if parent < 0:
            lines.append(f"ROOT {JOINT_NAMES[joint]}")
            offset = np.zeros(3)
            channels = "CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation"
        else:
            lines.append(f"{pad}JOINT {JOINT_NAMES[joint]}")
            offset = rest[joint] - rest[parent]
            channels = "CHANNELS 3 Zrotation Yrotation Xrotation"
        lines.extend([f"{pad}{{", f"{pad}\tOFFSET {vector(offset)}", f"{pad}\t{channels}"])
        for child in children[joint]:
            emit(child, depth + 1)
        if not children[joint]:
            end = END_SITE_FRACTION * (rest[joint] - rest[parent])
            lines.extend([f"{pad}\tEnd Site", f"{pad}\t{{", f"{pad}\t\tOFFSET {vector(end)}", f"{pad}\t}}"])
        lines.append(f"{pad}}}")

    emit(0, 0)
    frames = motion.frames
    euler = Rotation.from_matrix(fit.local.reshape(-1, 3, 3)).as_euler(CHANNEL_ORDER, degrees=True)
    euler = euler.reshape(frames, len(JOINT_NAMES), 3)[:, order].reshape(frames, -1)
    lines += ["MOTION", f"Frames: {frames}", f"Frame Time: {1.0 / motion.fps:.8f}"]
    for t in range(frames):
        root = " ".join(f"{scale * x:.6f}" for x in fit.root_position[t])
        lines.append(root + " " + " ".join(f"{a:.6f}" for a in euler[t]))
    return "\n".join(lines) + "\n"


def save_text(path: str | Path, text: str) -> None:
    with atomic_path(Path(path)) as tmp:
        Path(tmp).write_text(text)


def write_bvh(path: str | Path, motion: ExportMotion, units: str = "m",
              pose_from: str = "joints") -> SkeletonFit:
    """Write ``path`` atomically; returns the fit (for its residual)."""
    fit = motion.fit(pose_from)
    save_text(path, bvh_text(motion, fit, units))
    return fit
