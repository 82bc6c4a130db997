"""Exchange formats: motion out of the toolkit as SMPL-X parameters (AMASS layout), BVH and glTF.

``motion.py`` reads what is exported (a ``sarah-generate`` motion.npz, or a person of a shard
sequence) into one ``ExportMotion``; ``kinematics.py`` turns global rotations into the local ones
of the SMPL-X tree and back, and fits a rigid body to the motion's joints (``ExportMotion.fit``,
once per motion); ``smplx_params.py``, ``bvh.py`` and ``gltf.py`` write that body. It is always a
valid rigid body; the fit reports how far its joints are from the motion's own.
"""

from .bvh import write_bvh
from .gltf import write_glb
from .kinematics import (SkeletonFit, fit_skeleton, forward_kinematics, local_rotations,
                         rest_offsets_from_motion)
from .motion import BodyShape, ExportError, ExportMotion, motion_from_file, motion_from_shards
from .smplx_params import smplx_parameters, write_smplx

__all__ = ["BodyShape", "ExportError", "ExportMotion", "fit_skeleton", "forward_kinematics",
           "local_rotations", "motion_from_file", "rest_offsets_from_motion", "SkeletonFit", "motion_from_shards", "smplx_parameters",
           "write_bvh", "write_glb", "write_smplx"]
